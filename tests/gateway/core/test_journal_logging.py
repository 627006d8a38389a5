"""Under systemd the daemon's warnings reach the journal as warnings (PRIORITY=4), not info.

journald files a plain stderr line as priority 6; a "<N>" prefix sets it. The prefix is only
written when stderr really is the journal ($JOURNAL_STREAM names stderr's device and inode),
so a terminal or a pipe sees the usual lines. `make system-test` checks the real journal.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from pathlib import Path

from gateway.core.journal_logging import JournalFormatter, stderr_is_journal


def _record(level: int, msg: str) -> logging.LogRecord:
    return logging.LogRecord("gateway.x", level, __file__, 1, msg, None, None)


def test_each_level_gets_its_syslog_priority() -> None:
    f = JournalFormatter()
    assert f.format(_record(logging.WARNING, "rs485: radar not answering")) == (
        "<4>WARNING gateway.x: rs485: radar not answering")
    assert f.format(_record(logging.ERROR, "e")).startswith("<3>")
    assert f.format(_record(logging.CRITICAL, "c")).startswith("<2>")
    assert f.format(_record(logging.INFO, "i")).startswith("<6>")


def test_every_line_of_a_multi_line_message_keeps_the_priority() -> None:
    lines = JournalFormatter().format(_record(logging.ERROR, "boom\nTraceback\n  x")).split("\n")
    assert lines == ["<3>ERROR gateway.x: boom", "<3>Traceback", "<3>  x"]


def test_only_a_stderr_that_is_the_journal_stream_counts(tmp_path: Path) -> None:
    with (tmp_path / "stream").open("w") as stream:
        st = os.fstat(stream.fileno())
        assert stderr_is_journal({"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}, stream.fileno())
        assert not stderr_is_journal({"JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino + 1}"},
                                     stream.fileno())
        assert not stderr_is_journal({}, stream.fileno())


def test_the_cli_prefixes_only_under_the_journal(tmp_path: Path) -> None:
    code = ("import logging; from gateway.app.cli import setup_logging; setup_logging(False); "
            "logging.getLogger('gateway.t').warning('hopper low')")
    err = tmp_path / "stderr"
    for journal in (False, True):
        with err.open("w") as stream:
            env = dict(os.environ)
            st = os.fstat(stream.fileno())
            env.pop("JOURNAL_STREAM", None)
            if journal:
                env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
            subprocess.run([sys.executable, "-c", code], stderr=stream, env=env, check=True,
                           timeout=60)
        line = err.read_text().strip()
        if journal:
            assert line == "<4>WARNING gateway.t: hopper low"
        else:
            assert line.endswith(" WARNING gateway.t: hopper low") and not line.startswith("<")

"""Log lines the journal files under the right priority (PRIORITY=, `journalctl -p warning`).

Under systemd, stderr goes to the journal, and every line of plain text lands as priority 6
(info): the alarms and device faults logged as warnings would not show in
`journalctl -u sowgate -p warning`. journald reads a "<N>" prefix on a line as its syslog
priority (sd-daemon(3), SyslogLevelPrefix= is on by default), so when stderr is the journal
each line gets its level's prefix. On a terminal nothing changes.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Mapping

# syslog priorities of the logging levels
SYSLOG_PRIORITY = {logging.DEBUG: 7, logging.INFO: 6, logging.WARNING: 4, logging.ERROR: 3,
                   logging.CRITICAL: 2}


def stderr_is_journal(env: Mapping[str, str] = os.environ, fd: int = 2) -> bool:
    """True when systemd connected stderr to the journal ($JOURNAL_STREAM = its dev:inode)."""
    try:
        st = os.fstat(fd)
    except OSError:
        return False
    return env.get("JOURNAL_STREAM", "") == f"{st.st_dev}:{st.st_ino}"


class JournalFormatter(logging.Formatter):
    """Each line prefixed with its record's syslog priority; a traceback's continuation lines
    carry the same one. No time stamp: the journal has its own."""

    def __init__(self) -> None:
        super().__init__("%(levelname)s %(name)s: %(message)s")

    def format(self, record: logging.LogRecord) -> str:
        prefix = f"<{SYSLOG_PRIORITY.get(record.levelno, 6)}>"
        return "\n".join(prefix + line for line in super().format(record).splitlines())


def use_journal_priorities() -> None:
    """After logging.basicConfig: under systemd, the root handlers write priority prefixes."""
    if stderr_is_journal():
        for handler in logging.getLogger().handlers:
            handler.setFormatter(JournalFormatter())

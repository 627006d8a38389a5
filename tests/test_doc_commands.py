"""Every command the docs show is checked against the real program, so the docs cannot drift.

Which commands: in README.md, systemd/README.md and docs/*.md, every line of a fenced or
indented code block that starts with ``sowgate``, ``make`` or ``python -m``; the first column
of every table (README's "Command line"); and every inline ``make X`` / ``python -m X``.

How far each is taken (running them all for real would take the length of ``make bench``):

* ``sowgate ...``: parsed by the real argparse parser (``gateway.app.cli.build_parser``), in
  every variant the notation allows (``a|b`` alternatives each, ``[optional]`` parts included,
  placeholders such as FILE, DIR, NAME given a value). ``--version``, ``COMMAND --help`` and
  ``check-config`` (against each example config) really run. A command written with ``…``
  for "the other options" has each option it names checked against its sub-command.
* ``make TARGET``: ``make -n TARGET`` (the target exists and its recipe expands).
* ``python -m MODULE [ARGS]``: the module exists; ``python -m benchmarks NAME`` names a
  benchmark the runner knows.
The real runs of the long ones are elsewhere: the demo's printed export and report commands in
tests/simulator/test_demo.py, the examples in tests/test_examples.py.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import itertools
import re
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest

from gateway.app.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", ROOT / "systemd" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
COMMAND_START = re.compile(r"^(sowgate|make|python3? -m)\s")
EXAMPLE_CONFIG = ROOT / "examples" / "sowgate.toml"

# what a placeholder in the docs stands for, when checked
PLACEHOLDERS = {
    "FILE": "field.txt", "DIR": "state", "S": "5", "T": "2026-04-01T08:00:00Z", "N": "1",
    "NAME": "lot-2", "GRAMS": "45", "HOST:PORT": "127.0.0.1:8080",
}


@dataclass(frozen=True)
class DocCommand:
    where: str  # file:line
    text: str

    def __str__(self) -> str:
        return f"{self.where}: {self.text}"


def _code_lines(lines: list[str]) -> list[tuple[int, str]]:
    """(line number, text) of every line inside a fenced or an indented code block."""
    out: list[tuple[int, str]] = []
    fenced = indented = False
    previous_blank = True
    for number, line in enumerate(lines, 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif fenced:
            out.append((number, line.strip()))
        elif line.startswith("    ") and (indented or previous_blank):
            indented = True
            out.append((number, line.strip()))
        else:
            indented = False
        previous_blank = not line.strip()
    return out


def _strip_comment(text: str) -> str:
    return re.split(r"\s+#\s", text, maxsplit=1)[0].strip()


def doc_commands() -> list[DocCommand]:
    found: list[DocCommand] = []
    for doc in DOCS:
        name = doc.relative_to(ROOT)
        lines = doc.read_text(encoding="utf-8").splitlines()
        for number, line in _code_lines(lines):
            # a shell line may chain commands: `sowgate check-config F && systemctl restart …`
            for text in re.split(r"\s+(?:&&|\|\||;|\|)\s+", _strip_comment(line)):
                text = re.sub(r"^sudo\s+", "", text.strip())
                if COMMAND_START.match(text):
                    found.append(DocCommand(f"{name}:{number}", text))
        for number, line in enumerate(lines, 1):
            if line.startswith("|"):  # a table row: the commands in its first column
                first = line.split(" | ")[0]
                for span in re.findall(r"`([^`]+)`", first):
                    if span.startswith("sowgate"):
                        found.append(DocCommand(f"{name}:{number}", span.replace("\\|", "|")))
            for span in re.findall(r"`((?:make|python -m) [^`]+)`", line):
                found.append(DocCommand(f"{name}:{number}", span))
    return sorted(set(found), key=lambda c: (c.where, c.text))


COMMANDS = doc_commands()


def _ids(commands: list[DocCommand]) -> list[str]:
    return [str(c) for c in commands]


def test_the_docs_show_commands_of_every_kind() -> None:
    """The extraction itself: a change to the docs' notation must not make it find nothing."""
    texts = [c.text for c in COMMANDS]
    assert any(t.startswith("sowgate calibrate positions --survey") for t in texts)
    assert any(t.startswith("make ") for t in texts)
    assert any(t.startswith("python -m benchmarks") for t in texts)
    assert len([t for t in texts if t.startswith("sowgate")]) >= 20


# ---- sowgate --------------------------------------------------------------------------------

def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _alternatives(token: str) -> list[str]:
    """``a|b`` -> [a, b]; ``FILE.html|.pdf`` -> [FILE.html, FILE.pdf]."""
    if "|" not in token:
        return [token]
    first, *rest = token.split("|")
    stem = first.rsplit(".", 1)[0] if "." in first else first
    return [first, *(stem + alt if alt.startswith(".") else alt for alt in rest)]


def _variants(text: str) -> list[list[str]]:
    """The argv lists a documented command line stands for (after ``sowgate``)."""
    tokens = [t.strip("[]") for t in shlex.split(text)[1:]]
    tokens = [t for t in tokens if t]
    choices = [_alternatives(t) for t in tokens]
    return [list(v) for v in itertools.product(*choices)]


def _fill(argv: list[str]) -> list[str]:
    out: list[str] = []
    for i, token in enumerate(argv):
        if token in ("…", "...") and i > 0 and argv[i - 1].startswith("--"):
            out.append("1")  # "--mass …": some values
        elif token in PLACEHOLDERS:
            out.append(PLACEHOLDERS[token])
        elif re.fullmatch(r"FILE\.\w+", token):
            out.append("field" + token[4:])
        else:
            out.append(token)
    return out


def _parse(argv: list[str]) -> int:
    """The exit status argparse gives ``argv`` (0: accepted; --help and --version print)."""
    sink = io.StringIO()
    with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
        try:
            build_parser().parse_args(argv)
        except SystemExit as exc:
            return int(exc.code or 0)
    return 0


def _options_known(argv: list[str]) -> list[str]:
    """For a command written with ``…``: the options it names that its sub-command lacks."""
    parser = build_parser()
    known: set[str] = set()
    for token in argv:
        known |= {s for a in parser._actions for s in a.option_strings}
        sub = _subcommands(parser)
        if token in sub:
            parser = sub[token]
    known |= {s for a in parser._actions for s in a.option_strings}
    return [t for t in argv if t.startswith("--") and t not in known]


SOWGATE = [c for c in COMMANDS if c.text.startswith("sowgate")]


@pytest.mark.parametrize("command", SOWGATE, ids=_ids(SOWGATE))
def test_each_sowgate_command_in_the_docs_is_accepted_by_the_cli(command: DocCommand) -> None:
    for argv in _variants(command.text):
        if "COMMAND" in argv:  # "sowgate COMMAND --help": every command's help really runs
            for name in _subcommands(build_parser()):
                filled = [name if t == "COMMAND" else t for t in argv]
                assert _parse(filled) == 0, f"{command}: {filled}"
            continue
        bare_ellipsis = any(t in ("…", "...") and (i == 0 or not argv[i - 1].startswith("--"))
                            for i, t in enumerate(argv))
        if bare_ellipsis:  # "rotation … --seed-lot NAME": the options it names must exist
            unknown = _options_known(argv)
            assert unknown == [], f"{command}: unknown options {unknown}"
            continue
        filled = _fill(argv)
        assert _parse(filled) == 0, f"{command}: argparse refuses {filled}"


CHECK_CONFIG = [c for c in SOWGATE if c.text.startswith("sowgate check-config")]


@pytest.mark.parametrize("command", CHECK_CONFIG, ids=_ids(CHECK_CONFIG))
def test_the_documented_check_config_runs_on_the_example(
    command: DocCommand, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path / "state"))
    (argv,) = _variants(command.text)
    argv = [str(EXAMPLE_CONFIG) if t.endswith(".toml") or t == "FILE" else t for t in argv]
    assert main(argv) == 0, capsys.readouterr().err
    assert ": ok (machine " in capsys.readouterr().out


def test_the_version_the_docs_show_runs(capsys: pytest.CaptureFixture[str]) -> None:
    assert any(c.text == "sowgate --version" for c in SOWGATE)
    with pytest.raises(SystemExit) as done:
        main(["--version"])
    assert done.value.code == 0 and capsys.readouterr().out.startswith("sowgate ")


def test_calibrate_takes_config_and_state_dir_after_the_sub_command_too() -> None:
    """As docs/positioning.md writes it, and as before the sub-command."""
    after = build_parser().parse_args(["calibrate", "positions", "--survey", "s.csv",
                                       "--config", "f.toml", "--state-dir", "d"])
    before = build_parser().parse_args(["calibrate", "--config", "f.toml", "--state-dir", "d",
                                        "positions", "--survey", "s.csv"])
    neither = build_parser().parse_args(["calibrate", "show"])
    assert (after.config, after.state_dir) == (before.config, before.state_dir) == ("f.toml", "d")
    assert getattr(neither, "config", None) is None and neither.state_dir is None


# ---- make and python -m ---------------------------------------------------------------------

MAKE = [c for c in COMMANDS if c.text.startswith("make")]


@pytest.mark.parametrize("command", MAKE, ids=_ids(MAKE))
def test_each_make_target_in_the_docs_exists(command: DocCommand) -> None:
    targets = [t for t in shlex.split(command.text)[1:] if not t.startswith("-") and "=" not in t]
    targets = [t for t in targets if t not in ("&", "|")][:1]
    proc = subprocess.run(["make", "-n", *targets], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0, f"{command}: {proc.stderr}"


PYTHON_M = [c for c in COMMANDS if re.match(r"python3? -m", c.text)]


@pytest.mark.parametrize("command", PYTHON_M, ids=_ids(PYTHON_M))
def test_each_python_module_in_the_docs_exists(command: DocCommand) -> None:
    _python, _m, module, *args = shlex.split(command.text)
    assert importlib.util.find_spec(module) is not None, f"{command}: no module {module}"
    if module == "benchmarks":
        from benchmarks.__main__ import BENCHMARKS

        names = {m for m, _ in BENCHMARKS}
        asked = [a for a in args if not a.startswith("-") and a.isidentifier() and a.islower()]
        assert set(asked) <= names, f"{command}: unknown benchmarks {set(asked) - names}"

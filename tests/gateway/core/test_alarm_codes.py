"""The alarm registry is complete, and docs/mqtt.md's alarm table is the one generated from it."""

from __future__ import annotations

import ast
import logging
import re
from pathlib import Path

import pytest

from gateway.core import alarm_codes
from gateway.core.alarm_codes import REGISTRY, lookup, markdown_table, with_table
from gateway.core.alarms import AlarmBoard

ROOT = Path(__file__).resolve().parents[3]
GATEWAY = ROOT / "gateway"
# calls whose first argument is an alarm code: alarms.raise_/set, and recording_health's _set
RAISING_METHODS = {"raise_", "set", "_set"}


def _is_alarm_call(node: ast.Call) -> bool:
    func = node.func
    if not isinstance(func, ast.Attribute) or func.attr not in RAISING_METHODS or not node.args:
        return False
    receiver = ast.unparse(func.value)
    return receiver.endswith("alarms") or func.attr == "_set"


def _code_shapes(expr: ast.expr, scope: ast.AST, module: ast.Module) -> list[str]:
    """The codes (as regular expressions) an expression can evaluate to."""
    if isinstance(expr, ast.Constant) and isinstance(expr.value, str):
        return [re.escape(expr.value)]
    if isinstance(expr, ast.JoinedStr):
        return [
            "".join(
                re.escape(v.value) if isinstance(v, ast.Constant) else "[A-Za-z0-9_.<>-]+"
                for v in expr.values
            )
        ]
    if isinstance(expr, ast.IfExp):
        return _code_shapes(expr.body, scope, module) + _code_shapes(expr.orelse, scope, module)
    if isinstance(expr, ast.Name):
        for where in (scope, module):
            for node in ast.walk(where):
                if (
                    isinstance(node, ast.Assign)
                    and any(isinstance(t, ast.Name) and t.id == expr.id for t in node.targets)
                ):
                    return _code_shapes(node.value, scope, module)
    raise AssertionError(f"cannot tell which alarm code {ast.unparse(expr)!r} is")


def raised_codes() -> dict[str, str]:
    """Every alarm code shape raised in gateway/, mapped to where it is raised."""
    found: dict[str, str] = {}
    for path in sorted(GATEWAY.rglob("*.py")):
        if path.name == "alarms.py":
            continue  # the board itself: raise_ forwards its argument
        module = ast.parse(path.read_text(encoding="utf-8"))
        for func in ast.walk(module):
            if not isinstance(func, ast.FunctionDef | ast.AsyncFunctionDef):
                continue
            for node in ast.walk(func):
                if isinstance(node, ast.Call) and _is_alarm_call(node):
                    if func.name == "_set" and isinstance(node.args[0], ast.Name):
                        continue  # recording_health._set forwarding its own argument
                    for shape in _code_shapes(node.args[0], func, module):
                        found[shape] = f"{path.relative_to(ROOT)}:{node.lineno}"
    return found


def test_the_scan_finds_the_codes_raised_in_all_the_places_that_raise_them() -> None:
    shapes = raised_codes()
    for code in ("speed.lost", "records.lost", "pwm.no_watchdog", "mqtt.backlog",
                 "rate.outside_calibration", "gnss.heading_invalid", "channel.can_disabled"):
        assert any(re.fullmatch(s, code) for s in shapes), code
    assert any(re.fullmatch(s, "radar.implausible") for s in shapes)  # through a variable


def test_every_code_the_gateway_raises_is_in_the_registry() -> None:
    missing = [
        f"{shape} ({where})"
        for shape, where in raised_codes().items()
        if not any(re.fullmatch(shape, entry.code) or entry.matches(shape) for entry in REGISTRY)
    ]
    assert missing == []


def test_every_registered_code_is_raised_somewhere() -> None:
    shapes = raised_codes()
    unused = [
        entry.code for entry in REGISTRY
        if not any(re.fullmatch(s, entry.code) for s in shapes)
    ]
    assert unused == []


def test_families_match_their_members_only() -> None:
    assert lookup("channel.deep.off_target") is not None
    assert lookup("isobus.implausible") is not None
    assert lookup("hitch.lost") is not None
    assert lookup("channel.deep.exploded") is None
    assert lookup("speed.lost.again") is None


def test_docs_alarm_table_is_the_generated_one() -> None:
    doc = (ROOT / "docs" / "mqtt.md").read_text(encoding="utf-8")
    assert with_table(doc) == doc, "run: python -m gateway.core.alarm_codes --write docs/mqtt.md"
    assert markdown_table() in doc


def test_the_write_command_rewrites_only_the_table(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text(
        f"intro\n{alarm_codes.BEGIN_MARKER}\n| stale |\n{alarm_codes.END_MARKER}\nafter\n"
    )
    assert alarm_codes.main(["--write", str(page)]) == 0
    text = page.read_text()
    assert text.startswith("intro\n") and text.endswith(f"{alarm_codes.END_MARKER}\nafter\n")
    assert "| stale |" not in text and "`records.store_failed`" in text


def test_the_board_logs_an_unregistered_code(caplog: pytest.LogCaptureFixture) -> None:
    board = AlarmBoard()
    with caplog.at_level(logging.ERROR, logger="gateway.core.alarms"):
        board.raise_("speed.lost", "registered")
        assert caplog.records == []
        board.raise_("made.up", "not registered")
    assert "made.up" in caplog.text

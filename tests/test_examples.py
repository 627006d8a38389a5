"""The example configs show every table of the config, and each passes ``check-config``."""

from __future__ import annotations

import tomllib
import typing
from pathlib import Path

import pytest
from pydantic import BaseModel

from gateway.app.cli import main
from gateway.config import Settings

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = sorted((ROOT / "examples").glob("*.toml"))


def _table_paths(model: type[BaseModel], prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every table of the config: each section, and tables nested in one (``mqtt.tls``)."""
    paths = []
    for name, field in model.model_fields.items():
        kind = field.annotation
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        if typing.get_origin(kind) is list and args:
            kind = args[0]  # [[channel]]
        elif len(args) == 1 and typing.get_origin(kind) is not dict:
            kind = args[0]  # tls: TlsSection | None
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            key = field.alias or name
            paths.append((*prefix, key))
            paths += _table_paths(kind, (*prefix, key))
    return paths


def _has_table(doc: dict[str, typing.Any], path: tuple[str, ...]) -> bool:
    node: typing.Any = doc
    for key in path:
        if isinstance(node, list):
            node = node[0] if node else {}
        if not isinstance(node, dict) or key not in node:
            return False
        node = node[key]
    return True


def test_the_walk_finds_nested_and_array_tables() -> None:
    paths = _table_paths(Settings)
    assert ("mqtt", "tls") in paths and ("channel",) in paths and ("store",) in paths


def test_every_table_of_the_config_is_in_an_example() -> None:
    docs = [tomllib.loads(p.read_text(encoding="utf-8")) for p in EXAMPLES]
    missing = [
        ".".join(path) for path in _table_paths(Settings)
        if not any(_has_table(doc, path) for doc in docs)
    ]
    assert missing == []


@pytest.mark.parametrize("example", EXAMPLES, ids=lambda p: p.name)
def test_check_config_accepts_the_example(
    example: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # the examples name their files relative to themselves: checked from anywhere
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("SOWGATE_STATE_DIR", str(tmp_path / "state"))
    code = main(["check-config", str(example)])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert ": ok (machine " in out.out

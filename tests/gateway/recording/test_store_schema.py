"""The store carries its schema version: a store a newer sowgate wrote is refused, never read.

After an upgrade and ``install.sh --rollback`` the older daemon finds the newer version's store;
it must stop with a config error (exit 78: systemd does not restart it in a loop) that says
what to do, and leave the file exactly as it was.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest
import tomli_w

from gateway.recording.store import RecordStore
from gateway.recording.store.version import SCHEMA_VERSION, StoreTooNewError
from tests.helpers import run_sowgate, sowgate_env


def _user_version(path: Path) -> int:
    with sqlite3.connect(path) as db:
        return int(db.execute("PRAGMA user_version").fetchone()[0])


def _store_from_the_future(path: Path) -> Path:
    """A store as a later version might leave it: a version above ours, a table we don't know."""
    store = RecordStore(path, "seeder-01")
    store.close()
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE seeds_v2 (id INTEGER PRIMARY KEY)")
        db.execute(f"PRAGMA user_version = {SCHEMA_VERSION + 1}")
    return path


def test_a_new_store_is_stamped_with_this_schema_version(tmp_path: Path) -> None:
    RecordStore(tmp_path / "records.sqlite3", "seeder-01").close()
    assert _user_version(tmp_path / "records.sqlite3") == SCHEMA_VERSION


def test_a_store_from_before_the_version_existed_is_migrated_and_stamped(tmp_path: Path) -> None:
    path = tmp_path / "records.sqlite3"
    RecordStore(path, "seeder-01").close()
    with sqlite3.connect(path) as db:
        db.execute("PRAGMA user_version = 0")
    RecordStore(path, "seeder-01").close()
    assert _user_version(path) == SCHEMA_VERSION


@pytest.mark.parametrize("readonly", [False, True], ids=["daemon", "export"])
def test_a_store_written_by_a_newer_version_is_refused_untouched(
    tmp_path: Path, readonly: bool
) -> None:
    path = _store_from_the_future(tmp_path / "records.sqlite3")
    before = path.read_bytes()
    with pytest.raises(StoreTooNewError) as caught:
        if readonly:
            RecordStore.open_readonly(path, "seeder-01")
        else:
            RecordStore(path, "seeder-01")
    (problem,) = caught.value.problems
    assert problem.startswith(f"store.path: the record store {path} has schema version "
                              f"{SCHEMA_VERSION + 1}, written by a newer sowgate")
    assert "install.sh --rollback" in problem
    assert path.read_bytes() == before
    assert _user_version(path) == SCHEMA_VERSION + 1


def test_the_daemon_exits_78_on_a_store_from_a_newer_version(tmp_path: Path) -> None:
    store = _store_from_the_future(tmp_path / "records.sqlite3")
    cfg = tmp_path / "s.toml"
    cfg.write_text(tomli_w.dumps({"hmi": {"enabled": False}, "mqtt": {"port": 1},
                                  "store": {"path": str(store)}}))
    proc = run_sowgate("run", "--config", str(cfg), timeout=30, console_script=True,
                       env=sowgate_env(env={"SOWGATE_STATE_DIR": str(tmp_path / "st")},
                                       clean=True))
    assert proc.returncode == 78, proc.stderr
    assert f"has schema version {SCHEMA_VERSION + 1}, written by a newer sowgate" in proc.stderr
    assert "Traceback" not in proc.stderr

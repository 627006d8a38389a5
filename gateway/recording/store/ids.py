"""Ids that are never handed out twice, even when a power cut takes the store's last writes.

SQLite alone cannot promise that: its high-water mark (``sqlite_sequence``) lives in the same
file and the same WAL as the rows, so a lost WAL or an SD card whose cache lied about the last
seconds takes the mark back with the rows, and the next start would give the ids of records
already published to other seeds (the dashboard then drops the new ones as duplicates).

So the ids are reserved in a small file kept apart from the store (``<store>.ids``), in
blocks of ``ID_BLOCK``: before a commit makes an id visible (and with it publishable) that
leaves less than half a block reserved, the reservation is moved ``ID_BLOCK`` past it and
written durably (temp file, fsync, rename, fsync of the directory). Renewing at half a block
keeps at least ``ID_BLOCK / 2`` ids (5 s of a 48-row planter at 2 000 seeds/s) between what
was published and the last durable reservation, so even a card that loses its last seconds of
writes, the reservation's included, cannot hand out a published id again. At start the next id is
``max(store's highest id, reserved end) + 1``: after a stop that did not close the store
(SIGKILL, power cut) the ids jump by at most a block, and the ids skipped were never
published. A clean close lowers the reservation to the last committed id, so an ordinary
restart continues without a gap. Two fsyncs per half block (about 5 s of a 48-row planter) are the
whole cost.

The file is JSON (``{"seeds": 12345, "alarms": 17}``); an unreadable one is logged and taken
as absent: the store's own high-water mark then stands alone, as before this file existed.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

ID_BLOCK = 20_000  # ids reserved ahead; renewed when half of it is left


def reservation_path(store_path: Path) -> Path:
    return store_path.with_name(store_path.name + ".ids")


def write_durably(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that after a power cut it holds either the old content
    or the new, never a torn or empty file: temp file, fsync, rename, fsync the directory."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
    try:
        os.write(fd, data)
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


class IdReservation:
    """The reserved end of each table's id sequence, kept in ``path`` (see module docstring).

    Not thread-safe by itself: the store calls it from the thread that commits.
    """

    def __init__(self, path: Path, block: int = ID_BLOCK) -> None:
        self.path = path
        self.block = block
        self.reserved: dict[str, int] = self._load()
        self.writes = 0  # durable writes made (for tests and the log)

    def _load(self) -> dict[str, int]:
        try:
            raw = self.path.read_bytes()
        except FileNotFoundError:
            return {}
        except OSError as exc:
            log.error("id reservation %s unreadable (%s): ids continue from the store's own "
                      "high-water mark", self.path, exc)
            return {}
        try:
            doc = json.loads(raw)
            return {str(k): int(v) for k, v in doc.items() if int(v) >= 0}
        except (ValueError, TypeError, AttributeError) as exc:
            log.error("id reservation %s is not valid (%s): ids continue from the store's own "
                      "high-water mark", self.path, exc)
            return {}

    def end(self, table: str) -> int:
        """The highest id that may have been handed out and published for ``table``."""
        return self.reserved.get(table, 0)

    def next_id(self, table: str, store_max_id: int) -> int:
        """The first id of this run: above the store's rows and above every reservation."""
        return max(store_max_id, self.end(table)) + 1

    def cover(self, table: str, last_id: int) -> None:
        """Make sure ``last_id`` is reserved durably before it is committed (OSError if the
        reservation cannot be written: the caller must not commit then)."""
        if last_id <= self.end(table) - self.block // 2:
            return
        self._write({**self.reserved, table: last_id + self.block})

    def lower_to(self, ends: dict[str, int]) -> None:
        """At a clean close: the reservation ends at the last committed ids, so the next start
        continues without a gap. Never raises (a failed write leaves the higher, safe, end)."""
        new = {t: min(self.end(t), e) for t, e in ends.items()}
        if new == {t: self.end(t) for t in ends}:
            return
        with contextlib.suppress(OSError):
            self._write({**self.reserved, **new})

    def raise_to(self, ends: dict[str, int]) -> None:
        """Remember ids known to be used (a store moved aside): never below them again."""
        if all(e <= self.end(t) for t, e in ends.items()):
            return
        self._write({**self.reserved, **{t: max(self.end(t), e) for t, e in ends.items()}})

    def _write(self, reserved: dict[str, int]) -> None:
        write_durably(self.path, json.dumps(reserved, sort_keys=True).encode())
        self.reserved = reserved
        self.writes += 1

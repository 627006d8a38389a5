"""The TJC touchscreen as a scriptable peer on the far end of a pty.

Tests and the demo "press buttons" (the exact 8-byte frames the real screen's ``printh`` sends)
and read back what the daemon displayed, parsed from its ``obj.txt="…"`` instructions. With
``known_objects`` the peer behaves like a page that lacks other objects: it answers writes to
them with the Nextion "invalid variable" reply (``1A FF FF FF``), as a stock screen with
``bkcmd=2`` does.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import os
import time
from collections.abc import Callable, Iterable

from drivers.tasks import StartClose
from protocol.hmi import (
    INSTRUCTION_END,
    AckAlarm,
    EmptySeed,
    HmiCommand,
    RotationTest,
    SeedLevelMonitoring,
    SelectCrop,
    SelectSeedLot,
    StartWork,
    StopWork,
    ZeroTilt,
    encode_frame,
    parse_instruction,
)
from simulator.pty_link import PtyPair

# Bytes held while waiting for an FF FF FF terminator; a daemon writing junk cannot grow it.
MAX_PENDING_INSTRUCTION = 4096
KEEP_INSTRUCTIONS = 1000  # most recent raw instructions kept for inspection
INVALID_VARIABLE_REPLY = b"\x1a" + INSTRUCTION_END


class HmiPeer(StartClose):
    """One simulated screen. Create it inside a running event loop; ``await close()`` it."""

    def __init__(
        self,
        *,
        encoding: str = "ascii",
        link_path: str | os.PathLike[str] | None = None,
        known_objects: Iterable[str] | None = None,
    ) -> None:
        self.encoding = encoding
        self.known_objects = None if known_objects is None else frozenset(known_objects)
        self.texts: dict[str, str] = {}
        self.values: dict[str, int] = {}
        self.instructions: collections.deque[bytes] = collections.deque(maxlen=KEEP_INSTRUCTIONS)
        self.bytes_received = 0
        self._loop = asyncio.get_running_loop()
        self._pty = PtyPair(link_path)
        self._pending = bytearray()
        self._outbox = bytearray()
        self._changed = asyncio.Event()
        self._loop.add_reader(self._pty.master_fd, self._on_readable)

    @property
    def device_path(self) -> str:
        """What the daemon opens (the symlink if ``link_path`` was given)."""
        return self._pty.device_path

    @property
    def closed(self) -> bool:
        return self._pty.closed

    # -- the screen's buttons ------------------------------------------------------------------

    def press(self, command: HmiCommand) -> None:
        self.send_raw(encode_frame(command))

    def press_start(self) -> None:
        self.press(StartWork())

    def press_stop(self) -> None:
        self.press(StopWork())

    def select(self, crop_code: int, rate_kg_ha: float) -> None:
        self.press(SelectCrop(crop_code, rate_kg_ha))

    def empty(self) -> None:
        self.press(EmptySeed())

    def seed_level(self, enabled: bool) -> None:
        self.press(SeedLevelMonitoring(enabled))

    def acknowledge(self) -> None:
        self.press(AckAlarm())

    def zero_tilt(self) -> None:
        self.press(ZeroTilt())

    def select_seed_lot(self, crop_code: int, lot_number: int) -> None:
        self.press(SelectSeedLot(crop_code, lot_number))

    def rotation_test(self, action: str, value: float = 0.0) -> None:
        self.press(RotationTest(action, value))

    def send_raw(self, data: bytes) -> None:
        """Put bytes on the wire as they are (fault injection: garbage, split frames)."""
        if self.closed:
            raise OSError(f"HMI peer on {self.device_path} is closed")
        self._outbox += data
        self._on_writable()

    # -- what the daemon displayed ------------------------------------------------------------

    async def wait_text(
        self,
        obj: str,
        predicate: Callable[[str], bool] | None = None,
        timeout: float = 5.0,  # noqa: ASYNC109 - the brief's test-facing API
    ) -> str:
        """Wait until ``obj`` shows a text satisfying ``predicate`` (any text if None)."""
        deadline = time.monotonic() + timeout
        while True:
            text = self.texts.get(obj)
            if text is not None and (predicate is None or predicate(text)):
                return text
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError(
                    f"screen object {obj!r} shows {text!r} after {timeout} s; all: {self.texts}"
                )
            changed = self._changed
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(changed.wait(), remaining)

    # -- plumbing ------------------------------------------------------------------------------

    def _on_readable(self) -> None:
        try:
            data = os.read(self._pty.master_fd, 4096)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            return  # the device side is held open by PtyPair, so this is transient
        self.bytes_received += len(data)
        self._pending += data
        while (end := self._pending.find(INSTRUCTION_END)) >= 0:
            instruction = bytes(self._pending[:end])
            del self._pending[: end + len(INSTRUCTION_END)]
            self._execute(instruction)
        if len(self._pending) > MAX_PENDING_INSTRUCTION:
            self._pending.clear()
        self._notify()

    def _execute(self, instruction: bytes) -> None:
        self.instructions.append(instruction)
        parsed = parse_instruction(instruction, self.encoding)
        if parsed is None:
            return
        obj, value = parsed
        if self.known_objects is not None and obj not in self.known_objects:
            self.send_raw(INVALID_VARIABLE_REPLY)
            return
        if isinstance(value, str):
            self.texts[obj] = value
        else:
            self.values[obj] = value

    def _notify(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    def _on_writable(self) -> None:
        try:
            written = os.write(self._pty.master_fd, self._outbox)
        except (BlockingIOError, InterruptedError):
            written = 0
        del self._outbox[:written]
        if self._outbox:
            self._loop.add_writer(self._pty.master_fd, self._on_writable)
        else:
            self._loop.remove_writer(self._pty.master_fd)

    def vanish(self) -> None:
        """Unplug: both pty ends close, the daemon's reads fail and ``device_path`` disappears.
        A new HmiPeer on the same ``link_path`` plugs a screen back in."""
        if self.closed:
            return
        fd = self._pty.master_fd
        self._loop.remove_reader(fd)
        self._loop.remove_writer(fd)
        self._pty.close()
        self._notify()

    async def close(self) -> None:
        self.vanish()

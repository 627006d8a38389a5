"""Rate-limited logging: a storm of one kind of bad input costs a few log lines, not thousands.

A touchscreen with a floating RX pin, a receiver at the wrong baud rate or a seed-tube module
sending noise produce the same complaint hundreds of times a second; logging each one filled
the journal (8 239 warnings in 150 s) and hid everything else. ``RateLimitedLog`` logs the
first occurrence of each *key* at once, then at most one line per key per ``interval_s``,
saying how many were held back: ``... (1 234 more in the last 10 s)``. The held-back ones go
to DEBUG, so nothing is lost for whoever turns that on.

The clock is injected so tests can step time instead of sleeping.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

DEFAULT_INTERVAL_S = 10.0


@dataclass
class _KeyState:
    logged_at: float  # when the last line for this key was written
    held_back: int = 0  # occurrences since then that were not written
    level: int = logging.WARNING
    msg: str = ""
    args: tuple[object, ...] = ()


class RateLimitedLog:
    """First occurrence per key logged, then at most one line per ``interval_s`` per key."""

    def __init__(
        self,
        logger: logging.Logger,
        interval_s: float = DEFAULT_INTERVAL_S,
        *,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if interval_s <= 0:
            raise ValueError(f"interval_s must be > 0, got {interval_s}")
        self.logger = logger
        self.interval_s = interval_s
        self._clock = clock
        self._keys: dict[str, _KeyState] = {}

    def warning(self, key: str, msg: str, *args: object) -> bool:
        """Log ``msg % args`` at WARNING unless ``key`` was logged less than an interval ago.

        Returns True if a line was written."""
        return self._log(logging.WARNING, key, msg, args)

    def error(self, key: str, msg: str, *args: object) -> bool:
        return self._log(logging.ERROR, key, msg, args)

    def log(self, level: int, key: str, msg: str, *args: object) -> bool:
        return self._log(level, key, msg, args)

    def _log(self, level: int, key: str, msg: str, args: tuple[object, ...]) -> bool:
        now = self._clock()
        state = self._keys.get(key)
        if state is not None and now - state.logged_at < self.interval_s:
            state.held_back += 1
            state.level, state.msg, state.args = level, msg, args
            self.logger.debug(msg, *args, stacklevel=3)
            return False
        if state is None:
            self._keys[key] = _KeyState(now)
            self.logger.log(level, msg, *args, stacklevel=3)
            return True
        self._write(state, now, level, msg, args, count_this=False)
        return True

    def _write(
        self,
        state: _KeyState,
        now: float,
        level: int,
        msg: str,
        args: tuple[object, ...],
        *,
        count_this: bool,
    ) -> None:
        held = state.held_back - (1 if count_this else 0)
        if held > 0:
            msg = f"{msg} (%d more in the last %.0f s)"
            args = (*args, held, now - state.logged_at)
        self.logger.log(level, msg, *args, stacklevel=4)
        state.logged_at, state.held_back = now, 0

    def flush(self) -> None:
        """Write what was held back for keys whose interval has passed, with the count.

        Without it a storm's tail is only reported when the same key next occurs, which may
        be never; the totals are in the daemon's periodic summary (gateway.app.rejected_input)
        either way, so calling this is for owners that want the tail in their own words."""
        now = self._clock()
        for state in self._keys.values():
            if state.held_back and now - state.logged_at >= self.interval_s:
                # the held-back message itself was one of them: write it, count the others
                self._write(state, now, state.level, state.msg, state.args, count_this=True)

    def reset(self, key: str) -> None:
        """Forget ``key``: its next occurrence is logged at once (e.g. after a reconnect)."""
        self._keys.pop(key, None)

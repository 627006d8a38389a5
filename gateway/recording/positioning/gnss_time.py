"""Which GNSS time stamps to believe: every epoch's UTC checked against the time line the
receiver has kept so far and against the host's monotonic clock.

Why: the position model puts each epoch on the host clock through its UTC stamp
(:class:`.clock.ClockMap`) and stamps every record from that mapping. One epoch stamped two
hours ahead used to move the mapping, stall the epoch history (every later, correct epoch
looked "old") and stamp records two hours in the future; a receiver whose time stepped back
an hour had every epoch ignored and every seed extrapolated; a receiver with the GPS week
rollover bug stamped records 2007. So each epoch is judged before it is used:

- **established mapping**: ``t_mono − gnss`` is the arrival delay; over the recent accepted
  epochs its minimum is the receiver's output latency (jitter only ever makes an epoch
  *later*). An epoch that would have arrived before its own stamp by more than
  :data:`TIME_TOLERANCE_S` is stamped in the future; one stamped before the newest accepted
  epoch (by more than the tolerance), or that would have waited :data:`LATE_MAX_S` in a
  buffer, is stamped in the past. Either is an **outlier**: rejected, not entering the epoch
  history, the mapping untouched, so the next good epoch is used as if nothing happened.
- **step**: :data:`STEP_CONFIRM_EPOCHS` outliers in a row that agree with each other (one
  new mapping, time advancing) are not outliers but the receiver's clock stepping (a restart,
  a new almanac): the mapping is re-established on them, with a log line and an alarm.
- **GPS week rollover**: a date before :data:`EARLIEST_PLAUSIBLE_UTC` (older than any field
  this software has sown, or any log it may replay) is a receiver counting weeks modulo
  1024; it is corrected by adding 1024 weeks until it is not, and alarmed (the firmware
  needs updating). True dates from then for 1024 weeks (to 2039) are told apart.
- **leap second**: an epoch at 23:59:60 (``GnssEpoch.leap_second``) continues the time line
  (it is one second after 23:59:59), and every later epoch is counted one second further on,
  so the mapping never sees a step. Records are stamped in POSIX time, which has no second
  60: a seed that landed inside the leap second is stamped 23:59:59.999999 (monotonic order
  kept), every later one in ordinary UTC (:meth:`GnssTimeGuard.posix_of`).

The guard works on plain numbers (``t_mono`` passed in, seconds since the epoch): no clock
of its own, no I/O, so every case is a unit test.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Final, Literal

# A stamp this far (s) from the established mapping is not arrival jitter. Jitter is tens of
# ms; a loaded host delays arrivals by up to a few hundred ms (later, never earlier).
TIME_TOLERANCE_S: Final = 1.0
# An epoch cannot have waited longer than this in the serial buffers: a stamp that old,
# though after the newest accepted one, is a stamp in the past (the receiver stepped back
# after a silence), not a late delivery.
LATE_MAX_S: Final = 10.0
# Outliers in a row that agree on one new mapping before it is taken as the receiver's
# clock having stepped (0.5 s at 10 Hz): two or three bad stamps stay outliers.
STEP_CONFIRM_EPOCHS: Final = 5
# Accepted epochs whose arrival delays define the mapping (10 s at 10 Hz, as ClockMap).
REFERENCE_WINDOW_EPOCHS: Final = 100
# GPS counts weeks in 10 bits: a receiver that does not know its era is 1024 weeks early.
GPS_WEEK_ROLLOVER_WEEKS: Final = 1024
GPS_WEEK_ROLLOVER_S: Final = GPS_WEEK_ROLLOVER_WEEKS * 7 * 86_400.0
# No epoch this software receives (or replays from a log) is older: earlier is a week
# rollover. After the 2019 rollover, and 1024 weeks of true dates from it reach 2039.
EARLIEST_PLAUSIBLE_UTC: Final = datetime(2020, 1, 1, tzinfo=UTC)
# Where a record landing inside a leap second is stamped: this much before the midnight.
LEAP_SECOND_STAMP_BEFORE_S: Final = 1e-6

Verdict = Literal["first", "ok", "repeat", "outlier", "step"]
USABLE: Final = frozenset({"first", "ok", "step"})


@dataclass(frozen=True, slots=True)
class TimeCheck:
    """The guard's judgement of one epoch."""

    verdict: Verdict
    # the epoch's time on the guard's continuous scale: POSIX seconds, week rollover
    # corrected, plus the leap seconds seen since start (what the position model uses)
    gnss_s: float
    # how far the stamp is from the established mapping (s, positive = ahead of it); for a
    # step, how far the new mapping is from the old one
    error_s: float = 0.0
    rollover_weeks: int = 0  # weeks added to correct a GPS week rollover
    leap_second: bool = False
    message: str | None = None  # worth a log line (the first outlier of a run, a step...)

    @property
    def usable(self) -> bool:
        return self.verdict in USABLE


@dataclass(slots=True)
class TimeEvents:
    """What the guard has seen, for alarms and state: counts and when (``t_mono``) last."""

    outliers: int = 0
    last_outlier_mono: float | None = None
    steps: int = 0
    last_step_mono: float | None = None
    last_step_s: float = 0.0
    rollover_epochs: int = 0
    last_rollover_mono: float | None = None
    rollover_weeks: int = 0
    leap_seconds: int = 0
    last_leap_mono: float | None = None


def correct_week_rollover(
    posix_s: float, earliest_s: float = EARLIEST_PLAUSIBLE_UTC.timestamp()
) -> tuple[float, int]:
    """``(corrected seconds, weeks added)``: 1024-week eras added to a date before
    ``earliest_s`` until it is not (0 weeks for a plausible date)."""
    if posix_s >= earliest_s:
        return posix_s, 0
    eras = math.ceil((earliest_s - posix_s) / GPS_WEEK_ROLLOVER_S)
    return posix_s + eras * GPS_WEEK_ROLLOVER_S, eras * GPS_WEEK_ROLLOVER_WEEKS


class GnssTimeGuard:
    """Judges each epoch's stamp (:meth:`judge`) and maps the continuous scale back to the
    POSIX time records are stamped in (:meth:`posix_of`)."""

    def __init__(
        self,
        *,
        tolerance_s: float = TIME_TOLERANCE_S,
        step_confirm_epochs: int = STEP_CONFIRM_EPOCHS,
        window: int = REFERENCE_WINDOW_EPOCHS,
        earliest_utc: datetime = EARLIEST_PLAUSIBLE_UTC,
    ) -> None:
        self.tolerance_s = tolerance_s
        self.step_confirm_epochs = step_confirm_epochs
        self._earliest_s = earliest_utc.timestamp()
        self._delays: deque[float] = deque(maxlen=window)  # t_mono − gnss of accepted epochs
        self._last_gnss: float | None = None
        # outliers in a row that may be a new time line: their smallest delay, count, newest
        self._cand_delay = 0.0
        self._cand_n = 0
        self._cand_last = -math.inf
        self._cand_saved: tuple[int, float | None] = (0, None)  # outlier events before it
        # leap seconds seen: (POSIX midnight after it, scale value at its start)
        self._leaps: list[tuple[float, float]] = []
        self.events = TimeEvents()

    # ------------------------------------------------------------ judging

    def judge(self, t_mono: float, posix_s: float, leap_second: bool = False) -> TimeCheck:
        """Judge the epoch stamped ``posix_s`` (for a leap second: 23:59:59 + the fraction,
        with ``leap_second``) that arrived at ``t_mono``."""
        posix_s, weeks = correct_week_rollover(posix_s, self._earliest_s)
        gnss = posix_s + self._leap_shift(posix_s) + (1.0 if leap_second else 0.0)
        message: str | None = None
        if weeks:
            ev = self.events
            if ev.rollover_weeks != weeks:
                message = (
                    f"GNSS receiver reports dates {weeks} weeks early (GPS week rollover): "
                    "corrected; update the receiver firmware"
                )
            ev.rollover_epochs += 1
            ev.last_rollover_mono, ev.rollover_weeks = t_mono, weeks
        delay = t_mono - gnss
        if not self._delays:
            return self._accept("first", t_mono, gnss, delay, weeks, leap_second, message)
        error = min(self._delays) - delay  # > 0: the stamp is ahead of the mapping
        last = self._last_gnss
        assert last is not None
        if error > self.tolerance_s:
            why = f"{error:.1f} s ahead of"
        elif gnss <= last:
            if last - gnss <= self.tolerance_s:  # a repeated or reordered epoch: not news
                return TimeCheck("repeat", gnss, error, weeks, leap_second, message)
            why = f"{last - gnss:.1f} s before the last epoch on"
        elif -error > LATE_MAX_S:
            why = f"{-error:.1f} s behind"
        else:
            return self._accept("ok", t_mono, gnss, delay, weeks, leap_second, message)
        return self._inconsistent(t_mono, gnss, delay, error, weeks, leap_second, why, message)

    def _inconsistent(
        self, t_mono: float, gnss: float, delay: float, error: float, weeks: int,
        leap_second: bool, why: str, message: str | None,
    ) -> TimeCheck:
        if self._cand_n and abs(delay - self._cand_delay) <= self.tolerance_s \
                and gnss > self._cand_last:
            self._cand_n += 1
            self._cand_delay = min(self._cand_delay, delay)
        else:
            self._cand_n, self._cand_delay = 1, delay
            self._cand_saved = (self.events.outliers, self.events.last_outlier_mono)
        self._cand_last = gnss
        if self._cand_n >= self.step_confirm_epochs:
            step = min(self._delays) - self._cand_delay
            self._delays.clear()
            self._delays.append(self._cand_delay)
            self._cand_n = 0
            self._last_gnss = gnss
            ev = self.events
            ev.steps += 1
            ev.last_step_mono, ev.last_step_s = t_mono, step
            # the epochs that confirmed the step were the new time line, not outliers
            ev.outliers, ev.last_outlier_mono = self._cand_saved
            return TimeCheck(
                "step", gnss, step, weeks, leap_second,
                f"GNSS time stepped by {step:+.1f} s ({self.step_confirm_epochs} epochs in a "
                "row agree): positions continue on the receiver's new time line",
            )
        self.events.outliers += 1
        self.events.last_outlier_mono = t_mono
        if self._cand_n == 1:
            message = (
                f"GNSS epoch stamped {datetime.fromtimestamp(gnss, UTC):%Y-%m-%d %H:%M:%S.%f}"
                f" rejected: {why} the receiver's time line"
            )
        return TimeCheck("outlier", gnss, error, weeks, leap_second, message)

    def _accept(
        self, verdict: Verdict, t_mono: float, gnss: float, delay: float, weeks: int,
        leap_second: bool, message: str | None,
    ) -> TimeCheck:
        self._delays.append(delay)
        self._last_gnss = gnss
        self._cand_n = 0
        if leap_second:
            # gnss − 1 is the stamp's 23:59:59.x on the scale; the midnight after it in POSIX
            midnight = float(math.floor(self.posix_of(gnss - 1.0))) + 1.0
            if not self._leaps or self._leaps[-1][0] != midnight:
                self._leaps.append((midnight, math.floor(gnss)))
                self.events.leap_seconds += 1
                self.events.last_leap_mono = t_mono
                message = (
                    "GNSS leap second (23:59:60) received: positions continue; seeds in it "
                    "are stamped 23:59:59.999999"
                )
        return TimeCheck(verdict, gnss, 0.0, weeks, leap_second, message)

    # ------------------------------------------------------------ the continuous scale

    def _leap_shift(self, posix_s: float) -> float:
        """Leap seconds seen before ``posix_s`` (their midnight at or before it)."""
        return float(sum(1 for midnight, _ in self._leaps if posix_s >= midnight))

    def posix_of(self, gnss_s: float) -> float:
        """The POSIX time (what records are stamped in) of a time on the continuous scale;
        inside a leap second: the last microsecond before its midnight."""
        if not self._leaps:
            return gnss_s
        shift = 0.0
        for midnight, start in self._leaps:
            if gnss_s < start:
                break
            if gnss_s < start + 1.0:
                return midnight - LEAP_SECOND_STAMP_BEFORE_S
            shift += 1.0
        return gnss_s - shift

    @property
    def has_leaps(self) -> bool:
        return bool(self._leaps)

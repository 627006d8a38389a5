"""Alarms that tell the operator, in the cab and on the dashboard, when the as-planted map is
not being recorded as it should be.

The GNSS reader, the seed-sensor source and the recorder keep going through every fault (they
reconnect, extrapolate, retry the store) and count what happened; without these alarms the
only trace would be the journal, read after the field is sown. Each condition must hold for
``hold_s`` before it is raised, so the ports opening at start-up or a single late epoch do not
flap; it clears as soon as the condition is gone (``seed_sensors.implausible_rate``:
``IMPLAUSIBLE_CLEAR_AFTER_S`` after the last edge beyond ``seed_sensors.
max_seeds_per_s_per_row``, so a short burst is still seen).

| code | severity | raised while |
|---|---|---|
| ``gnss.unavailable`` | warning | no fresh epoch with a fix (port gone, receiver silent, no fix) |
| ``gnss.not_rtk_fixed`` | warning | recording, and the fix is RTK float, DGPS or single |
| ``gnss.heading_invalid`` | info | recording, and no ambiguity-fixed dual-antenna heading |
| ``gnss.time_outlier`` | warning | epochs with implausible time stamps rejected (last 60 s) |
| ``gnss.time_step`` | warning | the receiver's time stepped, mapping re-established (60 s) |
| ``gnss.week_rollover`` | warning | dates 1024·k weeks early corrected (last 60 s) |
| ``gnss.leap_second`` | info | a leap second (23:59:60) received (60 s) |
| ``seed_sensors.unavailable`` | warning | the seed-tube sensor port/chip is not being read |
| ``seed_sensors.implausible_rate`` | warning | edges beyond a row's plausible rate (not stored) |
| ``records.store_failed`` | critical | seed records cannot be written or committed |
| ``records.lost`` | critical | the store is failing and its memory for held records is full |

The two record alarms need nothing from the store to reach the operator: they are raised on
the ``AlarmBoard``, which the screen reads directly and the MQTT link publishes live when the
store cannot keep them (``gateway.link.mqtt``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, Protocol

from gateway.core.alarms import AlarmBoard
from gateway.core.records import AlarmSeverity

HOLD_S = 1.0
# the GNSS time alarms (gnss_time events) stay up this long after their last event
TIME_EVENT_ALARM_S = 60.0
# seed_sensors.implausible_rate stays up this long after the last implausible edge, so a
# burst shorter than a flush interval is still seen on the screen and on MQTT
IMPLAUSIBLE_CLEAR_AFTER_S = 5.0


class _GnssStats(Protocol):
    @property
    def connected(self) -> bool: ...
    @property
    def last_error(self) -> str | None: ...


class _Epoch(Protocol):
    @property
    def fix(self) -> str: ...
    @property
    def heading_valid(self) -> bool: ...


class GnssLike(Protocol):
    """What is read from ``drivers.gnss_reader.GnssReader``."""

    port: str

    @property
    def available(self) -> bool: ...
    @property
    def latest(self) -> _Epoch | None: ...
    @property
    def stats(self) -> _GnssStats: ...


class _SensorStats(Protocol):
    @property
    def last_error(self) -> str | None: ...


class SensorsLike(Protocol):
    """What is read from a ``drivers.seed_sensors`` source."""

    @property
    def available(self) -> bool: ...
    @property
    def stats(self) -> _SensorStats: ...


class TimeEventsLike(Protocol):
    """What is read from ``gateway.recording.positioning.gnss_time.TimeEvents``."""

    @property
    def outliers(self) -> int: ...
    @property
    def last_outlier_mono(self) -> float | None: ...
    @property
    def last_step_mono(self) -> float | None: ...
    @property
    def last_step_s(self) -> float: ...
    @property
    def last_rollover_mono(self) -> float | None: ...
    @property
    def rollover_weeks(self) -> int: ...
    @property
    def last_leap_mono(self) -> float | None: ...


class RecorderLike(Protocol):
    """What is read from ``gateway.recording.recorder.SeedRecorder``."""

    @property
    def gnss_time(self) -> TimeEventsLike: ...
    @property
    def store_error(self) -> str | None: ...
    @property
    def records_lost(self) -> int: ...

    def implausible_rows(self, within_s: float) -> list[int]: ...


class StoreLike(Protocol):
    """What is read from ``gateway.recording.store.RecordStore``."""

    @property
    def commit_error(self) -> str | None: ...
    @property
    def records_held(self) -> int: ...
    @property
    def records_lost(self) -> int: ...
    @property
    def max_held_records(self) -> int: ...
    @property
    def stalled(self) -> bool: ...
    @property
    def replaced(self) -> Any: ...  # a ReplacedStore (describe()) or None
    @property
    def unclean_stop(self) -> str | None: ...


class RecordingHealth:
    """Re-evaluated on every control tick (``check``); raises and clears on ``alarms``."""

    def __init__(
        self,
        alarms: AlarmBoard,
        *,
        gnss: GnssLike | None = None,
        sensors: SensorsLike | None = None,
        recorder: RecorderLike | None = None,
        store: StoreLike | None = None,
        clock: Callable[[], float] = time.monotonic,
        hold_s: float = HOLD_S,
    ) -> None:
        self.alarms = alarms
        self.gnss = gnss
        self.sensors = sensors
        self.recorder = recorder
        self.store = store
        self._clock = clock
        self.hold_s = hold_s
        self._bad_since: dict[str, float] = {}
        self._lost_before = 0  # records lost before the current store failure

    def _set(
        self, code: str, bad: bool, message: str, severity: AlarmSeverity, now: float
    ) -> None:
        if not bad:
            self._bad_since.pop(code, None)
            self.alarms.clear(code)
            return
        since = self._bad_since.setdefault(code, now)
        if now - since >= self.hold_s:
            self.alarms.raise_(code, message, severity)

    def check(self) -> None:
        now = self._clock()
        self._check_seed_rate(now)
        self._check_gnss_time(now)
        recording = self.recorder is not None
        gnss = self.gnss
        if gnss is not None:
            available = gnss.available
            stats = gnss.stats
            if not stats.connected:
                why = f"receiver on {gnss.port} not readable ({stats.last_error or 'not open'})"
            elif gnss.latest is None:
                why = "no position fix yet"
            else:
                why = "no fresh position fix"
            if recording:
                why += ": seed positions are estimates or missing"
            self._set("gnss.unavailable", not available, f"GNSS: {why}", "warning", now)
            latest = gnss.latest if available else None
            fix = latest.fix if latest is not None else "rtk_fixed"
            self._set(
                "gnss.not_rtk_fixed",
                recording and fix != "rtk_fixed",
                f"GNSS fix is {fix}, not RTK fixed: seed positions are less accurate",
                "warning",
                now,
            )
            self._set(
                "gnss.heading_invalid",
                recording and latest is not None and not latest.heading_valid,
                "no dual-antenna heading: seed positions use the course over ground",
                "info",
                now,
            )
        sensors = self.sensors
        if sensors is not None:
            self._set(
                "seed_sensors.unavailable",
                not sensors.available,
                "seed-tube sensors not readable "
                f"({sensors.stats.last_error or 'not open'}): seeds are not being recorded",
                "warning",
                now,
            )
        rec, store = self.recorder, self.store
        store_error = rec.store_error if rec is not None else None
        commit_error = store.commit_error if store is not None else None
        error = store_error or commit_error
        held = store.records_held if store is not None else 0
        cap = store.max_held_records if store is not None else 0
        # an event when the failure starts and ends; the message (what the screen and
        # state.alarms show) updates with the counts without one
        message = (
            f"record store cannot write ({error}): {held} seed records held in memory "
            f"(room for {cap}), written when the disk has space again"
        )
        self._set("records.store_failed", error is not None, message, "critical", now)
        self._check_store(now)
        lost = (store.records_lost if store is not None else 0) + (
            rec.records_lost if rec is not None else 0
        )
        if error is None:
            self._lost_before = lost
        self._set(
            "records.lost",
            error is not None and lost > self._lost_before,
            f"{lost - self._lost_before} seed records lost: the memory for records the store "
            "cannot write is full",
            "critical",
            now,
        )

    def _check_gnss_time(self, now: float) -> None:
        """The receiver's time stamps judged by the position model (``positioning.
        gnss_time``): each kind of bad time its own alarm, up ``TIME_EVENT_ALARM_S``."""
        if self.recorder is None:
            return
        ev = self.recorder.gnss_time

        def recent(t: float | None) -> bool:
            return t is not None and now - t <= TIME_EVENT_ALARM_S

        self._set(
            "gnss.time_outlier", recent(ev.last_outlier_mono),
            f"{ev.outliers} GNSS epoch(s) with an implausible time stamp rejected (not used "
            "for seed positions)", "warning", now,
        )
        self._set(
            "gnss.time_step", recent(ev.last_step_mono),
            f"GNSS receiver time stepped by {ev.last_step_s:+.1f} s: seed records are stamped "
            "in its new time", "warning", now,
        )
        self._set(
            "gnss.week_rollover", recent(ev.last_rollover_mono),
            f"GNSS receiver dates {ev.rollover_weeks} weeks early (GPS week rollover): "
            "corrected; update its firmware", "warning", now,
        )
        self._set(
            "gnss.leap_second", recent(ev.last_leap_mono),
            "GNSS leap second (23:59:60) received: seeds in it stamped 23:59:59.999999",
            "info", now,
        )

    def _check_store(self, now: float) -> None:
        """``store.stalled`` while a write has been running for seconds (a slow or frozen
        card: records are held in memory, control runs on); ``store.replaced`` for the rest
        of the run once a damaged store was moved aside; ``store.unclean_stop`` for the rest
        of the run when the last one did not close the store (ids skipped)."""
        store = self.store
        if store is None:
            return
        stalled = bool(getattr(store, "stalled", False))
        self._set(
            "store.stalled", stalled,
            f"the card has not finished a write for seconds: {store.records_held} seed records "
            "held in memory until it answers; rate control is not affected",
            "warning", now,
        )
        replaced = getattr(store, "replaced", None)
        if replaced is not None:
            self.alarms.raise_("store.replaced", replaced.describe(), "warning")
        unclean = getattr(store, "unclean_stop", None)
        if unclean is not None:
            self.alarms.raise_("store.unclean_stop", unclean, "warning")

    def _check_seed_rate(self, now: float) -> None:
        """``seed_sensors.implausible_rate`` while rows get edges beyond their plausible rate
        (``gateway.recording.seed_plausibility``), naming them."""
        if self.recorder is None:
            return
        rows = self.recorder.implausible_rows(IMPLAUSIBLE_CLEAR_AFTER_S)
        self._set(
            "seed_sensors.implausible_rate",
            bool(rows),
            f"seed edges on row(s) {', '.join(map(str, rows))} faster than a seed meter can "
            "drop seeds (sensor or module fault): counted, not stored as seeds",
            "warning",
            now,
        )

"""The row monitor in the daemon: fed on every control tick, its verdicts raised as alarms.

``gateway.recording.row_monitor`` does the judging on plain values; this reads what it needs
(the recorder's per-row seed counts and the rows whose edges are being dropped as implausible)
and turns its report into alarms on the ``AlarmBoard``, which the touchscreen, MQTT (event and
``state.alarms``), the dashboard and the field report all show:

| code | severity | raised while |
|---|---|---|
| ``row.<n>.blocked`` | critical | row n delivered at most ``blocked_pct`` % of the median row |
| ``row.<n>.skipping`` | warning | row n below ``skip_pct`` % of the median row |
| ``row.<n>.chattering`` | warning | row n's sensor sends edges no row can drop (not stored) |
| ``seed_sensors.all_rows_silent`` | critical | no seed on any row while the meter turns |

A blocked row is critical: it is a strip of the field left unsown until someone clears the
tube, and a critical alarm stays on the screen until acknowledged.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Protocol

from gateway.config import Settings
from gateway.core.alarms import AlarmBoard
from gateway.recording.row_monitor import RowMonitor, RowMonitorLimits, RowMonitorReport
from gateway.recording.seed_plausibility import QUARANTINE_S

ALL_ROWS_SILENT = "seed_sensors.all_rows_silent"


class RecorderCounts(Protocol):
    """What is read from ``gateway.recording.recorder.SeedRecorder``."""

    @property
    def edges_per_row(self) -> Mapping[int, int]: ...

    def implausible_rows(self, within_s: float) -> list[int]: ...


def limits_of(settings: Settings) -> RowMonitorLimits:
    rm = settings.row_monitor
    return RowMonitorLimits(
        delay_s=rm.delay_s, min_speed_kmh=rm.min_speed_kmh,
        min_expected_seeds=rm.min_expected_seeds, blocked_pct=rm.blocked_pct,
        skip_pct=rm.skip_pct,
    )


class RowAlarms:
    """``check`` once per control tick; ``report`` for the state payload."""

    def __init__(
        self,
        settings: Settings,
        alarms: AlarmBoard,
        recorder: RecorderCounts,
        clock: Callable[[], float],
    ) -> None:
        self.alarms = alarms
        self.recorder = recorder
        self._clock = clock
        self.monitor = RowMonitor(
            settings.machine.rows, limits_of(settings),
            target_spacing_m=settings.positioning.target_spacing_m,
        )
        self._limits = self.monitor.limits

    def check(self, *, working: bool, speed_kmh: float | None, meter_turning: bool) -> None:
        self.monitor.update(
            self._clock(), working=working, speed_kmh=speed_kmh, meter_turning=meter_turning,
            seeds=self.recorder.edges_per_row,
            chattering=self.recorder.implausible_rows(QUARANTINE_S),
        )
        self._raise(self.monitor.report())

    def report(self) -> RowMonitorReport:
        return self.monitor.report()

    def _raise(self, report: RowMonitorReport) -> None:
        limits = self._limits
        self.alarms.set(
            ALL_ROWS_SILENT, report.all_rows_silent,
            f"no seed on any row for {limits.delay_s:g} s while the meter turns: seed tubes "
            "blocked, the hopper empty, the meter not delivering or the sensor module dead",
            "critical",
        )
        for row, r in report.rows.items():
            share = "" if r.pct_of_reference is None else f" ({r.pct_of_reference:.0f} % of the " \
                "median row)"
            self.alarms.set(
                f"row.{row}.blocked", r.verdict == "blocked",
                f"row {row} blocked: no seeds{share}; check its tube and sensor", "critical",
            )
            self.alarms.set(
                f"row.{row}.skipping", r.verdict == "skipping",
                f"row {row} skipping: below {limits.skip_pct:g} % of the median row{share}",
                "warning",
            )
            self.alarms.set(
                f"row.{row}.chattering", r.verdict == "chattering",
                f"row {row}: its sensor sends edges faster than a row can drop seeds; they "
                "are counted, not stored as seeds: check that sensor and its wiring",
                "warning",
            )

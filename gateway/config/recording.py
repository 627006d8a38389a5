"""Sections for paper C: GNSS receiver, seed-tube sensors, position model and record store."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from gateway.config._base import FieldProblem, OptionalPart, Section

EpochSentence = Literal["RMC", "GGA", "HEADING", "VTG"]
DEFAULT_EPOCH_SENTENCES: tuple[EpochSentence, ...] = ("RMC", "GGA", "HEADING")


class GnssSection(OptionalPart):
    enabled: bool = False
    port: str = "/dev/ttyUSB1"
    baudrate: int = Field(115200, ge=1200, le=921600)
    rate_hz: float = Field(10.0, gt=0, le=50)
    stale_after_s: float = Field(0.5, gt=0, le=10)
    # sentence kinds an epoch waits for before it is emitted early (otherwise: when the next
    # UTC time begins). HEADING = #HEADINGA/#UNIHEADINGA, or $--HDT/$--THS.
    epoch_sentences: list[EpochSentence] = Field(
        default_factory=lambda: list(DEFAULT_EPOCH_SENTENCES), min_length=1
    )
    # no byte at all for this long: close and reopen the port (wedged USB adapter)
    silence_reconnect_s: float = Field(5.0, gt=0, le=600)
    # The UM982 reports the heading of its antenna baseline (primary -> secondary antenna).
    # Added to it to get the machine's heading: 0 with the secondary antenna straight ahead of
    # the primary, 180 straight behind, 90 / -90 side by side with the secondary on the left /
    # right (as on many cab roofs). A wrong value turns every row's lever arm.
    heading_offset_deg: float = Field(0.0, ge=-180, le=180)


# The fastest one row of a precision planter can plausibly drop seeds, plus a margin: a
# vacuum disc meter at 16 km/h (4.44 m/s, the top of high-speed planting) singulating at the
# closest in-row spacing such planters sow, about 3 cm (soybeans), delivers 148 seeds/s; a
# third more for doubles and a moment of overspeed gives 200. A 48-row planter at 16 km/h
# with 10 cm maize spacing is at 44 seeds/s a row. Anything above the limit is a sensor or
# module fault (noise counted as seeds, a firmware flood), not seeds: such edges are counted
# and raise seed_sensors.implausible_rate instead of becoming records.
DEFAULT_MAX_SEEDS_PER_S_PER_ROW = 200.0


class SeedSensorsSection(OptionalPart):
    enabled: bool = False
    source: Literal["serial", "gpio"] = "serial"
    port: str = "/dev/ttyUSB2"
    baudrate: int = Field(115200, ge=1200, le=921600)
    gpio_chip: str = "/dev/gpiochip0"
    gpio_lines: list[int] = Field(default_factory=list)
    debounce_ms: float = Field(2.0, ge=0, le=100)
    # through-beam sensors usually pull the line low when a seed breaks the beam
    gpio_bias: Literal["pull_up", "pull_down", "disabled", "as_is"] = "pull_up"
    # per row, over any 1 s (gateway.recording.seed_plausibility): edges beyond it are not stored
    max_seeds_per_s_per_row: float = Field(DEFAULT_MAX_SEEDS_PER_S_PER_ROW, ge=10, le=5000)


class RowMonitorSection(OptionalPart):
    """Per-row blockage and skip alarms (``gateway.recording.row_monitor``): on by default
    wherever seeds are recorded; ``enabled = false`` turns them off."""

    enabled: bool = True
    # a row is judged over at least this much working time (and the window grows until the
    # reference reaches min_expected_seeds): headland turns and short stops never alarm
    delay_s: float = Field(5.0, ge=1, le=120)
    # below this speed (and whenever not seeding) nothing is judged and the window restarts
    min_speed_kmh: float = Field(2.0, ge=0, le=30)
    min_expected_seeds: int = Field(20, ge=3, le=10_000)
    # a row with at most this % of the reference (the median row) is blocked ...
    blocked_pct: float = Field(10.0, ge=0, le=90)
    # ... and below this % it is skipping
    skip_pct: float = Field(70.0, gt=0, le=100)

    @model_validator(mode="after")
    def _thresholds_ordered(self) -> RowMonitorSection:
        if self.skip_pct <= self.blocked_pct:
            raise FieldProblem(
                "skip_pct", f"must be above blocked_pct ({self.blocked_pct:g}), in "
                f"{self.blocked_pct:g}..100", self.skip_pct,
            )
        return self


# Paper C, Table 1: seed fall time from sensor to furrow (ms) against speed (km/h).
DEFAULT_FALL_TIME_TABLE: list[tuple[float, float]] = [
    (4.0, 114.2),
    (5.0, 111.6),
    (6.0, 109.3),
    (7.0, 108.2),
    (8.0, 106.3),
    (9.0, 105.9),
    (10.0, 105.3),
    (11.0, 104.8),
    (12.0, 104.1),
]


def row_lateral_from_width(working_width_m: float, rows: int) -> list[float]:
    """Each row's lateral offset from the centre line (m), row 1 first, left to right, right
    of the centre line positive: ``rows`` rows sharing ``working_width_m`` evenly.

    Paper C writes the offset as ``R·m/(n−1)`` (R working width, n rows) with m only described
    as a "row coefficient related to n", counted from the centre line. We take each row to sow
    an equal strip of width R/n with its outlet in the middle: row spacing R/n, outer rows at
    ±(R/2 − R/(2n)). That is what a planter's working width means (rows × row spacing, so
    48 rows at 0.75 m work 36 m and their seeded strips tile the pass), and it is defined for
    one row. Reading m as the plain row index from the centre would instead put the outer
    outlets on the very edges of the working width (spacing R/(n−1)), making adjacent passes
    overlap by one row, and divide by zero for a single row.
    """
    if rows < 1:
        raise ValueError(f"rows must be >= 1, got {rows}")
    spacing = working_width_m / rows
    return [spacing * (i - (rows - 1) / 2.0) for i in range(rows)]


class HitchSection(Section):
    """A trailed implement on a drawbar hitch, the antenna on the tractor.

    On a curve the implement cuts inside the tractor's path: its heading lags the tractor's,
    so its outlets are not on the tractor's rigid lever arm. With this table the outlet
    lever arm (``positioning.outlet_behind_antenna_m``, ``row_lateral_m``) is ignored along
    the machine axis: the outlets sit ``outlets_behind_hitch_m`` behind the hitch point and
    ``row_lateral_m`` to the side of the implement's centre line, and the implement's heading
    is integrated from the hitch point's path (the drawbar follows its hitch).
    """

    # hitch point: this far behind the antenna, on the tractor's centre line (m)
    behind_antenna_m: float = Field(ge=0, le=20)
    # the implement's outlets (its axle line, where the seeds fall): this far behind the hitch
    outlets_behind_hitch_m: float = Field(gt=0, le=30)
    # the implement's wheel axle, this far behind the hitch (m; omitted: at the outlets). The
    # wheels steer a trailed implement (they roll without slipping sideways), so its heading
    # follows the hitch over this length: gauge wheels 2.2 m behind the hitch leave it 1-2 deg
    # off the tractor's heading for metres after a turn where 1.4 m would have straightened it.
    wheels_behind_hitch_m: float | None = Field(None, gt=0, le=30)
    # the hitch point's height above the ground (m). With terrain compensation (an attitude
    # source and antenna_height_m), the tractor's roll swings the hitch, and the implement
    # with it, downhill by height·sin(roll): 26 mm at 0.5 m and 3 deg.
    height_m: float = Field(0.0, ge=0, le=3)


class PositioningSection(Section):
    method: Literal["interpolated", "paper"] = "interpolated"
    outlet_behind_antenna_m: float = Field(1.2, ge=-20, le=20)
    # One lateral offset per row (m, row 1 first, right of the centre line positive). Omitted:
    # ``Settings`` derives it from machine.rows and machine.working_width_m (see
    # row_lateral_from_width), so a machine of any size works without listing them by hand; a
    # section built on its own, without the machine, must give it.
    row_lateral_m: list[float] | None = None
    fall_time_table: list[tuple[float, float]] = Field(
        default_factory=lambda: list(DEFAULT_FALL_TIME_TABLE)
    )
    # paper C's constant lags, used by method = "paper"
    paper_fall_ms: float = Field(107.7, ge=0, le=1000)
    paper_fix_age_ms: float = Field(50.0, ge=0, le=1000)
    paper_transmission_ms: float = Field(39.5, ge=0, le=1000)
    # interpolated method: the known latency between the epoch time and the sentence arrival
    gnss_output_latency_ms: float = Field(0.0, ge=0, le=1000)
    # fixed delay between a seed breaking the beam and the host stamping its edge
    seed_edge_latency_ms: float = Field(0.0, ge=0, le=1000)
    # a seed waits this long past its landing instant for the epoch that brackets it, then it
    # is extrapolated (at most one epoch ahead) and flagged; the daemon judges "overdue" at
    # its previous 0.5 s flush, so a loop stall cannot extrapolate seeds whose epochs wait in
    # its buffers (the wait is up to one flush longer in a real outage)
    pending_timeout_s: float = Field(0.5, gt=0, le=5)
    # a row's spacing restarts (None) after a gap this long: raised at the headland, stopped
    spacing_reset_gap_s: float = Field(3.0, gt=0, le=60)
    target_spacing_m: float | None = Field(None, gt=0, le=10)
    # Terrain compensation (docs/positioning.md). On a slope the antenna, high on the cab
    # roof, is not above the ground point it stands for: 3 deg of roll at 2.5 m moves it
    # 13 cm sideways. With the antenna's height above the ground and an attitude source, each
    # seed is positioned from the ground point below the antenna and the outlets' offsets are
    # projected by the same attitude; each record says which source corrected it (its
    # ``attitude`` field, "none" = not corrected).
    # Sign convention (sensor frame X forward, Y left, Z up): positive roll = right side
    # down, positive pitch = nose up.
    antenna_height_m: float = Field(0.0, ge=0, le=6)
    # "none": no correction. "dual_antenna": the UM982's #HEADINGA pitch, the elevation of its
    # antenna baseline: the machine's roll when the antennas sit side by side
    # (gnss.heading_offset_deg = 90 or -90) and its pitch when fore and aft (0 or 180).
    # "inclinometer": the RS485 WitMotion's roll axis (its pitch axis keeps telling raised
    # from lowered, inclinometer.axis; it is never read as ground slope).
    attitude_source: Literal["none", "dual_antenna", "inclinometer"] = "none"
    # a sensor mounted the other way round (inclinometer facing backwards): flip the signs
    attitude_invert: bool = False
    # Pitch from the track (m, 0 = off): where the attitude source does not measure pitch
    # (antennas side by side, the inclinometer's roll), take it from the antenna's climb over
    # this much of its track (RTK-fixed epochs; 3-5 m). 0.5 deg along the pass leans a 2.5 m
    # antenna 22 mm. Needs an attitude_source; records carry the pitch used (pitch_deg).
    pitch_from_track_m: float = Field(0.0, ge=0, le=50)
    # added to every seed's fall time (ms): what `sowgate calibrate positions` fits from
    # surveyed seeds (fall time and latencies the table and the config do not know)
    delay_correction_ms: float = Field(0.0, ge=-300, le=300)
    # A trailed implement (see HitchSection): its outlets follow the implement's path.
    hitch: HitchSection | None = None

    @model_validator(mode="after")
    def _table_sorted(self) -> PositioningSection:
        speeds = [s for s, _ in self.fall_time_table]
        if not speeds or speeds != sorted(speeds):
            raise FieldProblem(
                "fall_time_table", "must be non-empty and sorted by speed", self.fall_time_table
            )
        if self.antenna_height_m > 0 and self.attitude_source == "none":
            # it alone corrects nothing: on a 3 deg slope every seed stayed 13 cm off while the
            # config looked complete (issue 20); a config error, not a note nobody reads
            raise FieldProblem(
                "antenna_height_m",
                "corrects nothing without positioning.attitude_source (it is \"none\"): set "
                "attitude_source = \"dual_antenna\" or \"inclinometer\" for terrain "
                "compensation, or leave antenna_height_m out (0)",
                self.antenna_height_m,
            )
        return self

    def lateral_offsets(self) -> list[float]:
        """``row_lateral_m`` as the position model needs it: always a list once ``Settings``
        has resolved the section, so only a hand-built section can get here without one."""
        if self.row_lateral_m is None:
            raise ValueError(
                "positioning.row_lateral_m is not set: give it, or build the section through "
                "Settings, which derives it from machine.rows and machine.working_width_m"
            )
        return self.row_lateral_m


class StoreSection(Section):
    path: str | None = None  # default: <state dir>/records.sqlite3
    retention_days: float = Field(30.0, gt=0, le=3650)
    backlog_alarm_records: int = Field(200_000, ge=1)
    # the seed recorder flushes and commits every 0.5 s on the same tick grid
    # (gateway.recording.recorder.FLUSH_INTERVAL_S), so the store's own tick shares its wake-up
    commit_interval_s: float = Field(0.5, gt=0, le=1.0)

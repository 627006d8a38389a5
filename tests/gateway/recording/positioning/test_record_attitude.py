"""Re-positioning's attitude: each record's roll and pitch estimated again with the records
around it (``record_attitude.smooth_attitude``).

The truth here is the test's own: a tractor driving north over two rolling waves along the
pass and a cross tilt that rolls on a third wavelength; the records carry what the live
positioner would have measured of it (the baseline's roll with its per-epoch noise, the pitch
from the antenna's climb over the last 4 m as ``EpochAttitude`` computes it from noisy RTK
heights), interpolated between epochs for six rows of seeds.
"""

from __future__ import annotations

import itertools
import math
import random
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import numpy as np

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning.attitude import EpochAttitude
from gateway.recording.positioning.record_attitude import pitch_from_track, smooth_attitude

T0 = datetime(2026, 5, 2, 6, 0, 0, tzinfo=UTC)
H = 2.6  # antenna height (m)
WINDOW_M = 4.0


def settings(**kw: object) -> PositioningSection:
    base: dict[str, object] = {
        "outlet_behind_antenna_m": 3.0, "row_lateral_m": [-1.125, -0.375, 0.375, 1.125],
        "antenna_height_m": H, "attitude_source": "dual_antenna",
        "pitch_from_track_m": WINDOW_M,
    }
    base.update(kw)
    return PositioningSection(**base)  # type: ignore[arg-type]


def ground_height(n: float) -> float:
    return 0.04 * math.sin(2 * math.pi * n / 31.0) + 0.03 * math.sin(2 * math.pi * n / 47.0 + 1)


def true_pitch_deg(n: float) -> float:
    slope = (0.04 * 2 * math.pi / 31.0 * math.cos(2 * math.pi * n / 31.0)
             + 0.03 * 2 * math.pi / 47.0 * math.cos(2 * math.pi * n / 47.0 + 1))
    return math.degrees(math.atan(slope))


def true_roll_deg(n: float) -> float:
    return 1.5 + 1.2 * math.sin(2 * math.pi * n / 37.0 + 0.5)


@dataclass
class _Epoch:
    t_mono: float
    alt_m: float | None
    fix: str = "rtk_fixed"
    heading_valid: bool = True


def drive(speed_kmh: float, seconds: float, seed: int, *, start_s: float = 0.0,
          roll_noise_deg: float = 0.15, height_noise_m: float = 0.006
          ) -> tuple[list[SeedDrop], list[tuple[float, float]]]:
    """Records of six rows' seeds (the measured attitude interpolated between 10 Hz epochs)
    and the true (roll, pitch) at each."""
    rng = random.Random(seed)
    v = speed_kmh / 3.6
    att = EpochAttitude(settings(), baseline_offset_deg=-90.0)
    epochs = []  # (t, roll measured, pitch measured)
    for k in range(int(seconds * 10) + 1):
        t = start_s + k * 0.1
        n = v * (t - start_s)
        up = ground_height(n) + H * math.cos(math.radians(true_pitch_deg(n)))
        up += rng.gauss(0.0, height_noise_m)
        pitch = att.track_pitch(0.0, n, up, _Epoch(t, up))  # type: ignore[arg-type]
        epochs.append((t, true_roll_deg(n) + rng.gauss(0.0, roll_noise_deg), pitch))
    records, truth = [], []
    for (t0, r0, p0), (_t1, r1, p1) in itertools.pairwise(epochs):
        if p0 is None or p1 is None:
            continue
        for row in range(1, 7):
            a = (row - 0.5) / 6.0
            t = t0 + 0.1 * a
            n = v * (t - start_s)
            records.append(SeedDrop(
                row=row, utc=T0 + timedelta(seconds=t), lat=45.0 + n / 111_000.0, lon=126.0,
                fix="rtk_fixed", speed_kmh=speed_kmh, heading_deg=0.0,
                heading_source="dual_antenna", method="interpolated",
                attitude="dual_antenna", roll_deg=r0 + a * (r1 - r0),
                pitch_deg=p0 + a * (p1 - p0), delay_ms=120.0, offset_east_m=0.0,
                offset_north_m=-3.0,
            ))
            truth.append((true_roll_deg(n), true_pitch_deg(n)))
    return records, truth


def rms_errors(records: list[SeedDrop], truth: list[tuple[float, float]]
               ) -> tuple[float, float]:
    roll = np.array([r.roll_deg for r in records], dtype=float) - [x[0] for x in truth]
    pitch = np.array([r.pitch_deg for r in records], dtype=float) - [x[1] for x in truth]
    return float(np.sqrt(np.mean(roll**2))), float(np.sqrt(np.mean(pitch**2)))


def test_the_pitch_lags_no_more_and_the_roll_noise_averages_out_at_any_speed() -> None:
    """As stored, the pitch is the slope of the last 4 m (2 m behind the antenna) and the
    roll one epoch's noisy baseline; estimated again with the records around each, the pitch
    keeps under half its error and the roll under 0.6 (the lag is most of the pitch's; over
    the 2.6 m antenna 0.1° is 4.5 mm on the ground)."""
    for speed, seed in ((4.0, 1), (8.0, 2), (16.0, 3)):
        records, truth = drive(speed, 150.0 / (speed / 3.6), seed)
        roll_before, pitch_before = rms_errors(records, truth)
        roll_after, pitch_after = rms_errors(
            list(smooth_attitude(records, settings(), -90.0)), truth)
        assert pitch_before > 0.1
        assert pitch_after < 0.5 * pitch_before, (speed, pitch_before, pitch_after)
        # ±1.5 m holds 7 epochs at 16 km/h, 27 at 4 km/h
        assert roll_after < 0.6 * roll_before, (speed, roll_before, roll_after)


def test_a_pitch_the_baseline_measures_is_not_moved_along_the_track() -> None:
    """Antennas fore and aft measure the pitch where the machine is: no lag to take out (only
    the noise averaged); side by side or the inclinometer's roll: the pitch is the track's."""
    assert pitch_from_track(settings(), -90.0) and pitch_from_track(settings(), 90.0)
    assert not pitch_from_track(settings(), 0.0) and not pitch_from_track(settings(), 180.0)
    assert pitch_from_track(settings(attitude_source="inclinometer"), 0.0)
    assert not pitch_from_track(settings(pitch_from_track_m=0.0), -90.0)
    assert not pitch_from_track(
        settings(attitude_source="none", antenna_height_m=0.0, pitch_from_track_m=0.0), -90.0)
    records, _truth = drive(8.0, 30.0, 4, roll_noise_deg=0.0, height_noise_m=0.0)
    # as if measured by a fore-and-aft baseline: a pitch that changes along the pass
    measured = [r.model_copy(update={"pitch_deg": float(k) * 1e-3})
                for k, r in enumerate(records)]
    got = list(smooth_attitude(measured, settings(), 0.0))
    middle = len(got) // 2
    # the mean over ±1 m around the record itself: unchanged for a linear ramp
    assert got[middle].pitch_deg is not None
    assert abs(got[middle].pitch_deg - middle * 1e-3) < 0.01


def test_no_window_reaches_across_a_gap_and_records_without_raw_data_pass_as_stored() -> None:
    """A raised turn (no records for 12 s) between two passes on opposite tilts: neither
    pass's records are pulled toward the other's; a record without its raw data (method
    paper) keeps what it had and lends its attitude to none."""
    first, _ = drive(8.0, 20.0, 5, roll_noise_deg=0.0, height_noise_m=0.0)
    second, _ = drive(8.0, 20.0, 6, start_s=32.0, roll_noise_deg=0.0, height_noise_m=0.0)
    first = [r.model_copy(update={"roll_deg": 2.0}) for r in first]
    second = [r.model_copy(update={"roll_deg": -2.0}) for r in second]
    paper = first[-1].model_copy(update={"roll_deg": 40.0, "method": "paper"})
    got = list(smooth_attitude([*first, paper, *second], settings(), -90.0))
    assert all(r.roll_deg == 2.0 for r in got[:len(first)])
    assert got[len(first)] is paper
    assert all(r.roll_deg == -2.0 for r in got[len(first) + 1:])
    assert [(r.utc, r.row) for r in got] == [(r.utc, r.row) for r in [*first, paper, *second]]


def test_the_first_metres_of_a_track_get_the_pitch_ahead_instead_of_level() -> None:
    """The drive's first 4 m (the track's window not yet filled) were sown without pitch,
    counted as level: on 1.5° along the pass that is 68 mm at 2.6 m. Re-estimated, they get
    the climb measured just ahead."""
    slope = math.tan(math.radians(1.5))
    att = EpochAttitude(settings(), baseline_offset_deg=-90.0)
    records = []
    for k in range(200):  # 20 s at 4 km/h
        t, n = k * 0.1, k * 0.1 * 4.0 / 3.6
        up = slope * n + H * math.cos(math.radians(1.5))
        pitch = att.track_pitch(0.0, n, up, _Epoch(t, up))  # type: ignore[arg-type]
        records.append(SeedDrop(
            row=1, utc=T0 + timedelta(seconds=t), lat=45.0 + n / 111_000.0, lon=126.0,
            fix="rtk_fixed", speed_kmh=4.0, heading_deg=0.0, heading_source="dual_antenna",
            method="interpolated", attitude="dual_antenna", roll_deg=0.0, pitch_deg=pitch,
            delay_ms=120.0, offset_east_m=0.0, offset_north_m=-3.0,
        ))
    unmeasured = [i for i, r in enumerate(records) if r.pitch_deg is None]
    assert len(unmeasured) > 30
    got = list(smooth_attitude(records, settings(), -90.0))
    for i in unmeasured:
        assert got[i].pitch_deg is not None and abs(got[i].pitch_deg - 1.5) < 0.01
    # with the pitch measured by the baseline (fore and aft), a missing one stays missing
    kept = list(smooth_attitude(records, settings(), 0.0))
    assert all(kept[i].pitch_deg is None for i in unmeasured)

"""Seeds positioned end to end over real ptys, checked against the simulator's ground truth.

UM982 emulator → pty → GnssReader ─┐
                                   ├→ SeedPositioner → lat/lon ↔ true landing point
seed tubes → pty → SerialSeedSensors┘

Everything runs in real time on one shared time line (``t0_mono``), so this also checks that
the drivers' arrival stamps and the receiver's UTC are put on one clock correctly.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import statistics
import time
from datetime import UTC, datetime

import pytest

from drivers.gnss_reader import GnssEpoch, GnssReader
from drivers.seed_sensors import SeedEdgeEvent, SerialSeedSensors
from gateway.config.recording import PositioningSection
from gateway.recording.positioning import Landing, LocalFrame, SeedPositioner
from simulator.plant import Drive, Leg
from simulator.seed_tubes import PlanterModel, SeedTubeEmulator
from simulator.um982 import Um982Emulator
from tests.helpers import eventually

ORIGIN = (45.7536, 126.6339, 150.0)
OUTPUT_LATENCY_S = 0.02
START_DELAY_S = 0.4  # lets both readers open their ports before the drive starts
# a short pass: stand, accelerate to 8 km/h, sow for a few seconds, diagonal heading
DRIVE = Drive(legs=[Leg(0.6, 0.0), Leg(3.6, 8.0)], start_heading_deg=37.0)


async def test_predicted_landing_points_match_ground_truth_over_ptys() -> None:
    model = PlanterModel()  # the default machine's planter, as a default daemon derives it
    settings = PositioningSection(
        gnss_output_latency_ms=OUTPUT_LATENCY_S * 1000.0, row_lateral_m=list(model.row_lateral_m)
    )
    positioner = SeedPositioner(settings)
    landed: list[Landing] = []

    def on_epoch(epoch: GnssEpoch) -> None:
        landed.extend(positioner.add_epoch(epoch))

    edges_seen = 0

    def on_edge(edge: SeedEdgeEvent) -> None:
        nonlocal edges_seen
        edges_seen += 1
        landed.extend(positioner.add_edge(edge.row, edge.t_mono))

    t0 = time.monotonic() + START_DELAY_S
    gnss = Um982Emulator(
        DRIVE.pose_at,
        origin_lat=ORIGIN[0],
        origin_lon=ORIGIN[1],
        origin_alt_m=ORIGIN[2],
        output_latency_s=OUTPUT_LATENCY_S,
        seed=3,
        utc_start=datetime.now(UTC).replace(microsecond=0),
        t0_mono=t0,
    )
    async with gnss, SeedTubeEmulator(DRIVE, model, t0_mono=t0, seed=3) as tubes:
        sensors = SerialSeedSensors(tubes.device_path, 115200, rows=6, on_edge=on_edge)
        sensor_task = asyncio.create_task(sensors.run(), name="seed-sensors")
        try:
            async with GnssReader(gnss.device_path, on_epoch=on_epoch):
                await tubes.wait_done()
                # every seed line read (a loaded loop gets to the pty late), then the epochs
                # after the last seed's landing
                await eventually(lambda: edges_seen >= len(tubes.truth), 30.0,
                                 "every seed line read")
                await asyncio.sleep(0.5)
        finally:
            sensor_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sensor_task
        truth = list(tubes.truth)
    landed.extend(positioner.flush())

    assert len(truth) > 60
    assert len(landed) == len(truth)
    assert [la.drop.row for la in landed] == [s.row for s in truth]
    frame = LocalFrame(*ORIGIN)
    errors = []
    for la, s in zip(landed, truth, strict=True):
        e, n, _ = frame.to_enu(la.drop.lat, la.drop.lon)
        errors.append(math.hypot(e - s.east, n - s.north))
    assert statistics.median(errors) < 0.05, f"median error {statistics.median(errors):.3f} m"
    assert sum(la.drop.extrapolated for la in landed) <= len(landed) // 10
    assert all(la.drop.heading_source == "dual_antenna" for la in landed)
    assert all(la.drop.fix == "rtk_fixed" for la in landed)
    spacings = [la.drop.spacing_m for la in landed if la.drop.spacing_m is not None]
    assert statistics.median(spacings) == pytest.approx(model.spacing_m, rel=0.1)

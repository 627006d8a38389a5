"""Re-positioning and the survey fit follow a trailed implement's heading along the records."""

from __future__ import annotations

import math

import pytest

from gateway.config.recording import HitchSection
from gateway.recording.positioning.geometry import heading_diff
from gateway.recording.positioning.implement_track import ImplementTrack
from gateway.recording.positioning.survey import Sown, apply_fit, fit_survey, reposition
from simulator.plant import Drive, Leg
from tests.gateway.recording.test_positioning import FRAME, settings
from tests.gateway.recording.test_positioning_survey import drops_of

HITCH = HitchSection(behind_antenna_m=1.5, outlets_behind_hitch_m=2.5)
TRAILED = settings(hitch=HITCH, delay_correction_ms=12.0)
# a straight run-in, then a weave of the autosteer (±3°/s) on a 40 m curve: the implement's
# heading lags the tractor's by up to a few degrees
WEAVE = Drive(legs=[Leg(3.0, 10.0), Leg(2.0, 10.0, yaw_rate_dps=4.0),
                    Leg(2.0, 10.0, yaw_rate_dps=-3.0), Leg(3.0, 10.0, yaw_rate_dps=4.0)],
              start_heading_deg=20.0, accel_ms2=1000.0)
EDGES = [(1 + k % 6, 0.3 + k * 0.05) for k in range(190)]


def enu(lat: float, lon: float) -> tuple[float, float]:
    e, n, _ = FRAME.to_enu(lat, lon)
    return e, n


def test_records_repositioned_with_their_own_trailed_model_stay_where_they_are() -> None:
    """Following the implement along the records' antenna track gives back what the
    positioner put there; a rigid lever arm along the tractor's heading (the former
    re-positioning) moves the seeds across by the drawbar times the articulation."""
    drops = drops_of(TRAILED, WEAVE, EDGES, until=10.5)
    track = ImplementTrack(TRAILED)
    followed, rigid, articulation = [], [], []
    for d in drops:
        implement = track.heading(d)
        assert implement is not None and d.heading_deg is not None
        articulation.append(abs(heading_diff(implement, d.heading_deg)))
        e0, n0 = enu(d.lat, d.lon)
        e, n = enu(*reposition(d, TRAILED, implement))
        followed.append(math.hypot(e - e0, n - n0))
        e, n = enu(*reposition(d, TRAILED))
        rigid.append(math.hypot(e - e0, n - n0))
    assert max(articulation) > 2.0
    assert max(followed) < 0.004
    assert max(rigid) > 0.08


def test_the_survey_fit_on_a_trailed_implement_finds_the_drawbar_and_the_delay() -> None:
    """A fitter's drawbar 6 cm long and lateral 3 cm off (one speed: the lever arm alone);
    the truth is the trailed model itself, surveyed exactly. Fitted along the implement's
    heading (kept for the surveyed records while following every one), the fit recovers
    the errors and the seeds land on the truth; fitted on a rigid lever arm, the weave's
    articulation is left in them."""
    configured = apply_fit(TRAILED, 0.0, 0.06, 0.03)
    drops = drops_of(configured, WEAVE, EDGES, until=10.5)
    track = ImplementTrack(TRAILED)
    truth = [reposition(d, TRAILED, track.heading(d)) for d in drops]
    sown = Sown.empty(configured)
    for d in drops:
        sown.add(d)
        sown.keep(d)
    fit = fit_survey(drops, truth, configured, fit_delay=False, sown=sown)
    assert fit.behind_m == pytest.approx(-0.06, abs=0.005)
    assert fit.right_m == pytest.approx(-0.03, abs=0.003)
    assert fit.after.mean_m < 0.004
    rigid = fit_survey(drops, truth, configured, fit_delay=False)
    assert rigid.after.mean_m > 2 * fit.after.mean_m

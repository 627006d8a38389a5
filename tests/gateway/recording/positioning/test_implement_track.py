"""Re-positioning and the survey fit follow a trailed implement's heading along the records."""

from __future__ import annotations

import itertools
import math

import pytest

from gateway.config.recording import HitchSection
from gateway.recording.positioning.attitude import EpochAttitude
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


def test_a_track_that_restarts_mid_curve_reads_the_implement_back_from_the_records() -> None:
    """Records that start where the implement is articulated (a raised turn's left-over, here
    the weave's curve: the records before are not given): restarted straight behind the
    tractor, the first seeds moved across by the drawbar times the articulation; read back
    from the records' stored offsets (given the settings they were made with), they stay
    where the positioner put them."""
    drops = drops_of(TRAILED, WEAVE, EDGES, until=10.5)
    full = ImplementTrack(TRAILED)
    bent = [abs(heading_diff(h, d.heading_deg)) if (h := full.heading(d)) is not None
            and d.heading_deg is not None else 0.0 for d in drops]
    start = next(i for i, a in enumerate(bent) if a > 2.0)
    track = ImplementTrack(TRAILED, made_with=TRAILED)
    moved = []
    for d in drops[start:start + 12]:
        e0, n0 = enu(d.lat, d.lon)
        e, n = enu(*reposition(d, TRAILED, track.heading(d)))
        moved.append(math.hypot(e - e0, n - n0))
    assert max(moved) < 0.004


def _tractrix_heading(points: list[tuple[float, float]], wheels_m: float, start_deg: float,
                      ) -> float:
    """The test's own implement: heading ψ with dψ/ds = sin(bearing of the hitch's step −
    ψ) / wheels (its wheels roll without side slip), Euler steps of the hitch's path."""
    psi = math.radians(start_deg)
    for (e0, n0), (e1, n1) in itertools.pairwise(points):
        ds = math.hypot(e1 - e0, n1 - n0)
        if ds > 0:
            psi += math.sin(math.atan2(e1 - e0, n1 - n0) - psi) * ds / wheels_m
    return math.degrees(psi) % 360.0


def test_the_implement_turns_about_its_wheels_not_its_outlets() -> None:
    """Outlets 1.4 m behind the hitch, the wheels that steer the implement 2.2 m: after a
    turn onto a straight line the implement straightens over the wheels' distance. Given
    ``wheels_behind_hitch_m`` the followed heading matches an integration of the wheels'
    no-slip path; without it (the axle at the outlets) it straightens too early."""
    hitch = HitchSection(behind_antenna_m=1.6, outlets_behind_hitch_m=1.4)
    wheels = hitch.model_copy(update={"wheels_behind_hitch_m": 2.2})
    # the antenna: a quarter circle of 8 m radius, then 5 m straight, 1 cm steps
    path, headings = [], []
    for k in range(1257):
        a = k / 1256 * math.pi / 2
        path.append((8.0 - 8.0 * math.cos(a), 8.0 * math.sin(a)))
        headings.append(math.degrees(a))
    for k in range(1, 501):
        path.append((8.0 + 0.01 * k, 8.0))
        headings.append(90.0)
    hitch_path = [(e - 1.6 * math.sin(math.radians(h)), n - 1.6 * math.cos(math.radians(h)))
                  for (e, n), h in zip(path, headings, strict=True)]
    truth = _tractrix_heading(hitch_path, 2.2, 0.0)
    got = {}
    for name, h in (("wheels", wheels), ("outlets", hitch)):
        att = EpochAttitude(settings(hitch=h))
        for (e, n), hd in list(zip(path, headings, strict=True))[::10]:
            last = att.follow_hitch(e, n, hd)
        assert last is not None
        got[name] = abs(heading_diff(last, truth))
    assert abs(heading_diff(truth, 90.0)) > 1.0  # still articulated 5 m after the turn
    assert got["wheels"] < 0.2  # the discrete tractrix against the Euler steps
    assert got["outlets"] > 10 * got["wheels"]

"""The radar's scale stays calibrated: learnt against an RTK-fixed GNSS (issue 25 §3).

The truth here: a tractor driving 80 s passes at 8 km/h with 12 s headland turns at 4 km/h;
the radar was calibrated (factor 1.0) on another surface and now reads +4 % (its scale, not
its noise: paper A's 3 % per-sample scatter on top), and reads 10 % low in the turns (it
sees the ground sideways there). The RTK receiver's Doppler speed has 0.03 km/h of noise.
"""

from __future__ import annotations

import math
import random
import statistics
from collections.abc import Callable

import pytest

from gateway.config import ConfigError, parse_config
from gateway.control.controller import Controller
from gateway.control.radar_scale import RadarScaleLearner, RadarScaleSettings
from gateway.core.alarms import AlarmBoard

PASS_S, TURN_S = 80.0, 12.0


def truth(t: float) -> tuple[float, float, bool]:
    """(true km/h, course °, turning) at ``t``."""
    cycle = PASS_S + TURN_S
    k, u = divmod(t, cycle)
    base = 90.0 if int(k) % 2 == 0 else 270.0
    if u < PASS_S:
        return 8.0, base, False
    return 4.0, base + 180.0 * (u - PASS_S) / TURN_S, True


def drive(ctl: Controller, minutes: float, *, radar_scale: float, fix: str = "rtk_fixed",
          seed: int = 1) -> list[tuple[float, float]]:
    """Feeds GNSS at 10 Hz and the radar at 3 Hz; (controller speed, true speed) on passes
    after the first minute."""
    rng = random.Random(seed)
    out = []
    t, next_radar = 0.0, 0.0
    while t < minutes * 60.0:
        v, course, turning = truth(t)
        ctl.on_gnss_epoch(t, fix, v + rng.gauss(0.0, 0.03), course % 360.0)
        if t >= next_radar:
            next_radar += 1.0 / 3.0
            side = 0.9 if turning else 1.0
            ctl.on_speed("radar", v * radar_scale * side * (1 + rng.gauss(0.0, 0.03)), t)
            speed, _ = ctl.speed(t)
            if not turning and t > 60.0 and speed is not None:
                out.append((speed, v))
        t += 0.1
    return out


def controller(**speed: object) -> Controller:
    settings = parse_config({"gnss": {"enabled": True},
                             "speed": {"source": ["radar"], **speed}})
    return Controller(settings, AlarmBoard())


def mean_error_pct(pairs: list[tuple[float, float]]) -> float:
    return 100.0 * (statistics.fmean(s for s, _ in pairs) / statistics.fmean(v for _, v in pairs)
                    - 1.0)


def test_a_4_pct_surface_change_is_learnt_used_and_alarmed() -> None:
    ctl = controller()
    before = mean_error_pct(drive(controller(radar_scale={"enabled": False}), 10.0,
                                  radar_scale=1.04))
    pairs = drive(ctl, 10.0, radar_scale=1.04)
    late = pairs[len(pairs) // 2:]  # the last five minutes
    assert before == pytest.approx(4.0, abs=0.5)  # unlearnt: 1:1 into the rate
    assert abs(mean_error_pct(late)) <= 1.0
    assert ctl.radar_scale is not None and ctl.radar_scale.scale == pytest.approx(
        1 / 1.04, rel=0.005)
    alarm = next(a for a in ctl.alarms.active if a.code == "radar.scale_drift")
    assert "+4." in alarm.message or "+3.9" in alarm.message


def test_a_radar_within_its_calibration_raises_nothing() -> None:
    ctl = controller()
    pairs = drive(ctl, 6.0, radar_scale=1.01)
    assert not ctl.alarms.is_active("radar.scale_drift")
    assert abs(mean_error_pct(pairs[len(pairs) // 2:])) <= 1.0


def test_without_an_rtk_fixed_fix_nothing_is_learnt() -> None:
    ctl = controller()
    drive(ctl, 4.0, radar_scale=1.04, fix="rtk_float")
    assert ctl.radar_scale is not None and ctl.radar_scale.scale is None
    assert ctl.sources["radar"].correction == 1.0


def test_turns_and_speed_changes_are_left_out() -> None:
    """The radar reads 10 % low in every turn; the scale learnt from passes only ignores it."""
    learner = RadarScaleLearner(RadarScaleSettings())
    rng = random.Random(3)
    t = 0.0
    while t < 600.0:
        v, course, turning = truth(t)
        learner.on_gnss(t, "rtk_fixed", v, course % 360.0)
        if round(t * 10) % 3 == 0:
            learner.on_radar(t, v * (0.9 if turning else 1.0) * (1 + rng.gauss(0.0, 0.03)))
        t += 0.1
    assert learner.scale == pytest.approx(1.0, abs=0.004)
    assert learner.rejected > 0


def test_course_change_wraps_at_north() -> None:
    learner = RadarScaleLearner(RadarScaleSettings(), calibrated=1.0)
    for i in range(40):
        learner.on_gnss(i * 0.1, "rtk_fixed", 8.0, (359.5 + i * 0.02) % 360.0)
    learner.on_radar(3.95, 8.0)
    assert learner.accepted == 1
    assert not math.isnan(learner.calibrated)


def test_its_settings_are_checked_with_the_key_named() -> None:
    with pytest.raises(ConfigError, match="alarm_pct"):
        parse_config({"speed": {"radar_scale": {"alarm_pct": 0}}})


def straight_pass(learner: RadarScaleLearner, t0: float, seconds: float, *, kmh: float,
                  radar_scale: Callable[[float], float], rng: random.Random,
                  glitch_every: int = 0) -> list[tuple[float, float | None]]:
    """A straight pass at ``kmh`` with the speed wandering ±3 % (a tractor's load), the GNSS
    at 10 Hz (0.03 km/h) and the radar at 3 Hz (3 % scatter, and every ``glitch_every``-th
    reading off by half: a clod in the beam); ``radar_scale(t)`` is the truth's scale.
    Returns (t, learnt scale) after every radar reading."""
    out: list[tuple[float, float | None]] = []
    t = t0
    n = 0
    while t < t0 + seconds:
        v = kmh * (1.0 + 0.03 * math.sin(2 * math.pi * t / 23.0))
        learner.on_gnss(t, "rtk_fixed", v + rng.gauss(0.0, 0.03), 90.0 + rng.gauss(0.0, 0.2))
        if round(t * 10) % 3 == 0:
            n += 1
            reading = v * radar_scale(t) * (1.0 + rng.gauss(0.0, 0.03))
            if glitch_every and n % glitch_every == 0:
                reading *= 0.5
            learner.on_radar(t, reading)
            out.append((t, learner.scale))
        t = round(t + 0.1, 6)
    return out


def test_a_surface_change_mid_pass_is_followed_within_seconds() -> None:
    """The radar reads right for 3 min, then +4 % (the pass runs onto another surface): the
    learnt scale is 1/1.04 within 15 s of the change, not the window's 3 min."""
    learner = RadarScaleLearner(RadarScaleSettings(), calibrated=1.0)
    change_t = 180.0
    trace = straight_pass(learner, 0.0, 300.0, kmh=3.5, rng=random.Random(5),
                          radar_scale=lambda t: 1.04 if t >= change_t else 1.0)
    before = [k for t, k in trace if 60.0 <= t < change_t]
    after = [k for t, k in trace if t >= change_t + 15.0]
    assert all(k is not None and abs(k - 1.0) < 0.006 for k in before)
    assert all(k is not None and abs(k * 1.04 - 1.0) < 0.01 for k in after)
    assert learner.changes >= 1
    assert learner.drifted()


def test_noise_and_glitches_do_not_restart_the_learning() -> None:
    """20 min at one scale with every 40th radar reading off by half: no change is found, the
    scale holds within 0.6 % and nothing is alarmed."""
    learner = RadarScaleLearner(RadarScaleSettings(), calibrated=1.0 / 1.015)
    trace = straight_pass(learner, 0.0, 1200.0, kmh=2.5, rng=random.Random(11),
                          radar_scale=lambda t: 1.015, glitch_every=40)
    assert learner.changes == 0
    assert all(k is not None and abs(k * 1.015 - 1.0) < 0.006 for t, k in trace if t >= 40.0)
    assert not learner.drifted()


def test_a_slow_drift_is_followed() -> None:
    """The soil dries along the pass: the radar's scale creeps from 0 to +3 % over 10 min
    (no step to detect); the learnt scale stays within 1 % of it."""
    learner = RadarScaleLearner(RadarScaleSettings(), calibrated=1.0)

    def scale(t: float) -> float:
        return 1.0 + 0.03 * min(1.0, t / 600.0)

    trace = straight_pass(learner, 0.0, 720.0, kmh=4.5, rng=random.Random(7), radar_scale=scale)
    assert all(k is not None and abs(k * scale(t) - 1.0) < 0.01 for t, k in trace if t >= 40.0)


def test_the_scale_learnt_holds_across_a_stop_longer_than_the_window() -> None:
    """A 10 min stop (no fair comparison): the next pass starts with the learnt scale, not
    one made of its first reading."""
    learner = RadarScaleLearner(RadarScaleSettings(window_s=60.0), calibrated=1.0)
    rng = random.Random(2)
    straight_pass(learner, 0.0, 120.0, kmh=3.5, rng=rng, radar_scale=lambda t: 1.04)
    learnt = learner.scale
    assert learnt is not None and abs(learnt * 1.04 - 1.0) < 0.005
    trace = straight_pass(learner, 720.0, 60.0, kmh=3.5, rng=rng, radar_scale=lambda t: 1.04)
    assert all(k is not None and abs(k * 1.04 - 1.0) < 0.008 for _, k in trace)


def test_lags_unlike_each_other_and_turns_do_not_bias_the_scale() -> None:
    """A truth unlike the learner's pairing: the radar smooths over 0.6 s (its own filter),
    the GNSS speed comes 0.2 s late, the tractor surges ±5 % every 15 s on the passes and
    the radar reads 10 % low in the turns; the radar reads +3 %. The scale is learnt within
    0.5 % and the turns are left out."""
    learner = RadarScaleLearner(RadarScaleSettings(), calibrated=1.0)
    rng = random.Random(9)
    lagged = 0.0
    history: list[tuple[float, float]] = []
    t = 0.0
    while t < 900.0:
        v, course, turning = truth(t)
        if not turning:
            v *= 1.0 + 0.05 * math.sin(2 * math.pi * t / 15.0)
        history.append((t, v))
        late_v = next(x for s, x in reversed(history) if s <= t - 0.2 + 1e-9) if t >= 0.2 else v
        learner.on_gnss(t, "rtk_fixed", late_v + rng.gauss(0.0, 0.03), course % 360.0)
        lagged += (v - lagged) * 0.1 / 0.6
        if round(t * 10) % 3 == 0:
            side = 0.9 if turning else 1.0
            learner.on_radar(t, lagged * 1.03 * side * (1.0 + rng.gauss(0.0, 0.03)))
        t = round(t + 0.1, 6)
    assert learner.scale is not None and abs(learner.scale * 1.03 - 1.0) < 0.005
    assert learner.changes == 0
    assert learner.drifted()

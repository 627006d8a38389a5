"""Paper A's rate chain: target kg/ha and ground speed → metering flow → shaft speed → duty.

    M = 3Q / (5·B·V)          eq. (4)  M kg/ha, Q g/min, B m, V km/h
    Q = a·ω² + b·ω + c        eq. (6)  per crop, ω r/min, fitted on the machine
    ω = slope·K + intercept   eq. (5)  per crop, K duty %

The controller needs the inverse of (6) and (5). A rotation test of >= 5 set points replaces
both with the drill's own monotone curves (``CropModel.meter_curve`` / ``motor_curve``,
``gateway.core.monotone``), inverted exactly. Eq. (6) is a parabola; only the branch on the
rising side of its vertex is physical (more shaft speed, more seed), so the inverse takes that
root and reports anything past the vertex or outside the fitted ω range instead of guessing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from gateway.config import CropModel
from gateway.core.errors import OutsideCalibrationError, RateError, TooFastError
from gateway.core.monotone import MonotoneCurve, cached_curve

MAX_DUTY_PCT = 100.0


def flow_for_rate(rate_kg_ha: float, width_m: float, speed_kmh: float) -> float:
    """Q in g/min that applies ``rate_kg_ha`` over ``width_m`` at ``speed_kmh`` (eq. 4)."""
    return 5.0 * width_m * speed_kmh * rate_kg_ha / 3.0


def rate_for_flow(flow_g_min: float, width_m: float, speed_kmh: float) -> float:
    """Applied kg/ha for a flow (eq. 4); zero speed gives zero by convention (nothing sown)."""
    if speed_kmh <= 0.0:
        return 0.0
    return 3.0 * flow_g_min / (5.0 * width_m * speed_kmh)


def _curve(points: list[tuple[float, float]]) -> MonotoneCurve:
    return cached_curve(tuple((float(x), float(y)) for x, y in points))


def flow_at(omega_rpm: float, crop: CropModel) -> float:
    """Eq. (6) (or the drill's own monotone curve, when calibrated): discharge at a speed."""
    if crop.meter_curve is not None:
        return _curve(crop.meter_curve)(omega_rpm)
    return crop.meter_a * omega_rpm**2 + crop.meter_b * omega_rpm + crop.meter_c


def omega_peak(crop: CropModel) -> float:
    """The shaft speed where eq. (6) stops rising (inf for a straight line, a convex fit or
    a monotone curve, which rises everywhere)."""
    if crop.meter_curve is not None or crop.meter_a >= 0.0:
        return math.inf
    return -crop.meter_b / (2.0 * crop.meter_a)


def omega_for_flow(flow_g_min: float, crop: CropModel) -> float:
    """Exact inverse of eq. (6) on its rising branch.

    Raises OutsideCalibrationError when no shaft speed on that branch delivers the flow.
    A monotone curve has one shaft speed for each flow: its inverse.
    """
    if crop.meter_curve is not None:
        try:
            return _curve(crop.meter_curve).inverse(flow_g_min)
        except ValueError as exc:
            raise OutsideCalibrationError(f"flow {flow_g_min:.0f} g/min: {exc}") from None
    a, b, c = crop.meter_a, crop.meter_b, crop.meter_c
    if a == 0.0:
        if b <= 0.0:
            raise OutsideCalibrationError("metering model is not increasing (meter_b <= 0)")
        return (flow_g_min - c) / b
    disc = b * b - 4.0 * a * (c - flow_g_min)
    if disc < 0.0:
        peak = flow_at(omega_peak(crop), crop)
        raise OutsideCalibrationError(
            f"flow {flow_g_min:.0f} g/min is beyond the metering device's maximum {peak:.0f} g/min"
        )
    root = math.sqrt(disc)
    # For a < 0 the rising-branch root is (-b + root)/(2a); for a > 0 it is (-b + root)/(2a) too
    # (the larger root, right of the vertex). One expression serves both.
    return (-b + root) / (2.0 * a)


def duty_for_omega(omega_rpm: float, crop: CropModel) -> float:
    """Inverse of eq. (5) (or of the motor's own monotone curve): the PWM duty (%) that
    turns the shaft at ``omega_rpm``."""
    if crop.motor_curve is not None:
        try:
            return _curve(crop.motor_curve).inverse(omega_rpm)
        except ValueError:
            return MAX_DUTY_PCT + 1.0 if omega_rpm > crop.motor_curve[-1][1] else 0.0
    return (omega_rpm - crop.motor_intercept) / crop.motor_slope


def omega_for_duty(duty_pct: float, crop: CropModel) -> float:
    if crop.motor_curve is not None:
        return _curve(crop.motor_curve)(duty_pct)
    return crop.motor_slope * duty_pct + crop.motor_intercept


def max_speed_kmh(rate_kg_ha: float, width_m: float, crop: CropModel) -> float:
    """The fastest ground speed at which ``rate_kg_ha`` is still reachable at 100 % duty."""
    omega = min(omega_for_duty(MAX_DUTY_PCT, crop), omega_peak(crop))
    q = flow_at(omega, crop)
    return 3.0 * q / (5.0 * width_m * rate_kg_ha)


@dataclass(frozen=True)
class DutyPlan:
    """What the motor should do and why; ``problem`` is set when the target cannot be met."""

    flow_g_min: float
    omega_rpm: float
    duty_pct: float  # clamped to 0..100, what is actually commanded
    problem: RateError | None = None
    warning: str | None = None


def required_duty(rate_kg_ha: float, width_m: float, speed_kmh: float, crop: CropModel) -> float:
    """The unclamped duty for a target; raises TooFastError / OutsideCalibrationError."""
    plan = plan_duty(rate_kg_ha, width_m, speed_kmh, crop)
    if plan.problem is not None:
        raise plan.problem
    return plan.duty_pct


def plan_duty(rate_kg_ha: float, width_m: float, speed_kmh: float, crop: CropModel) -> DutyPlan:
    """Plan the motor duty for a target rate at a speed, never raising.

    When the target is out of reach the plan still commands the closest safe duty (100 % when
    too fast, the extrapolated duty outside the fitted range) and names the problem, so the
    operator sees an alarm while the drill keeps sowing as close to target as it can.
    """
    if speed_kmh <= 0.0 or rate_kg_ha <= 0.0:
        return DutyPlan(0.0, 0.0, 0.0)
    flow = flow_for_rate(rate_kg_ha, width_m, speed_kmh)
    try:
        omega = omega_for_flow(flow, crop)
    except OutsideCalibrationError:
        return DutyPlan(
            flow,
            omega_peak(crop),
            MAX_DUTY_PCT,
            TooFastError(max_speed_kmh(rate_kg_ha, width_m, crop)),
        )
    duty = duty_for_omega(omega, crop)
    if duty > MAX_DUTY_PCT:
        return DutyPlan(
            flow, omega, MAX_DUTY_PCT, TooFastError(max_speed_kmh(rate_kg_ha, width_m, crop))
        )
    problem: RateError | None = None
    if not crop.omega_min_rpm <= omega <= crop.omega_max_rpm:
        problem = OutsideCalibrationError(
            f"shaft speed {omega:.1f} r/min outside calibrated range "
            f"{crop.omega_min_rpm:g}-{crop.omega_max_rpm:g} r/min"
        )
    warning = None
    clamped = max(0.0, duty)
    if clamped < crop.startup_duty_pct:
        warning = (
            f"duty {clamped:.1f} % below start-up duty {crop.startup_duty_pct:g} %: "
            "motor may not turn"
        )
    return DutyPlan(flow, omega, clamped, problem, warning)

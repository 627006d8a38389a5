"""Where a row outlet is relative to the antenna, and where that is on the Earth.

Owns the pure geometry every positioning method shares: the row outlets' lever arms
(:class:`RowOffset`, :func:`row_offset`), their rotation by the machine heading
(:func:`rotate_offset`), heading arithmetic on the circle (:func:`wrap_deg`,
:func:`heading_diff`, :func:`interpolate_heading`) and the WGS84 <-> local ENU frame
(:class:`LocalFrame`, including its fast scalar and numpy paths for ENU -> geodetic).

Separate because it knows nothing of time, GNSS epochs or seeds: it is the part the paper's
model, the interpolated method, the simulator's ground truth and the benchmarks' oracle all
agree on, and it is tested against pymap3d on its own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, overload

import numpy as np
import numpy.typing as npt
import pymap3d

from gateway.config.recording import PositioningSection

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class RowOffset:
    """A row outlet relative to the main antenna, in the machine frame."""

    behind_m: float
    right_m: float


def row_offset(settings: PositioningSection, row: int) -> RowOffset:
    """``row``'s outlet on a rigid lever arm; with a trailed implement (``[positioning.hitch]``)
    the lever arm it has when driving straight (hitch + drawbar behind the antenna)."""
    lateral = settings.lateral_offsets()
    if not 1 <= row <= len(lateral):
        raise ValueError(f"row {row} outside 1..{len(lateral)} (positioning.row_lateral_m)")
    return RowOffset(rigid_behind_m(settings), lateral[row - 1])


def rigid_behind_m(settings: PositioningSection) -> float:
    """The outlets' distance behind the antenna on a straight line."""
    hitch = settings.hitch
    if hitch is None:
        return settings.outlet_behind_antenna_m
    return hitch.behind_antenna_m + hitch.outlets_behind_hitch_m


def rotate_offset(offset: RowOffset, heading_deg: float) -> tuple[float, float]:
    """(east, north) displacement from the antenna to the outlet for a machine heading."""
    h = math.radians(heading_deg)
    fwd_e, fwd_n = math.sin(h), math.cos(h)
    right_e, right_n = math.cos(h), -math.sin(h)
    return (
        -offset.behind_m * fwd_e + offset.right_m * right_e,
        -offset.behind_m * fwd_n + offset.right_m * right_n,
    )


# ---------------------------------------------------------------- terrain (attitude)
#
# Sign convention, in the machine's frame X forward, Y left, Z up: positive roll = right side
# down, positive pitch = nose up (docs/positioning.md, positioning.attitude_source).


def terrain_offset(
    offset: RowOffset, roll_deg: float, pitch_deg: float, antenna_height_m: float
) -> RowOffset:
    """The horizontal antenna → outlet lever arm on a slope.

    The antenna stands ``antenna_height_m`` above the ground point it represents, along the
    machine's Z axis: rolled right side down it leans right by H·sin(roll), pitched nose up
    it leans back by H·sin(pitch), so the ground point is that far the other way. The outlets'
    offsets, measured along the (tilted) implement, shorten to their horizontal projection.
    Level ground returns ``offset`` unchanged.
    """
    r, p = math.radians(roll_deg), math.radians(pitch_deg)
    return RowOffset(
        offset.behind_m * math.cos(p) - antenna_height_m * math.sin(p),
        offset.right_m * math.cos(r) - antenna_height_m * math.sin(r),
    )


def antenna_ground_shift(
    roll_deg: float, pitch_deg: float, antenna_height_m: float
) -> tuple[float, float]:
    """(forward, right) metres from the antenna to the ground point below it."""
    r, p = math.radians(roll_deg), math.radians(pitch_deg)
    return antenna_height_m * math.sin(p), -antenna_height_m * math.sin(r)


def baseline_attitude(
    baseline_pitch_deg: float, heading_offset_deg: float
) -> tuple[float | None, float | None]:
    """(roll, pitch) of the machine from the dual-antenna baseline's elevation.

    The UM982's #HEADINGA "pitch" is the elevation of its baseline (primary → secondary
    antenna); ``gnss.heading_offset_deg`` says where the baseline points: machine heading =
    baseline heading + offset, so the baseline points ``offset`` degrees left of forward.
    Its elevation is pitch·cos(offset) + roll·sin(offset) for small angles: side by side
    (offset ±90) it is ± the roll, fore and aft (0/180) ± the pitch. One baseline measures one
    tilt: the other is None (not measured), and whichever axis the baseline is closer to is
    the one reported.
    """
    off = math.radians(heading_offset_deg)
    s, c = math.sin(off), math.cos(off)
    if abs(s) >= abs(c):
        return baseline_pitch_deg / s, None
    return None, baseline_pitch_deg / c


# ---------------------------------------------------------------- trailed implement


def hitch_point(
    east: float, north: float, heading_deg: float, behind_m: float
) -> tuple[float, float]:
    """The tractor's hitch, ``behind_m`` behind the antenna on its centre line."""
    h = math.radians(heading_deg)
    return east - behind_m * math.sin(h), north - behind_m * math.cos(h)


def follow_hitch(
    axle: tuple[float, float], hitch: tuple[float, float], length_m: float
) -> tuple[float, float]:
    """Where a trailed implement's axle line (``length_m`` behind its hitch) goes when the
    hitch moves to ``hitch``: it is pulled straight towards it (a drawbar follows its hitch
    without side slip, the tractrix), staying ``length_m`` away. Exact in the limit of small
    steps; callers step a few centimetres at a time (``HITCH_STEP_M``)."""
    de, dn = hitch[0] - axle[0], hitch[1] - axle[1]
    d = math.hypot(de, dn)
    if d == 0.0:
        return axle
    return hitch[0] - length_m * de / d, hitch[1] - length_m * dn / d


def implement_heading(axle: tuple[float, float], hitch: tuple[float, float]) -> float:
    """The implement's heading: from its axle line towards its hitch."""
    return wrap_deg(math.degrees(math.atan2(hitch[0] - axle[0], hitch[1] - axle[1])))


def trailed_offset(
    tractor_heading_deg: float,
    implement_heading_deg: float,
    hitch_behind_antenna_m: float,
    outlets_behind_hitch_m: float,
    right_m: float,
) -> tuple[float, float]:
    """(east, north) from the antenna to an outlet of a trailed implement: back along the
    tractor to the hitch, then back along the implement, then across the implement."""
    ht, hi = math.radians(tractor_heading_deg), math.radians(implement_heading_deg)
    return (
        -hitch_behind_antenna_m * math.sin(ht) - outlets_behind_hitch_m * math.sin(hi)
        + right_m * math.cos(hi),
        -hitch_behind_antenna_m * math.cos(ht) - outlets_behind_hitch_m * math.cos(hi)
        - right_m * math.sin(hi),
    )


def articulation_on_circle_deg(
    radius_m: float, hitch_behind_antenna_m: float, outlets_behind_hitch_m: float
) -> float:
    """Steady-state tractor heading − implement heading with the antenna on a circle of
    ``radius_m``: the hitch runs on a circle of R_h = √(R² + b²), turned atan(b/R) from the
    antenna's tangent, and the implement's axle on one of √(R_h² − L²), a further asin(L/R_h)
    behind."""
    r_h = math.hypot(radius_m, hitch_behind_antenna_m)
    return math.degrees(
        math.atan2(hitch_behind_antenna_m, radius_m) + math.asin(outlets_behind_hitch_m / r_h)
    )


def wrap_deg(angle: float) -> float:
    """Angle in [0, 360); guards the float case where ``x % 360`` returns 360.0."""
    a = angle % 360.0
    return 0.0 if a >= 360.0 else a


def heading_diff(h0: float, h1: float) -> float:
    """Signed shortest turn from h0 to h1, in (−180, 180]."""
    d = (h1 - h0) % 360.0
    return d - 360.0 if d > 180.0 else d


def interpolate_heading(h0: float, h1: float, a: float) -> float:
    """Heading a fraction ``a`` of the way from h0 to h1 along the short arc (359 → 1 via 0)."""
    return wrap_deg(h0 + a * heading_diff(h0, h1))


# WGS84, as pymap3d's Ellipsoid.from_name("wgs84") defines it.
_WGS84_A = 6378137.0
_WGS84_B = 6356752.31424518
_WGS84_E2 = _WGS84_A**2 - _WGS84_B**2  # E² of You (2000)
# Below this |u| or distance from the polar axis (m) You's formula divides by ~0: use pymap3d.
_GEODETIC_FAST_MIN_M = 1000.0


@dataclass(frozen=True)
class LocalFrame:
    """A WGS84 ↔ local ENU tangent frame (pymap3d) around a fixed origin."""

    lat0: float
    lon0: float
    alt0: float = 0.0
    # origin in ECEF and the ENU→ECEF rotation, computed once (see to_geodetic)
    _origin: tuple[float, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        x0, y0, z0 = pymap3d.geodetic2ecef(self.lat0, self.lon0, self.alt0)
        la, lo = math.radians(self.lat0), math.radians(self.lon0)
        origin = (float(x0), float(y0), float(z0),
                  math.sin(la), math.cos(la), math.sin(lo), math.cos(lo))
        object.__setattr__(self, "_origin", origin)

    def to_enu(
        self, lat: float, lon: float, alt: float | None = None
    ) -> tuple[float, float, float]:
        e, n, u = pymap3d.geodetic2enu(
            lat, lon, self.alt0 if alt is None else alt, self.lat0, self.lon0, self.alt0
        )
        return float(e), float(n), float(u)

    @overload
    def _ecef(self, east: float, north: float, up: float) -> tuple[float, float, float]: ...
    @overload
    def _ecef(
        self, east: FloatArray, north: FloatArray, up: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray]: ...

    def _ecef(self, east: Any, north: Any, up: Any) -> tuple[Any, Any, Any]:
        """Local ENU → ECEF: the rotation both geodesy paths share (floats or arrays)."""
        x0, y0, z0, sin_la, cos_la, sin_lo, cos_lo = self._origin
        t = cos_la * up - sin_la * north
        z = z0 + sin_la * up + cos_la * north
        x = x0 + cos_lo * t - sin_lo * east
        y = y0 + sin_lo * t + cos_lo * east
        return x, y, z

    def to_geodetic(self, east: float, north: float, up: float = 0.0) -> tuple[float, float]:
        """pymap3d's ``enu2geodetic`` (You 2000, non-iterative) in scalar ``math``.

        Called once per seed: pymap3d on scalars goes through numpy (~150 µs a call, most
        of the daemon's CPU at 2 000 seeds/s); these are the same formulas on plain floats
        (~3 µs) and agree with pymap3d to ~1e-12° (tested). Near the poles, where the
        formula's special cases apply, pymap3d itself answers.
        """
        x, y, z = self._ecef(east, north, up)
        r2 = x * x + y * y + z * z
        e2 = _WGS84_E2
        u = math.sqrt(0.5 * (r2 - e2) + 0.5 * math.hypot(r2 - e2, 2.0 * math.sqrt(e2) * z))
        hxy = math.hypot(x, y)
        if u < _GEODETIC_FAST_MIN_M or hxy < _GEODETIC_FAST_MIN_M:
            lat, lon, _h = pymap3d.enu2geodetic(
                east, north, up, self.lat0, self.lon0, self.alt0
            )
            return float(lat), float(lon)
        hue = math.hypot(u, math.sqrt(e2))
        beta = math.atan(hue / u * z / hxy)
        beta += ((_WGS84_B * u - _WGS84_A * hue + e2) * math.sin(beta)) / (
            _WGS84_A * hue * 1 / math.cos(beta) - e2 * math.cos(beta)
        )
        lat = math.atan(_WGS84_A / _WGS84_B * math.tan(beta))
        return math.degrees(lat), math.degrees(math.atan2(y, x))

    def to_geodetic_many(
        self, east: FloatArray, north: FloatArray, up: FloatArray
    ) -> tuple[FloatArray, FloatArray, BoolArray]:
        """``to_geodetic`` over arrays, in numpy: (lat, lon, ok).

        The same formulas, operation for operation, so results agree with the scalar path to
        an ulp or two of numpy's libm (≪ 1e-12°). Where ``ok`` is False (near the poles or
        the Earth's centre) the values are meaningless: use the scalar ``to_geodetic``.
        """
        x, y, z = self._ecef(east, north, up)
        r2 = x * x + y * y + z * z
        e2 = _WGS84_E2
        u = np.sqrt(0.5 * (r2 - e2) + 0.5 * np.hypot(r2 - e2, 2.0 * math.sqrt(e2) * z))
        hxy = np.hypot(x, y)
        ok = (u >= _GEODETIC_FAST_MIN_M) & (hxy >= _GEODETIC_FAST_MIN_M)
        if not ok.all():
            u = np.where(ok, u, _GEODETIC_FAST_MIN_M)
            hxy = np.where(ok, hxy, _GEODETIC_FAST_MIN_M)
        hue = np.hypot(u, math.sqrt(e2))
        beta = np.arctan(hue / u * z / hxy)
        beta += ((_WGS84_B * u - _WGS84_A * hue + e2) * np.sin(beta)) / (
            _WGS84_A * hue * 1 / np.cos(beta) - e2 * np.cos(beta)
        )
        lat = np.arctan(_WGS84_A / _WGS84_B * np.tan(beta))
        return np.degrees(lat), np.degrees(np.arctan2(y, x)), ok


"""A positioned seed and the record it becomes, built without per-seed validation cost.

Owns :class:`Landing` (a seed's local-frame position, landing instant and stored row, its
``SeedDrop`` built only on demand) and ``_new_drop``, which skips pydantic validation when
the values already satisfy ``SeedDrop``'s schema (checked cheaply, falling back to the real
validator otherwise). The names with a leading underscore are private to this package: the
positioner's fast paths use them.

Separate because it is the boundary to the record model (``gateway.core.records``) and its
speed tricks concern the record, not the positioning.
"""

from __future__ import annotations

import math
from datetime import datetime

from gateway.core.records import (
    AttitudeSource,
    FixQuality,
    HeadingSource,
    PositionMethod,
    SeedDrop,
    SeedRow,
    drop_row,
    stated_accuracy_m,
    us_to_utc,
)
from gateway.recording.positioning.methods import FIX_RANK

_DROP_FIELDS = frozenset(SeedDrop.model_fields)
_object_new = object.__new__
_setattr = object.__setattr__
_FIX_NAMES = frozenset(FIX_RANK)
# SeedDrop's own bounds (gateway/core/records.py), checked before skipping its validation.
_DROP_MAX_ROW = 128


def _new_drop(
    row: int,
    utc: datetime,
    lat: float,
    lon: float,
    fix: FixQuality,
    speed_kmh: float,
    heading_deg: float | None,
    heading_source: HeadingSource,
    extrapolated: bool,
    method: PositionMethod,
    spacing_m: float | None,
    attitude: AttitudeSource = "none",
    roll_deg: float | None = None,
    pitch_deg: float | None = None,
    delay_ms: float | None = None,
    offset_east_m: float | None = None,
    offset_north_m: float | None = None,
) -> SeedDrop:
    """A ``SeedDrop`` without pydantic validation when the values already satisfy it.

    Validation is ~6 µs of the ~20 µs a seed costs, and every value here is valid by
    construction (wrapped headings, clamped speeds, hypot spacings, a geodetic conversion).
    The bounds and types are still checked, cheaply; anything odd (a NaN from a broken epoch,
    an int subclass) goes through the real validator and fails or coerces exactly as before.
    A test checks the result equals a validated drop.
    """
    if (
        type(row) is int and 1 <= row <= _DROP_MAX_ROW
        and type(lat) is float and -90.0 <= lat <= 90.0
        and type(lon) is float and -180.0 <= lon <= 180.0
        and type(speed_kmh) is float and speed_kmh >= 0.0
        and (heading_deg is None or (type(heading_deg) is float and 0.0 <= heading_deg < 360.0))
        and (spacing_m is None or (type(spacing_m) is float and spacing_m >= 0.0))
        and type(fix) is str and fix in _FIX_NAMES
        and (roll_deg is None or (type(roll_deg) is float and -90.0 <= roll_deg <= 90.0))
        and (pitch_deg is None or (type(pitch_deg) is float and -90.0 <= pitch_deg <= 90.0))
        and (delay_ms is None or type(delay_ms) is float)
        and (offset_east_m is None or type(offset_east_m) is float)
        and (offset_north_m is None or type(offset_north_m) is float)
    ):
        drop = _object_new(SeedDrop)
        _setattr(drop, "__dict__", {
            "row": row, "utc": utc, "lat": lat, "lon": lon, "fix": fix,
            "speed_kmh": speed_kmh, "heading_deg": heading_deg,
            "heading_source": heading_source, "extrapolated": extrapolated,
            "method": method, "spacing_m": spacing_m, "attitude": attitude,
            "roll_deg": roll_deg, "pitch_deg": pitch_deg, "delay_ms": delay_ms,
            "offset_east_m": offset_east_m, "offset_north_m": offset_north_m,
            "accuracy_m": stated_accuracy_m(fix, extrapolated),
        })
        _setattr(drop, "__pydantic_fields_set__", set(_DROP_FIELDS))
        _setattr(drop, "__pydantic_extra__", None)
        _setattr(drop, "__pydantic_private__", None)
        return drop
    return SeedDrop(
        row=row, utc=utc, lat=lat, lon=lon, fix=fix, speed_kmh=speed_kmh,
        heading_deg=heading_deg, heading_source=heading_source, extrapolated=extrapolated,
        method=method, spacing_m=spacing_m, attitude=attitude, roll_deg=roll_deg,
        pitch_deg=pitch_deg, delay_ms=delay_ms, offset_east_m=offset_east_m,
        offset_north_m=offset_north_m,
    )


def utc_us_of(ts: float) -> int:
    """``datetime.fromtimestamp(ts, UTC)`` as integer microseconds, rounded as CPython does."""
    frac, whole = math.modf(ts)
    us = round(frac * 1e6)  # half to even, like _PyTime_ROUND_HALF_EVEN
    return int(whole) * 1_000_000 + us


class Landing:
    """A positioned seed in the local frame, alongside the record it became.

    ``stored`` holds the record as the store writes it (a ``SeedRow``); ``drop`` (the
    ``SeedDrop``) is built from it on first access, so the daemon, which only stores rows,
    never builds one. Rows
    given to :meth:`_lazy` must already satisfy ``SeedDrop``'s schema (the positioner checks).
    """

    __slots__ = ("_drop", "east", "north", "stored", "t_land")

    def __init__(self, drop: SeedDrop, east: float, north: float, t_land: float) -> None:
        self._drop: SeedDrop | None = drop
        self.stored: SeedRow = drop_row(drop)
        self.east = east
        self.north = north
        self.t_land = t_land

    @classmethod
    def _lazy(cls, row: SeedRow, east: float, north: float, t_land: float) -> Landing:
        la = _object_new(cls)
        la._drop = None
        la.stored = row
        la.east = east
        la.north = north
        la.t_land = t_land
        return la

    @property
    def drop(self) -> SeedDrop:
        drop = self._drop
        if drop is None:
            (us, row, lat, lon, fix, speed, heading, source, extrap, method, spacing,
             attitude, roll, pitch, delay, off_e, off_n) = self.stored
            drop = _new_drop(
                row, us_to_utc(us), lat, lon, fix, speed, heading,
                source, extrap, method, spacing, attitude, roll, pitch, delay, off_e, off_n,
            )
            self._drop = drop
        return drop

    def _key(self) -> tuple[SeedRow, float, float, float]:
        return (self.stored, self.east, self.north, self.t_land)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Landing):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def __repr__(self) -> str:
        return (
            f"Landing(drop={self.drop!r}, east={self.east!r}, north={self.north!r}, "
            f"t_land={self.t_land!r})"
        )

"""A trailed implement's heading at each stored record, followed again from the records.

Re-positioning a stored seed (``survey.reposition``: ``sowgate export --reposition`` and the
survey fit) starts from the antenna at its landing instant, which every record keeps (its
position less ``offset_east_m`` / ``offset_north_m``). With a trailed implement
(``[positioning.hitch]``) that is not enough: the outlets follow the implement's own heading,
which lags the tractor's on every weave of the autosteer and every curve, and a rigid lever
arm along the tractor's heading puts them across by ``outlets_behind_hitch_m`` times the
articulation (0.4° of weave at 1.6 m: 11 mm, every seed). The records do not keep the
implement's heading, but they keep the antenna's track: :class:`ImplementTrack` pulls the
implement after the hitch along it again, record by record in stored order, exactly as the
positioner did epoch by epoch (``attitude.EpochAttitude.follow_hitch``, the same tractrix).

Where the track restarts (a jump of more than ``attitude.HITCH_RESET_M`` between records:
a raised turn, a gap in sowing) the implement restarts as the record says the positioner had
it (read back from its stored offset, which the positioner made with the implement it had
followed through the turn: a raised U-turn leaves it 1-2° off the tractor's heading for the
first metres, 25-50 mm across at the outlets), or straight behind the tractor where the
record was made with another hitch geometry. Separate from :mod:`.survey` because it is state
over the record stream, where the survey's functions are per record.
"""

from __future__ import annotations

import math

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning.attitude import EpochAttitude
from gateway.recording.positioning.geometry import (
    RowOffset,
    antenna_ground_shift,
    rotate_offset,
    row_offset,
    wrap_deg,
)

# WGS84, for the metres of a record's offset and of the track (a tangent plane at the first
# record: across a field of a few km the scale is off by under 1e-3, nothing for a tractrix)
_A = 6378137.0
_E2 = 6.69437999014e-3
# A record's stored outlet vector this much longer or shorter than the hitch geometry's was
# made with another geometry: its implement heading is not read back from it (m).
STORED_MISMATCH_M = 0.15
# ... nor one that would put the implement further than this off the tractor's heading (°).
STORED_MAX_ARTICULATION_DEG = 45.0


class ImplementTrack:
    """Feed it every stored record in stored order (``heading``); it answers the trailed
    implement's heading at each one (None without ``[positioning.hitch]``, or for a record
    that keeps no antenna offset or heading)."""

    def __init__(self, settings: PositioningSection,
                 made_with: PositioningSection | None = None) -> None:
        """``made_with``: the positioning the records were made with (the read-back at a
        restart needs its hitch, rows and lean); None: restart straight behind. Settings a
        survey calibration moved by a few centimetres read back a heading a fraction of a
        degree off, which decays over the wheels' distance like the turn's articulation."""
        self.hitch = settings.hitch
        self.made_with = made_with
        self._attitude = EpochAttitude(settings)
        self._origin: tuple[float, float, float, float] | None = None  # lat, lon, m/°lat, m/°lon

    def heading(self, record: SeedDrop) -> float | None:
        if (
            self.hitch is None or record.heading_deg is None
            or record.offset_east_m is None or record.offset_north_m is None
        ):
            return None
        if self._origin is None:
            phi = math.radians(record.lat)
            w = math.sqrt(1.0 - _E2 * math.sin(phi) ** 2)
            per_lat = math.radians(_A * (1.0 - _E2) / w**3)
            per_lon = math.radians(_A / w * math.cos(phi))
            self._origin = (record.lat, record.lon, per_lat, per_lon)
        lat0, lon0, per_lat, per_lon = self._origin
        east = (record.lon - lon0) * per_lon - record.offset_east_m
        north = (record.lat - lat0) * per_lat - record.offset_north_m
        made = self.made_with
        start = None
        if (made is not None and made.hitch is not None
                and self._attitude.restarts_hitch(east, north, record.heading_deg)):
            start = _stored_heading(record, made)
        return self._attitude.follow_hitch(east, north, record.heading_deg, start)


def _stored_heading(record: SeedDrop, made: PositioningSection) -> float | None:
    """The implement's heading the positioner placed ``record``'s seed with, read back
    from its stored offset (antenna → seed): less the antenna's lean and the tractor's
    hitch vector, the rest is the implement's outlet vector (``trailed_offset``), whose
    bearing less its angle on the implement is the implement's heading. None where the
    rest is not such a vector (records made with another hitch geometry, or mounted)."""
    hitch = made.hitch
    assert hitch is not None and record.heading_deg is not None
    assert record.offset_east_m is not None and record.offset_north_m is not None
    rows = len(made.lateral_offsets())
    right = row_offset(made, record.row).right_m if record.row <= rows else 0.0
    shift_e = shift_n = 0.0
    if record.attitude != "none" and (record.roll_deg is not None
                                      or record.pitch_deg is not None):
        roll, pitch = record.roll_deg or 0.0, record.pitch_deg or 0.0
        forward, sideways = antenna_ground_shift(
            roll, pitch, made.antenna_height_m - hitch.height_m)
        shift_e, shift_n = rotate_offset(RowOffset(-forward, sideways), record.heading_deg)
        right *= math.cos(math.radians(roll))
    h = math.radians(record.heading_deg)
    we = record.offset_east_m - shift_e + hitch.behind_antenna_m * math.sin(h)
    wn = record.offset_north_m - shift_n + hitch.behind_antenna_m * math.cos(h)
    length = hitch.outlets_behind_hitch_m
    if abs(math.hypot(we, wn) - math.hypot(length, right)) > STORED_MISMATCH_M:
        return None
    # the outlet vector is (forward -length, right) on the implement
    heading = wrap_deg(math.degrees(math.atan2(we, wn) - math.atan2(right, -length)))
    articulation = abs(wrap_deg(heading - record.heading_deg + 180.0) - 180.0)
    return None if articulation > STORED_MAX_ARTICULATION_DEG else heading

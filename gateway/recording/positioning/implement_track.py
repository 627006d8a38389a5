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
a raised turn, a gap in sowing) the implement restarts straight behind the tractor, where
the positioner had followed it through the turn: the first metres after lowering may differ
by the turn's left-over articulation. Separate from :mod:`.survey` because it is state over
the record stream, where the survey's functions are per record.
"""

from __future__ import annotations

import math

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning.attitude import EpochAttitude

# WGS84, for the metres of a record's offset and of the track (a tangent plane at the first
# record: across a field of a few km the scale is off by under 1e-3, nothing for a tractrix)
_A = 6378137.0
_E2 = 6.69437999014e-3


class ImplementTrack:
    """Feed it every stored record in stored order (``heading``); it answers the trailed
    implement's heading at each one (None without ``[positioning.hitch]``, or for a record
    that keeps no antenna offset or heading)."""

    def __init__(self, settings: PositioningSection) -> None:
        self.hitch = settings.hitch
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
        return self._attitude.follow_hitch(east, north, record.heading_deg)

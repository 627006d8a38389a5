"""The machine's attitude at each stored record, estimated again with the records after it.

Why: live, the positioner has only the epochs up to a seed's landing, so the roll and pitch
each record keeps (``roll_deg``, ``pitch_deg``) are what one epoch measured then. Both have a
cost a 2.5 m antenna turns into millimetres on the ground:

* the dual antenna's baseline elevation is noisy epoch to epoch (σ 0.1-0.2° for a 1 m
  baseline: 4-9 mm of lean at 2.5 m), while the ground the tractor rolls on changes its slope
  over metres, not between two epochs;
* the pitch from the track (``positioning.pitch_from_track_m``) is the antenna's climb over
  the last ``L`` metres: the slope at the window's middle, ``L/2`` behind the antenna. On
  rolling ground (a wave of a few cm over some 40 m tilts ±0.5°) that lag is a pitch error of
  a few tenths of a degree, 5-15 mm along the row at 2.5 m.

Re-positioning afterwards (``sowgate calibrate positions`` and ``export --reposition``) has the
records after each one too. :func:`smooth_attitude` gives every record the mean roll of the
records within ``ROLL_HALF_WINDOW_M`` of it along the track (the noise averaged, the ground's
slope left: a mean over ±1.5 m of a 40 m wave changes it by under 1 %), and, where the pitch
came from the track, the mean pitch of the records ``L/2`` further on (within
``PITCH_HALF_WINDOW_M``), whose windows are centred on it: the lag is gone. The first metres
of a track (the drive's start, after a float fix or a dropout), which the positioner sowed
without pitch (its window not yet filled: counted as level, up to 2.5 m · sin 1.5° = 65 mm
on a slope along the pass), get the nearest pitch ahead. The distance along
the track comes from the records' own speed and time; a gap in the records (a raised turn, a
stop of the metering) longer than ``GAP_S`` starts a new stretch, and no window reaches across.
Where a window holds no measured value the record keeps its own; a record that cannot be
re-positioned (no raw data) passes as stored and lends its attitude to none.

Separate from :mod:`.survey` (per-record functions) and :mod:`.implement_track` (state over
the stream): this one needs the records ahead, so it buffers a stretch of them.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import TypeVar

import numpy as np

from gateway.config.recording import PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning.geometry import FloatArray, baseline_attitude
from gateway.recording.positioning.survey import repositionable

# Half-widths (m along the track) of the means: short against the ground's undulations (tens
# of metres), long enough to average the baseline's per-epoch noise over many epochs.
ROLL_HALF_WINDOW_M = 1.5
PITCH_HALF_WINDOW_M = 1.0
# Records further apart than this (s) belong to separate stretches (turn, stop, outage).
GAP_S = 2.0
# A stretch is smoothed once it holds this many records (a day's store: bounded memory).
MAX_STRETCH = 200_000
KMH_PER_MS = 3.6

R = TypeVar("R", bound=SeedDrop)


def pitch_from_track(settings: PositioningSection, baseline_offset_deg: float) -> bool:
    """Whether the records' pitch came from the track's climb (the attitude source measures
    none: side-by-side antennas, or the inclinometer's roll), as ``SeedPositioner`` took it."""
    if settings.pitch_from_track_m <= 0.0:
        return False
    if settings.attitude_source == "inclinometer":
        return True
    if settings.attitude_source == "dual_antenna":
        return baseline_attitude(1.0, baseline_offset_deg)[1] is None
    return False


def _window_mean(s: FloatArray, values: FloatArray, centre: FloatArray,
                 half: float) -> FloatArray:
    """Mean of the finite ``values`` with ``s`` within ``half`` of each ``centre`` (``s``
    sorted); NaN where none."""
    finite = np.isfinite(values)
    total = np.concatenate(([0.0], np.cumsum(np.where(finite, values, 0.0))))
    count = np.concatenate(([0], np.cumsum(finite)))
    lo = np.searchsorted(s, centre - half, side="left")
    hi = np.searchsorted(s, centre + half, side="right")
    n = count[hi] - count[lo]
    out: FloatArray = np.where(n > 0, (total[hi] - total[lo]) / np.maximum(n, 1), np.nan)
    return out


def _smooth_stretch(records: Sequence[R], lag_m: float) -> list[R]:
    t = np.array([r.utc.timestamp() for r in records], dtype=np.float64)
    order = np.argsort(t, kind="stable")
    ts = t[order]
    v = np.array([records[i].speed_kmh for i in order], dtype=np.float64) / KMH_PER_MS
    step = np.diff(ts) * 0.5 * (v[1:] + v[:-1])
    s = np.concatenate(([0.0], np.cumsum(step)))
    # only what re-positioning reads: a record that cannot be re-positioned stays as stored
    measured = [r.attitude != "none" and repositionable(r) for r in records]
    roll = np.array([np.nan if r.roll_deg is None or not m else r.roll_deg
                     for r, m in zip(records, measured, strict=True)], dtype=np.float64)[order]
    pitch = np.array([np.nan if r.pitch_deg is None or not m else r.pitch_deg
                      for r, m in zip(records, measured, strict=True)], dtype=np.float64)[order]
    new_roll = _window_mean(s, roll, s, ROLL_HALF_WINDOW_M)
    new_pitch = _window_mean(s, pitch, s + lag_m, PITCH_HALF_WINDOW_M)
    if lag_m > 0.0:
        # the track's first metres (a start, an outage) had no pitch yet: the nearest
        # window ahead, within one track window of the centred one
        have = np.flatnonzero(np.isfinite(pitch))
        if len(have):
            near = have[np.minimum(np.searchsorted(s[have], s + lag_m), len(have) - 1)]
            ahead = np.abs(s[near] - (s + lag_m)) <= 2.0 * lag_m
            new_pitch = np.where(np.isnan(new_pitch) & ahead, pitch[near], new_pitch)
    out = list(records)
    for k, i in enumerate(order.tolist()):
        r = records[i]
        update: dict[str, float] = {}
        if r.roll_deg is not None and measured[i] and np.isfinite(new_roll[k]):
            update["roll_deg"] = float(new_roll[k])
        if measured[i] and np.isfinite(new_pitch[k]) and (r.pitch_deg is not None
                                                           or lag_m > 0.0):
            update["pitch_deg"] = float(new_pitch[k])
        if update:
            out[i] = r.model_copy(update=update)
    return out


def smooth_attitude(records: Iterable[R], settings: PositioningSection,
                    baseline_offset_deg: float = 0.0) -> Iterator[R]:
    """``records`` (in stored order) again, each with its roll and pitch estimated from the
    records around it (module docstring); ``baseline_offset_deg``: ``gnss.heading_offset_deg``
    (whether the pitch came from the track). Records without a measured attitude pass as
    they are."""
    lag_m = settings.pitch_from_track_m / 2.0 if pitch_from_track(
        settings, baseline_offset_deg) else 0.0
    stretch: list[R] = []
    newest = None
    for r in records:
        t = r.utc.timestamp()
        if stretch and (len(stretch) >= MAX_STRETCH
                        or (newest is not None and t - newest > GAP_S)):
            yield from _smooth_stretch(stretch, lag_m)
            stretch = []
            newest = None
        stretch.append(r)
        newest = t if newest is None else max(newest, t)
    if stretch:
        yield from _smooth_stretch(stretch, lag_m)

"""Receiver time to host time: when, on ``time.monotonic()``, each GNSS epoch was true.

Owns :class:`ClockMap`, the estimate of the offset between the receiver's UTC stamps and the
host's monotonic clock from the (one-sided, jittery) arrival times of the epochs.

Separate because it is the one piece of timing the interpolated method rests on (paper C
absorbs the same uncertainty as a constant), it has its own statistics (a windowed minimum)
and it needs no geometry at all. Which stamps it is given is decided before, by
:mod:`.gnss_time` (outliers rejected, a time step re-establishes it through :meth:`reset`).
"""

from __future__ import annotations

import itertools
from collections import deque

# Epochs over which the UTC↔monotonic offset is estimated (10 s at 10 Hz; drift ≪ 1 ms).
CLOCK_WINDOW_EPOCHS = 100


class ClockMap:
    """Maps receiver UTC to the host monotonic clock: ``t_mono = utc + offset``.

    Each epoch's first sentence reaches the host at ``instant + L + J``: ``L`` is the receiver's
    fixed output latency (solution computation plus the serial transmission of the first
    sentence, from config — it cannot be observed from the host side alone) and ``J ≥ 0`` is
    jitter (UART/USB polling, scheduler wake-ups, the occasional burst). The arrival time of
    any single epoch is therefore late by an unknown J, up to tens of ms, which at 12 km/h is
    tens of mm. The UTC stamp, on the other hand, is exact to the receiver's PPS.

    So the offset is estimated as ``min over recent epochs of (t_mono − utc) − L``. Because J
    is one-sided, the minimum is the right statistic: it converges to ``offset + min J`` within
    a few epochs, ignores heavy tails, whereas a mean would be biased by E[J] and dragged
    around by bursts. The window (:data:`CLOCK_WINDOW_EPOCHS`) is short enough that crystal
    drift between host and receiver (≤ 50 ppm → 0.5 ms per 10 s) does not accumulate, and long
    enough to contain some near-zero-jitter epochs. The result is timing good to about 1 ms
    instead of the whole fix-age uncertainty that paper C has to absorb as a constant T/2.
    """

    def __init__(self, latency_s: float, window: int = CLOCK_WINDOW_EPOCHS) -> None:
        self.latency_s = latency_s
        self._samples: deque[float] = deque(maxlen=window)
        # min(self._samples), kept up to date by observe(): every seed maps several times
        # and the window only changes once per epoch
        self._min_raw = 0.0

    def observe(self, t_mono: float, utc_s: float) -> None:
        """An epoch the time guard accepted (``gnss_time.GnssTimeGuard``)."""
        self._samples.append(t_mono - utc_s)
        self._min_raw = min(self._samples)

    def reset(self) -> None:
        """The receiver's time stepped: the old offsets describe another clock."""
        self._samples.clear()
        self._min_raw = 0.0

    def would_change(self, t_mono: float, utc_s: float) -> bool:
        """Would ``observe(t_mono, utc_s)`` move the offset (a new minimum, or the minimum
        leaving the window)?"""
        samples = self._samples
        if not samples:
            return True
        raw = t_mono - utc_s
        if raw < self._min_raw:
            return True
        if len(samples) == samples.maxlen and samples[0] == self._min_raw:
            return min(min(itertools.islice(samples, 1, None)), raw) != self._min_raw
        return False

    @property
    def ready(self) -> bool:
        return bool(self._samples)

    @property
    def offset_s(self) -> float:
        if not self._samples:
            raise ValueError("no epoch observed yet")
        return self._min_raw - self.latency_s

    def mono_of_utc(self, utc_s: float) -> float:
        return utc_s + self.offset_s

    def utc_of_mono(self, t_mono: float) -> float:
        return t_mono - self.offset_s

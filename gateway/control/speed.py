"""Ground speed: paper A's moving-average filter and the trend filter.

The radar is polled at 3 Hz and averaged over the last 12 samples (paper A); while fewer than
12 exist the mean is over what there is, so the controller has a speed from the first reply.
The default ``trend`` filter fits a line instead, bounded by the machine's acceleration
(:class:`TrendFilter`). Paper A's Doppler relation (eq. 1) turns a radar's shift into km/h
where the radar's registers are decoded: ``protocol.registers.doppler_to_kmh``.
"""

from __future__ import annotations

from collections import deque


class MovingAverage:
    """Mean of the last ``n`` samples; ``reset`` when the source is lost so stale speed dies."""

    def __init__(self, n: int = 12) -> None:
        if n < 1:
            raise ValueError("moving average needs n >= 1")
        self._samples: deque[float] = deque(maxlen=n)

    def add(self, value: float, t: float = 0.0) -> float:
        self._samples.append(value)
        return self.value

    @property
    def value(self) -> float:
        # n is small (12): summing afresh avoids the drift of a running sum
        return sum(self._samples) / len(self._samples) if self._samples else 0.0

    def __len__(self) -> int:
        return len(self._samples)

    def reset(self) -> None:
        self._samples.clear()


class Hysteresis:
    """A boolean that turns on above ``on_at`` and off below ``off_at`` (on_at >= off_at)."""

    def __init__(self, on_at: float, off_at: float, initial: bool | None = None) -> None:
        if on_at < off_at:
            raise ValueError("on_at must be >= off_at")
        self.on_at = on_at
        self.off_at = off_at
        self.state = initial

    def update(self, value: float) -> bool:
        if self.state is None:
            self.state = value >= self.on_at
        elif self.state and value < self.off_at:
            self.state = False
        elif not self.state and value >= self.on_at:
            self.state = True
        return self.state


KMH_PER_MPS = 3.6
# How far one reading may differ from the filtered speed beyond what the machine's acceleration
# allows before it counts as a step (see TrendFilter): 15 % of the speed, at least 0.5 km/h.
# Paper A's radar scatters by up to 4.12 % (Table 4), so ordinary noise is 3.6 sigma inside
# this even before the acceleration allowance (1.8 km/h per 3 Hz poll at 1.5 m/s2) is added.
STEP_MARGIN_FRACTION = 0.15
STEP_MARGIN_MIN_KMH = 0.5


class TrendFilter:
    """Least-squares line through the last ``n`` (t, v) samples, read at the newest sample.

    A moving average of 12 samples at 3 Hz lags a ramp by ~1.8 s, so a seeder accelerating
    out of a headland under-doses for several metres. The fitted line has no lag on a ramp
    and still averages noise over the same window (about twice the noise of the plain mean
    on a single reading, which the metering drive smooths anyway).

    A line fitted to a *step* extrapolates it into a slope no tractor can make: a radar that
    read 0 for 1 s at 8 km/h and then 8 again gave 10.2 km/h (93.6 % motor duty instead of
    73 %), and a ramp remembered across an 8 s gap of failed polls gave more. So the line may
    only say what a machine that accelerates at most ``max_accel_mps2`` can do:

    * the fitted slope is clamped to +/- ``max_accel_mps2``;
    * the window restarts (only the new reading is kept) when a reading differs from the
      filtered speed by more than that acceleration allows since the previous reading plus
      a noise margin (``STEP_MARGIN_*``): the readings before a step describe something the
      machine cannot have become, so a line through both sides means nothing;
    * the window restarts when no reading arrived for longer than ``restart_after_s`` (the
      source was lost; what it said before says nothing about now), and when the caller
      drops a glitch reading (:meth:`reset`).

    After a restart the output is the mean of what there is until half the window exists
    (6 readings, 2 s at 3 Hz; 3 readings when the filter is new): a slope through 3–5 noisy
    readings is mostly noise, and read at the newest reading it is multiplied by half their
    span. With paper A's radar scatter and the poll jitter of a loaded box, the 3-reading line
    overshot a return to 8 km/h by up to 6 % (the fault matrix's radar_speed_gap_1s row); the
    mean of a few readings cannot overshoot what they read. Restarts follow steps and gaps,
    not ramps, so a pull-away from a standstill keeps the line (no restart: it is reachable).
    """

    def __init__(
        self, n: int = 12, *, max_accel_mps2: float = 1.5, restart_after_s: float = 2.0
    ) -> None:
        if n < 2:
            raise ValueError("trend filter needs n >= 2")
        if not max_accel_mps2 > 0.0:
            raise ValueError("trend filter needs max_accel_mps2 > 0")
        if not restart_after_s > 0.0:
            raise ValueError("trend filter needs restart_after_s > 0")
        self._samples: deque[tuple[float, float]] = deque(maxlen=n)
        self.max_slope_kmh_per_s = max_accel_mps2 * KMH_PER_MPS
        self.restart_after_s = restart_after_s
        self.restarts = 0  # window restarts after a gap or a step (for tests and diagnostics)
        # readings before the line is used: 3 when new, half the window after a restart
        self._line_from = 3
        self._line_after_restart = max(3, n // 2)

    def add(self, value: float, t: float) -> float:
        if self._samples:
            last_t = self._samples[-1][0]
            dt = t - last_t
            estimate = self.value
            reachable = (
                self.max_slope_kmh_per_s * max(0.0, dt)
                + max(STEP_MARGIN_MIN_KMH, STEP_MARGIN_FRACTION * abs(estimate))
            )
            if dt > self.restart_after_s or dt < 0.0 or abs(value - estimate) > reachable:
                self._samples.clear()
                self.restarts += 1
                self._line_from = self._line_after_restart
        self._samples.append((t, value))
        return self.value

    @property
    def value(self) -> float:
        k = len(self._samples)
        if k == 0:
            return 0.0
        if k < self._line_from:
            return sum(v for _, v in self._samples) / k
        t_mean = sum(t for t, _ in self._samples) / k
        v_mean = sum(v for _, v in self._samples) / k
        stt = sum((t - t_mean) ** 2 for t, _ in self._samples)
        if stt <= 0.0:
            return v_mean
        slope = sum((t - t_mean) * (v - v_mean) for t, v in self._samples) / stt
        bound = self.max_slope_kmh_per_s
        slope = max(-bound, min(bound, slope))
        return max(0.0, v_mean + slope * (self._samples[-1][0] - t_mean))

    def __len__(self) -> int:
        return len(self._samples)

    def reset(self) -> None:
        self._samples.clear()
        self._line_from = self._line_after_restart

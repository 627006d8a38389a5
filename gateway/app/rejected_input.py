"""Input the daemon received and did not use, per device and reason: counted, published, summed up.

Every driver keeps going through bad input and counts it per reason (``GnssStats.rejected``,
``HmiLinkStats.rejected_by_reason``, ``SeedSensorStats.rejected_by_reason``) and the recorder
counts the seed edges beyond the plausible rate. Without this module those numbers lived only
inside the process: the state payload carries them now (``state.rejected``, see
docs/mqtt.md), and once a minute, if anything was rejected since the last time, one INFO line
sums up what and how much, so the journal tells the story of a flaky cable without a line per
bad frame (the drivers' own warnings are rate-limited, see ``drivers.log_limit``).
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Mapping
from typing import Any, Protocol

from gateway.state import RejectedCounts

log = logging.getLogger(__name__)

SUMMARY_INTERVAL_S = 60.0
IMPLAUSIBLE_RATE = "implausible_rate"  # seed_sensors reason: edges beyond the row limit


class _HasStats(Protocol):
    @property
    def stats(self) -> Any: ...


class RejectedInputs:
    """Reads the counters of whichever devices exist; ``counts`` is ``state.rejected``."""

    def __init__(
        self,
        *,
        gnss: _HasStats | None = None,
        hmi: _HasStats | None = None,
        seed_sensors: _HasStats | None = None,
        recorder: Any = None,
        interval_s: float = SUMMARY_INTERVAL_S,
    ) -> None:
        self.gnss = gnss
        self.hmi = hmi
        self.seed_sensors = seed_sensors
        self.recorder = recorder
        self.interval_s = interval_s
        self._last_logged = self.counts()

    def counts(self) -> RejectedCounts:
        """Totals since start: GNSS lines, touchscreen frames and seed-sensor lines or edges
        per reason, and the bytes dropped from overlong GNSS lines."""
        gnss: dict[str, int] = {}
        discarded = 0
        if self.gnss is not None:
            stats = self.gnss.stats
            gnss, discarded = dict(stats.rejected), stats.discarded_bytes
        hmi = dict(self.hmi.stats.rejected_by_reason) if self.hmi is not None else {}
        seeds: dict[str, int] = {}
        if self.seed_sensors is not None:
            seeds = dict(self.seed_sensors.stats.rejected_by_reason)
        if self.recorder is not None and self.recorder.plausibility.implausible_total:
            seeds[IMPLAUSIBLE_RATE] = self.recorder.plausibility.implausible_total
        return RejectedCounts(
            gnss=gnss, gnss_discarded_bytes=discarded, hmi=hmi, seed_sensors=seeds
        )

    def summary(self) -> str | None:
        """What was rejected since the last summary, as one line; None if nothing was."""
        now = self.counts()
        before, self._last_logged = self._last_logged, now
        parts = []
        devices: tuple[tuple[str, Mapping[str, int], Mapping[str, int]], ...] = (
            ("gnss", now.gnss, before.gnss),
            ("hmi", now.hmi, before.hmi),
            ("seed_sensors", now.seed_sensors, before.seed_sensors),
        )
        for device, counts, counted in devices:
            grown = {
                reason: n - counted.get(reason, 0)
                for reason, n in sorted(counts.items())
                if n > counted.get(reason, 0)
            }
            if grown:
                parts.append(f"{device}: " + ", ".join(f"{r} {n}" for r, n in grown.items()))
        discarded = now.gnss_discarded_bytes - before.gnss_discarded_bytes
        if discarded > 0:
            parts.append(f"gnss bytes discarded (binary output?): {discarded}")
        return "; ".join(parts) or None

    async def run(self) -> None:
        """Log ``summary`` at INFO every ``interval_s`` when there is one."""
        while True:
            await asyncio.sleep(self.interval_s)
            line = self.summary()
            if line is not None:
                log.info(
                    "input rejected in the last %.0f s: %s (totals in state.rejected)",
                    self.interval_s, line,
                )

"""Capped, jittered exponential backoff shared by every reconnecting driver.

Full jitter keeps a fleet of boxes (or several drivers on one box) from retrying in lockstep
after a shared outage such as a broker restart or a bus brown-out.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field


@dataclass
class Backoff:
    initial_s: float = 0.1
    cap_s: float = 10.0
    factor: float = 2.0
    rng: random.Random = field(default_factory=random.Random)
    _attempt: int = 0

    def next_delay(self) -> float:
        """Delay before the next retry: uniform in [ceiling/2, ceiling], ceiling capped."""
        ceiling = min(self.cap_s, self.initial_s * self.factor**self._attempt)
        self._attempt += 1
        return self.rng.uniform(ceiling / 2.0, ceiling)

    def reset(self) -> None:
        self._attempt = 0

    @property
    def attempts(self) -> int:
        return self._attempt

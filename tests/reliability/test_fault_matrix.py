"""Nothing lost, nothing silent: each row of the fault matrix holds its invariant.

The faults are injected and measured by ``tests.reliability.matrix`` (see the ``fault_matrix``
fixture); this file judges them, one test per row, and the table in docs/reliability.md is
rendered from the same measurements.
"""

from __future__ import annotations

import pytest

from tests.reliability.harness import RowResult
from tests.reliability.rows import FARM_FULL_SCALE, FARM_OFFLINE_S, ROWS, ROWS_BY_NAME

# the campaign (about three minutes, the broker outage alone one) runs in the first row's setup
CAMPAIGN_TIMEOUT_S = 600 + (int(FARM_OFFLINE_S) + 300 if FARM_FULL_SCALE else 0)


@pytest.mark.slow
@pytest.mark.timeout(CAMPAIGN_TIMEOUT_S)
@pytest.mark.parametrize("row", [r.name for r in ROWS])
def test_fault_matrix(row: str, fault_matrix: dict[str, RowResult]) -> None:
    result = fault_matrix[row]
    spec = ROWS_BY_NAME[row]
    assert not result.problems, (
        f"{row}: invariant broken ({spec.invariant}):\n- " + "\n- ".join(result.problems)
    )

"""Runs the fault matrix once per session and writes its table when the session ends.

The rows' groups run concurrently in one event loop before the first row is judged (the
broker outage alone lasts a minute); each ``test_fault_matrix[row]`` then checks its row.
Only the groups of the rows selected (``-k``) run. The table goes to
``--reliability-report`` (default ``build/reliability.md``, not tracked);
``make reliability`` points it at docs/reliability.md.
"""

from __future__ import annotations

import asyncio
import os
import shlex
import sys
import tempfile
from pathlib import Path

import pytest

from tests.reliability.harness import RowResult
from tests.reliability.matrix import run_campaign

REPO = Path(__file__).resolve().parents[2]
DEFAULT_REPORT = REPO / "build" / "reliability.md"
_results = pytest.StashKey[dict[str, RowResult]]()


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--reliability-report",
        default=str(DEFAULT_REPORT),
        help="where the fault matrix table is written (default: build/reliability.md)",
    )


@pytest.fixture(scope="session")
def fault_matrix(request: pytest.FixtureRequest) -> dict[str, RowResult]:
    """Every selected row's measurements (the campaign runs on first use)."""
    wanted = [
        item.callspec.params["row"]
        for item in request.session.items
        # other tests in the suite have a parameter called "row" too (planter rows)
        if getattr(item, "originalname", None) == "test_fault_matrix"
        and "row" in item.callspec.params
    ]
    with tempfile.TemporaryDirectory(prefix="sowgate-reliability-") as tmp:
        results = asyncio.run(run_campaign(Path(tmp), wanted))
    request.config.stash[_results] = results
    return results


def pytest_sessionfinish(session: pytest.Session) -> None:
    results = session.config.stash.get(_results, None)
    if not results:
        return
    from tests.reliability.report import render

    path = Path(session.config.getoption("--reliability-report"))
    if not path.is_absolute():
        path = Path(session.config.invocation_params.dir) / path
    path.parent.mkdir(parents=True, exist_ok=True)
    command = os.environ.get("SOWGATE_RELIABILITY_COMMAND") or "pytest " + shlex.join(
        session.config.invocation_params.args
    )
    path.write_text(render(results, command))
    print(f"\nfault matrix written to {path}", file=sys.stderr)

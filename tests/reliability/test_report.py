"""The table in docs/reliability.md is rendered from a run's results, failures spelled out."""

from __future__ import annotations

from tests.reliability.harness import RowResult
from tests.reliability.report import render


def test_the_table_shows_each_row_its_figures_and_why_a_row_fails() -> None:
    results = {
        "broker_down_60s": RowResult(lost="0 of 10 edges not stored", recovery="1.0 s",
                                     daemon="exited 0", tracebacks="0"),
        "disk_full_20s": RowResult(lost="7 of 10 edges not stored", daemon="exited 0",
                                   tracebacks="0",
                                   problems=["7 of 10 seed edges lost in /tmp/sowgate-"
                                             "reliability-abc/disk | full"]),
    }
    text = render(results, "make reliability")
    assert "- command: `make reliability`" in text
    assert "**Result: 1 of 2 rows hold their invariant.**" in text
    rows = [line for line in text.splitlines() if line.startswith("| `")]
    assert [r.split("|")[1].strip() for r in rows] == ["`broker_down_60s`", "`disk_full_20s`"]
    assert rows[0].rstrip().endswith("| ok |") and "| 1.0 s |" in rows[0]
    assert rows[1].rstrip().endswith("| **FAIL** |")
    # why it failed, with the scratch directory and the table's separator made harmless
    assert "  - 7 of 10 seed edges lost in <tmp>/disk \\| full" in text

"""The ``sowgate export`` and ``sowgate report`` the demo prints, run exactly as printed, give
the same per-row spacing quality: the export has no ``--config``, and judges the spacings
against the target the daemon ran with (kept in the store's run marker), as the report does."""

from __future__ import annotations

import csv
import json
import re
import shlex
from pathlib import Path

import pytest

from gateway.app.cli import main as cli_main
from tests.helpers import run_sowgate, sowgate_env

ROOT = Path(__file__).resolve().parents[2]


def printed_command(out: str, name: str) -> list[str]:
    """The arguments after ``sowgate`` of the printed ``sowgate NAME ...`` next step."""
    m = re.search(rf"\S*sowgate ({name} [^\n]*)", out)
    assert m is not None, out
    return shlex.split(m.group(1))


def test_the_printed_export_and_report_give_the_same_per_row_numbers(tmp_path: Path) -> None:
    proc = run_sowgate(
        "demo", "--no-tui", "--duration", "8",
        cwd=tmp_path, timeout=120, env=sowgate_env(env={"PYTHONPATH": str(ROOT)}, clean=True),
    )
    assert proc.returncode == 0, proc.stderr
    export = printed_command(proc.stdout, "export")
    report = printed_command(proc.stdout, "report")
    assert "--config" not in export  # the case the target must come from the store
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp_path)  # the paths are printed relative to where the demo ran
        assert cli_main(export) == 0
        assert cli_main(report) == 0
    seeds_csv = tmp_path / export[export.index("--output") + 1]
    with Path(f"{seeds_csv}.quality.csv").open(encoding="utf-8") as f:
        exported = {row["row"]: row for row in csv.DictReader(f)}
    html = (tmp_path / report[report.index("--output") + 1]).read_text(encoding="utf-8")
    m = re.search(r'id="report-data">(.*?)</script>', html, re.S)
    assert m is not None
    reported = json.loads(m.group(1).replace("<\\/", "</"))["quality"]
    assert exported and set(exported) == set(reported)
    for row, q in reported.items():
        assert q["x_ref_m"] == pytest.approx(0.2)  # the demo's target, not a row's median
        for key in ("x_ref_m", "multiples_index", "miss_index", "quality_of_feed_index",
                    "precision"):
            if q[key] is None:
                assert exported[row][key] == ""
            else:
                assert float(exported[row][key]) == pytest.approx(q[key], rel=1e-12), (row, key)

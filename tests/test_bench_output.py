"""A partial run writes its figures to an untracked file; only ``make bench`` (every benchmark,
``--output docs/benchmarks.md``) rewrites the published page, which says it is generated."""

from __future__ import annotations

import subprocess
import sys
import types
from pathlib import Path

import pytest

import benchmarks.__main__ as bench

REPO = Path(__file__).resolve().parents[1]
PUBLISHED = REPO / "docs" / "benchmarks.md"


def test_the_default_output_is_ignored_by_git_and_is_not_the_published_page() -> None:
    assert bench.DEFAULT_OUT != PUBLISHED
    ignored = subprocess.run(["git", "check-ignore", "-q", str(bench.DEFAULT_OUT)], cwd=REPO)
    assert ignored.returncode == 0, f"{bench.DEFAULT_OUT} is not in .gitignore"
    tracked = subprocess.run(["git", "ls-files", "--error-unmatch", str(PUBLISHED)], cwd=REPO,
                             capture_output=True)
    assert tracked.returncode == 0  # the published page stays in the repository


def test_a_run_writes_where_it_is_told_and_leaves_the_published_page_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    fake = types.ModuleType("benchmarks.bench_fake")
    fake.run = lambda: {"markdown": "42 seeds per second"}  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "benchmarks.bench_fake", fake)
    monkeypatch.setattr(bench, "BENCHMARKS", [("bench_fake", "a fake benchmark")])
    before = PUBLISHED.read_bytes()
    out = tmp_path / "figures.md"
    assert bench.main(["--output", str(out)]) == 0
    text = out.read_text()
    assert "### a fake benchmark" in text and "42 seeds per second" in text
    assert "make bench" in text and "Generated" in text  # the page says how it is made
    assert PUBLISHED.read_bytes() == before

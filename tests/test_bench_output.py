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


def test_an_update_replaces_only_the_named_sections_and_stamps_each_with_its_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    figures = {"bench_a": "1 seed per second", "bench_b": "2 seeds per second"}
    for name in figures:
        fake = types.ModuleType(f"benchmarks.{name}")
        fake.run = lambda name=name: {"markdown": figures[name]}  # type: ignore[attr-defined]
        monkeypatch.setitem(sys.modules, f"benchmarks.{name}", fake)
    monkeypatch.setattr(bench, "BENCHMARKS", [("bench_a", "benchmark A"), ("bench_b", "B")])
    page = tmp_path / "page.md"
    assert bench.main(["--output", str(page)]) == 0
    first = bench.sections_of(page.read_text())
    assert list(first) == ["bench_a", "bench_b"]
    assert all("_Run " in text for text in first.values())  # each section says its run

    figures["bench_b"] = "3 seeds per second"
    figures["bench_a"] = "changed, but not re-run"
    assert bench.main(["--update", str(page), "bench_b"]) == 0
    after = bench.sections_of(page.read_text())
    assert after["bench_a"] == first["bench_a"]  # kept, byte for byte
    assert "3 seeds per second" in after["bench_b"] and "2 seeds" not in after["bench_b"]
    assert "different runs" in page.read_text()


def test_an_update_refuses_a_page_it_cannot_split(tmp_path: Path) -> None:
    page = tmp_path / "page.md"
    page.write_text("# figures\n\n### hand-made\n\n1 seed\n")
    with pytest.raises(SystemExit) as stop:
        bench.main(["--update", str(page), "bench_rate"])
    assert stop.value.code == 2
    assert page.read_text() == "# figures\n\n### hand-made\n\n1 seed\n"

"""``make bench``: run every benchmark and write their figures to ``docs/benchmarks.md``.

Each benchmark module exposes ``run() -> dict`` with a ``markdown`` entry; every figure is a
ratio against a baseline measured in the same run, so numbers stay comparable across machines.

docs/benchmarks.md is a generated page, meant to change with every full run (``make bench``
passes ``--output docs/benchmarks.md``); review its diff and commit it. A run of a few
benchmarks alone writes to ``benchmarks/latest.md`` (ignored by git) by default, so it never
leaves the published page with only some of its sections.

    python -m benchmarks [--output FILE] [bench_rate bench_store ...]
    python -m benchmarks --update docs/benchmarks.md bench_ingest ...

``--update`` re-runs only the named benchmarks and replaces their sections of an existing page,
keeping the others. Every section starts with a marker that names its benchmark, the run's
date and commit (``<!-- bench: bench_rate 2026-11-24 11:55 UTC abc1234 -->``, shown as a line
under its heading), so a page whose sections come from different runs says so for each.
"""

from __future__ import annotations

import argparse
import importlib
import platform
import re
import subprocess
import sys
import time
import traceback
from datetime import UTC, datetime
from pathlib import Path

from rich.console import Console
from rich.progress import Progress

BENCHMARKS = [
    ("bench_rate", "applied-rate error (paper A)"),
    ("bench_latency", "control latency"),
    ("bench_positioning", "seed position error (paper C)"),
    ("bench_store", "record store throughput"),
    ("bench_held_records", "records held while the disk is full"),
    ("bench_mqtt", "MQTT outbox throughput, control latency under load, RSS/CPU"),
    ("bench_cpu", "daemon CPU per seed record, counted (callgrind)"),
    ("bench_multichannel", "multi-channel metering (paper B)"),
    ("bench_dashboard", "dashboard seed map render time (headless chromium)"),
    ("bench_report", "field report and export on a day-sized store"),
    ("bench_fleet_dashboard", "fleet dashboard: a day of 1 M seeds from the farm database"),
    ("bench_ingest", "farm server: ten cabs through mosquitto into PostgreSQL"),
]

DEFAULT_OUT = Path(__file__).resolve().parent / "latest.md"
_MARKER = re.compile(r"^<!-- bench: (\w+) (.*?) -->$", re.MULTILINE)


def _commit() -> str:
    """The checkout's commit (with ``+dirty`` when it has uncommitted changes), or ``?``."""
    here = Path(__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, check=True,
                              capture_output=True, text=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=here, capture_output=True, text=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "?"
    return head + ("+dirty" if dirty else "")


def _stamped(module: str, stamp: str, text: str) -> str:
    """A section with its marker line first and a visible run line under its heading."""
    heading, _, body = text.partition("\n")
    return (f"<!-- bench: {module} {stamp} -->\n{heading}\n\n_Run {stamp}._\n"
            f"{body.rstrip()}\n")


def sections_of(page: str) -> dict[str, str]:
    """The marked sections of a generated page, by benchmark module (in page order)."""
    marks = list(_MARKER.finditer(page))
    return {m.group(1): page[m.start(): marks[i + 1].start() if i + 1 < len(marks)
                             else len(page)].rstrip() + "\n"
            for i, m in enumerate(marks)}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUT,
                        help="markdown file to write (default: benchmarks/latest.md, untracked)")
    parser.add_argument("--update", type=Path, default=None, metavar="PAGE",
                        help="re-run only the named benchmarks and replace their sections of "
                             "this generated page, keeping the others")
    parser.add_argument("only", nargs="*", help="benchmark modules to run (default: all)")
    args = parser.parse_args(argv)
    out_path: Path = args.update or args.output
    only = set(args.only)
    unknown = only - {m for m, _ in BENCHMARKS}
    if unknown:
        parser.error(f"unknown benchmark(s): {', '.join(sorted(unknown))}")
    kept: dict[str, str] = {}
    if args.update is not None:
        if not only:
            parser.error("--update needs the benchmarks to re-run (make bench runs them all)")
        if not args.update.is_file():
            parser.error(f"--update {args.update}: no such page (make bench writes it first)")
        kept = sections_of(args.update.read_text())
        if not kept:
            parser.error(f"--update {args.update}: the page has no section markers "
                         "(written before they existed): run make bench once")
    stamp = f"{datetime.now(UTC):%Y-%m-%d %H:%M} UTC at {_commit()}"
    console = Console(stderr=True)
    sections: dict[str, str] = {}
    failed = 0
    with Progress(console=console) as progress:
        todo = [(m, d) for m, d in BENCHMARKS if not only or m in only]
        bar = progress.add_task("benchmarks", total=len(todo))
        for module, desc in todo:
            progress.update(bar, description=desc)
            t0 = time.perf_counter()
            try:
                mod = importlib.import_module(f"benchmarks.{module}")
                result = mod.run()
                text = str(result["markdown"]).strip()
                if not text.startswith("#"):
                    text = f"### {desc}\n\n{text}"
                sections[module] = _stamped(module, stamp, text)
            except Exception:
                failed += 1
                sections[module] = _stamped(
                    module, stamp,
                    f"### {desc}\n\nFAILED in this run:\n\n```\n{traceback.format_exc()}```",
                )
            console.log(f"{module}: {time.perf_counter() - t0:.1f} s")
            progress.advance(bar)
    if kept:  # --update: the page's other sections stay, in the benchmarks' order
        sections = {m: sections.get(m) or kept[m] for m, _ in BENCHMARKS
                    if m in sections or m in kept}
        when = (f"Sections written by `python -m benchmarks` in different runs (each says "
                f"when, at which commit; the last: {stamp}), ")
    else:
        when = f"Written by `python -m benchmarks` on {stamp}, "
    header = (
        "# sowgate benchmarks\n\n"
        f"{when}Python {platform.python_version()}, {platform.machine()}, "
        "2-core sandbox. Each figure is compared with a baseline measured in the same run.\n\n"
        "Generated: every `make bench` rewrites this page (the README quotes it); do not edit "
        "it by hand. `python -m benchmarks NAME ...` alone writes to `benchmarks/latest.md` "
        "(ignored by git); `python -m benchmarks --update docs/benchmarks.md NAME ...` re-runs "
        "those sections of this page.\n\n"
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(header + "\n".join(sections.values()))
    console.print(f"wrote {out_path}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

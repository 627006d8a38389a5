"""``make bench``: run every benchmark and write their figures to ``docs/benchmarks.md``.

Each benchmark module exposes ``run() -> dict`` with a ``markdown`` entry; every figure is a
ratio against a baseline measured in the same run, so numbers stay comparable across machines.

docs/benchmarks.md is a generated page, meant to change with every full run (``make bench``
passes ``--output docs/benchmarks.md``); review its diff and commit it. A run of a few
benchmarks alone writes to ``benchmarks/latest.md`` (ignored by git) by default, so it never
leaves the published page with only some of its sections.

    python -m benchmarks [--output FILE] [bench_rate bench_store ...]
"""

from __future__ import annotations

import argparse
import importlib
import platform
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


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks")
    parser.add_argument("--output", type=Path, default=DEFAULT_OUT,
                        help="markdown file to write (default: benchmarks/latest.md, untracked)")
    parser.add_argument("only", nargs="*", help="benchmark modules to run (default: all)")
    args = parser.parse_args(argv)
    out_path: Path = args.output
    only = set(args.only)
    unknown = only - {m for m, _ in BENCHMARKS}
    if unknown:
        parser.error(f"unknown benchmark(s): {', '.join(sorted(unknown))}")
    console = Console(stderr=True)
    sections: list[str] = []
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
                sections.append(text + "\n")
            except Exception:
                failed += 1
                sections.append(
                    f"### {desc}\n\nFAILED in this run:\n\n```\n{traceback.format_exc()}```\n"
                )
            console.log(f"{module}: {time.perf_counter() - t0:.1f} s")
            progress.advance(bar)
    header = (
        "# sowgate benchmarks\n\n"
        f"Written by `python -m benchmarks` on {datetime.now(UTC):%Y-%m-%d %H:%M} UTC, "
        f"Python {platform.python_version()}, {platform.machine()}, "
        "2-core sandbox. Each figure is compared with a baseline measured in the same run.\n\n"
        "Generated: every `make bench` rewrites this page (the README quotes it); do not edit "
        "it by hand. `python -m benchmarks NAME ...` alone writes to `benchmarks/latest.md` "
        "(ignored by git).\n\n"
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(header + "\n".join(sections))
    console.print(f"wrote {out_path}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

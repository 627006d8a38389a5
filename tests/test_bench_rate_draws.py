"""bench_rate's draws are independent, so its process pool cannot change a figure.

``benchmarks.bench_rate.run_draws`` hands the (crop, drill) draws to worker processes in
whatever order keeps the pool busy. That is only sound if a draw's figures depend on its
(crop, drill) alone: no random stream, cache or directory shared with the draw before it.
"""

from __future__ import annotations

import multiprocessing as mp
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

from benchmarks import bench_rate


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_a_draw_gives_the_same_figures_in_a_fresh_process_as_after_another_draw(
        tmp_path: Path) -> None:
    last = bench_rate.N_DRILLS - 1  # past N_DRILLS_COSTLY: the cheapest draws
    assert last >= bench_rate.N_DRILLS_COSTLY
    here_root, fresh_root = tmp_path / "here", tmp_path / "fresh"
    here_root.mkdir()
    fresh_root.mkdir()
    # in this process, right after another crop's draw (whatever it leaves behind would show)
    bench_rate.run_draw(0, "rapeseed", last, here_root)
    here = bench_rate.run_draw(1, "wheat", last, here_root)
    with ProcessPoolExecutor(max_workers=1, mp_context=mp.get_context("spawn")) as pool:
        fresh = pool.submit(bench_rate.run_draw, 1, "wheat", last, fresh_root).result()
    assert fresh.per_draw  # the draw ran its rows
    assert fresh == here  # every figure, exactly (floats compared bit for bit)

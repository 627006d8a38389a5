"""bench_multichannel's headline is judged on the p90 over its draws, channel by channel.

The verdicts come from ``summarise``; fed draws whose figures are known, a channel whose p90
CV exceeds paper B's CV (or whose p90 |bias| exceeds 1 %) must read NOT met even when its
median is well inside, and a single outlier beyond the p90 must not decide it.
"""

from __future__ import annotations

from typing import Any

import benchmarks.bench_multichannel as mc


def _draws(cv: dict[str, list[float]], bias: dict[str, list[float]]) -> list[dict[str, Any]]:
    n = len(next(iter(cv.values())))
    out = []
    for i in range(n):
        channels = {}
        for name, _node, _t, g in mc.CHANNELS:
            fig = {"cv_pct": cv[name][i], "bias_pct": bias[name][i], "mean_abs_dev_pct": 1.0}
            channels[name] = {"fitted_g_per_rev": g, "sowgate": fig,
                              "open_loop": {**fig, "bias_pct": -5.0}}
        out.append({"channels": channels, "alarms_closed_loop": 0})
    return out


def test_a_channel_is_judged_on_its_p90_not_its_median_nor_its_single_worst() -> None:
    n = 20
    paper = mc.PAPER_CV
    cv = {name: [paper[name] * 0.5] * n for name in paper}
    bias = {name: [0.1] * n for name in paper}
    # shallow: median inside, but 3 of 20 draws over paper's CV -> p90 over -> NOT met
    cv["shallow"][-3:] = [paper["shallow"] * 1.2] * 3
    # deep: one draw far out (beyond the p90) -> still met on CV
    cv["deep"][-1] = paper["deep"] * 3
    # seed: |bias| over 1 % in 3 draws, of either sign -> NOT met on bias
    bias["seed"][-3:] = [1.5, -1.6, 1.4]
    s = mc.summarise(_draws(cv, bias))
    assert not s["shallow"]["cv_met"] and s["shallow"]["bias_met"]
    assert s["shallow"]["sowgate"]["cv_pct"][0] < paper["shallow"]
    assert s["deep"]["cv_met"] and s["deep"]["bias_met"]
    assert s["deep"]["sowgate"]["cv_pct"][2] == paper["deep"] * 3
    assert s["seed"]["cv_met"] and not s["seed"]["bias_met"]
    assert s["seed"]["sowgate"]["bias_pct"][2] == -1.6
    md = mc.markdown({"draws_n": n, "window_s": mc.WINDOW_S, "duration_s": mc.RUN_S,
                      "alarms_closed_loop": 0, "channels": s, "seed": 1,
                      "one_draw": _draws(cv, bias)[0]})
    assert "— **NOT met**" in md


def test_two_draws_of_the_dynamic_test_differ_and_a_seed_repeats() -> None:
    a, b = mc.one_draw(2), mc.one_draw(3)
    assert a["channels"]["seed"]["sowgate"]["cv_pct"] != b["channels"]["seed"]["sowgate"]["cv_pct"]
    assert mc.one_draw(2)["channels"] == a["channels"]

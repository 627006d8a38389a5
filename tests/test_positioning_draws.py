"""The truth draws of the positioning headline: independent, reproducible, in their ranges."""

from __future__ import annotations

import math

from benchmarks.positioning_draws import DRAWS, draw, draws, next_drives, summary, with_outages
from simulator.field_truth import FieldDrive


def test_twenty_draws_each_another_field_drill_lot_receiver_and_fitter() -> None:
    ds = draws()
    assert len(ds) == DRAWS >= 20
    assert len({d.config.seed for d in ds}) == DRAWS
    for attr in ("terrain", "machine", "lot", "receiver", "timing", "tube", "furrow"):
        assert len({getattr(d.config, attr) for d in ds}) == DRAWS, attr
    assert len({d.fitter for d in ds}) == DRAWS
    assert draw(105) == ds[4]  # reproducible


def test_the_draws_stay_in_their_stated_ranges() -> None:
    for d in draws():
        c = d.config
        assert 0.0 <= c.terrain.cross_slope_deg <= 4.0
        assert 0.008 <= c.receiver.rtk_sigma_m <= 0.016
        assert 0.025 <= c.timing.gnss_latency_s <= 0.060
        assert 0.40 <= c.lot.wall_friction <= 0.70
        assert abs(d.fitter.behind_m) <= 0.03 and abs(d.fitter.gnss_latency_s) <= 0.012
        assert c.receiver.float_windows and c.receiver.dropout_windows


def test_later_drives_keep_the_drill_and_change_the_field_and_sky() -> None:
    d = draw(101)
    later = next_drives(d)
    assert len(later) == 5
    for nd in later:
        assert (nd.config.machine, nd.config.lot, nd.fitter) == (d.config.machine, d.config.lot,
                                                                   d.fitter)
        assert nd.config.terrain != d.config.terrain and nd.config.receiver != d.config.receiver


def test_float_twenty_percent_covers_a_fifth_of_the_passes() -> None:
    cfg = with_outages(draw(101).config, 0.2)
    drive = FieldDrive(cfg.drive, cfg.machine)
    sowing = sum(b - a for a, b in drive.pass_times)
    floating = sum(dur for _a, dur in cfg.receiver.float_windows)
    assert 0.15 <= floating / sowing <= 0.25


def test_summary_is_median_p90_worst() -> None:
    s = summary([float(x) for x in range(1, 21)] + [math.nan])
    assert (s["n"], s["median"], s["worst"], s["best"]) == (20, 10.5, 20.0, 1.0)
    assert s["p90"] == 18.1

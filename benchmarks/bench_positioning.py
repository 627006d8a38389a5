"""Seed landing-position error judged by an independent truth (issue 16 §1).

The truth is ``simulator.field_truth``: a field drive at 4, 8, 12 and 16 km/h (accelerating
after lowering, decelerating before lifting, an autosteer weave, raised U-turns), rolling
sloping ground under a tractor whose primary antenna stands 2.5 m up (secondary beside it, so
#HEADINGA's pitch is the roll), a trailed implement, seeds that fly down an inclined tube with
friction and drag (this lot falls 10 ms longer than paper C's table at 4–8 km/h, 4 ms shorter
at 16) and slide and bounce in the furrow, an RTK error that wanders (Gauss–Markov σ 12 mm,
τ 60 s, + 3 mm white), a float period and a dropout, a receiver whose output latency varies,
USB jitter with bursts, a host clock 40 ppm fast. None of it is the position model's code or
tables. The gateway gets what it would get on that field: the UM982's sentences (decoded by the
real decoder and epoch assembler) and seed edges, both stamped on the host clock.

Rows, all on the same drive, the same seeds and the same noise:

* ``paper C`` — paper C's method (constant 197.2 ms lag, latest fix) with the fitter's lever
  arm, rigid, on level ground;
* ``sowgate as configured`` — the interpolated method as a fitter sets it up, with the
  gateway's own terrain compensation and trailed-implement model: ``antenna_height_m``,
  ``attitude_source = "dual_antenna"`` (the roll the daemon decodes from #HEADINGA's pitch,
  ``gnss.heading_offset_deg = -90``), ``pitch_from_track_m = 4`` (the pitch side-by-side
  antennas cannot see, from the antenna's climb) and ``[positioning.hitch]`` with its
  height, each measured with the fitter's errors (``FITTER``: drawbar 2 cm long, centre
  line 2 cm right, hitch 1 cm short and 2 cm high, antenna 5 cm high, receiver latency 8 ms
  short) and paper C's fall-time table (another seed lot); ``..., terrain compensation
  off`` is the same without antenna height and attitude, ``..., roll only`` without the
  pitch from the track;
* ``sowgate, exact config`` — the same with every measurement true: what is left is the
  model's (this lot's fall time, slide, the pitch's lag and noise, articulation);
* ``sowgate after survey calibration`` — ``sowgate calibrate positions --survey`` then
  ``export --reposition`` on "as configured": the gateway's ``fit_survey`` on the stored
  records of 50 surveyed seeds (``survey_pairs``) and their surveyed lat/lon, the other
  records re-positioned with ``reposition``;
* ``oracle`` — ``benchmarks.positioning_oracle``: every parameter known, only the seed's own
  scatter and the receiver's noise remain.

No inclinometer row: the truth has no WitMotion readings, and the gateway reads only the
inclinometer's roll axis (its pitch axis tells raised from lowered, issue 16 §2), which the
dual-antenna baseline already gives with the antennas side by side; the ground pitch the two
cannot see comes from the track instead (``pitch_from_track_m``).

Seeds sown while the receiver is float or silent (± 0.5 s) are reported apart, as are the 50
seeds set aside for the survey calibration (``survey_pairs``); every row is evaluated on the
same remaining seeds. The calibration is refitted on other surveys (20/50/100 seeds, pole
σ 10/20 mm, one speed, two slow speeds). Then a sensitivity table: from a clean field (flat,
exact config, a perfectly measured fall-time table, no noise) one error source at a time,
the mean error and its change per unit of the source.

Everything runs in simulated time, so the figures do not depend on how loaded the box is.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from benchmarks.positioning_draws import DRAWS, Draw, draws, next_drives, summary, with_outages
from benchmarks.positioning_oracle import EpochError, oracle_landing
from drivers.gnss_reader import EpochAssembler, GnssEpoch
from gateway.config.recording import HitchSection, PositioningSection
from gateway.core.records import SeedDrop
from gateway.recording.positioning import Landing, SeedPositioner
from gateway.recording.positioning.implement_track import ImplementTrack
from gateway.recording.positioning.record_attitude import smooth_attitude
from gateway.recording.positioning.survey import (
    Sown,
    SurveyError,
    SurveyFit,
    fit_survey,
    reposition,
    repositionable,
)
from protocol.gnss import GnssLineDecoder, Rejected
from protocol.unicore import Heading
from simulator.field_truth import (
    FLAT,
    Configured,
    FieldConfig,
    FieldDrive,
    FieldRun,
    FitterErrors,
    Furrow,
    Receiver,
    SeedLot,
    Terrain,
    Timing,
    epoch_lines,
    mean_fall_time_s,
    simulate,
    survey,
)

SPEEDS_KMH = (4.0, 8.0, 12.0, 16.0)
SURVEY_SEEDS = 50
# the fitter's tape and datasheet: drawbar (hitch → outlets) 2 cm long, centre line 2 cm to
# the right, hitch 1 cm short and 2 cm high, antenna height 5 cm high, receiver latency 8 ms
# short
FITTER = FitterErrors(behind_m=0.02, lateral_m=0.02, gnss_latency_s=-0.008,
                      antenna_height_m=0.05, hitch_behind_m=-0.01, hitch_height_m=0.02)
# targets of issue 16 for sowgate after the survey calibration (§3)
TARGET_VS_PAPER = 0.5
TARGET_ABS_MM = 25.0
PAPER = "paper C"
CONFIGURED = "sowgate as configured"
NO_TERRAIN = "sowgate as configured, terrain compensation off"
ROLL_ONLY = "sowgate as configured, roll only (pitch_from_track_m = 0)"
EXACT = "sowgate, exact config"
CALIBRATED = "sowgate after survey calibration"
ORACLE = "oracle"
METHODS = (PAPER, NO_TERRAIN, ROLL_ONLY, CONFIGURED, EXACT, CALIBRATED, ORACLE)
# positioning.pitch_from_track_m as "as configured" sets it
PITCH_TRACK_M = 4.0


# ------------------------------------------------------------------ the gateway's view


@dataclass
class GatewayInputs:
    """What the daemon sees of a run: decoded epochs and edges, host-stamped."""

    epochs: list[tuple[float, GnssEpoch]]
    edges: list[tuple[float, int]]
    baseline_pitch: dict[float, float]  # epoch UTC (s) → #HEADINGA pitch as decoded


def gateway_inputs(run: FieldRun) -> GatewayInputs:
    """Render every epoch as UM982 sentences, decode and assemble them as the daemon does."""
    offset = -90.0 if run.config.machine.baseline == "side_by_side" else 0.0
    decoder = GnssLineDecoder()
    assembler = EpochAssembler(
        today=lambda: run.config.utc_start.date(), heading_offset_deg=offset
    )
    epochs: list[tuple[float, GnssEpoch]] = []
    pitch: dict[float, float] = {}
    for ep in run.epochs:
        data = "".join(f"{ln}\r\n" for ln in epoch_lines(ep)).encode()
        for item in decoder.feed(data):
            if isinstance(item, Rejected):
                raise RuntimeError(f"truth line rejected: {item}")
            if isinstance(item, Heading):
                pitch[ep.utc.timestamp()] = item.pitch_deg
            for epoch in assembler.add(item, ep.t_host):
                epochs.append((epoch.t_mono, epoch))
    edges = [(s.t_host, s.row) for s in run.seeds]
    return GatewayInputs(epochs, edges, pitch)


def baseline_offset_deg(run: FieldRun) -> float:
    """``gnss.heading_offset_deg`` as the fitter sets it for the truth's antennas."""
    return -90.0 if run.config.machine.baseline == "side_by_side" else 0.0


def section(conf: Configured, fall_table: Sequence[tuple[float, float]] | None = None,
            *, terrain: bool = True, hitch: bool = True, pitch_track_m: float = 0.0
            ) -> PositioningSection:
    """The ``[positioning]`` a fitter enters for ``conf``: lever arm, latencies, and (with
    ``terrain``) the gateway's own terrain compensation (``antenna_height_m``,
    ``attitude_source = "dual_antenna"``) and (with ``hitch``) a trailed implement's
    ``[positioning.hitch]``; paper C's method has neither: a rigid lever arm on level ground."""
    kw: dict[str, Any] = {}
    if fall_table is not None:
        kw["fall_time_table"] = [tuple(x) for x in fall_table]
    if terrain:
        kw["antenna_height_m"] = conf.antenna_height_m
        kw["attitude_source"] = "dual_antenna"
        kw["pitch_from_track_m"] = pitch_track_m
    if (hitch and conf.hitch_behind_antenna_m is not None
            and conf.outlets_behind_hitch_m is not None):
        kw["hitch"] = HitchSection(behind_antenna_m=conf.hitch_behind_antenna_m,
                                   outlets_behind_hitch_m=conf.outlets_behind_hitch_m,
                                   height_m=conf.hitch_height_m or 0.0,
                                   wheels_behind_hitch_m=conf.wheels_behind_hitch_m)
    return PositioningSection(
        outlet_behind_antenna_m=conf.outlet_behind_antenna_m,
        row_lateral_m=list(conf.row_lateral_m),
        gnss_output_latency_ms=conf.gnss_output_latency_ms,
        seed_edge_latency_ms=conf.seed_edge_latency_ms,
        **kw,
    )


def replay(settings: PositioningSection, method: str, inputs: GatewayInputs,
           offset_deg: float = -90.0) -> list[Landing]:
    """Feed epochs and edges in host-arrival order, as the daemon would (the recorder builds
    its positioner with ``baseline_offset_deg = gnss.heading_offset_deg``)."""
    positioner = SeedPositioner(settings, method="paper" if method == "paper" else "interpolated",
                                baseline_offset_deg=offset_deg)
    events: list[tuple[float, int, Any]] = [(t, 0, e) for t, e in inputs.epochs]
    events += [(t, 1, row) for t, row in inputs.edges]
    events.sort(key=lambda x: (x[0], x[1]))
    out: list[Landing] = []
    for t, kind, what in events:
        out += positioner.add_epoch(what) if kind == 0 else positioner.add_edge(what, t)
    out += positioner.flush()
    if len(out) != len(inputs.edges):
        raise RuntimeError(f"{len(out)} seeds positioned of {len(inputs.edges)}")
    return out


# ------------------------------------------------------------------ errors


@dataclass(frozen=True)
class Errors:
    """Per seed: predicted minus true, in the direction of travel and to its right (m)."""

    along: np.ndarray
    across: np.ndarray

    @property
    def total(self) -> np.ndarray:
        return np.asarray(np.hypot(self.along, self.across))


def _decompose(run: FieldRun, pe: np.ndarray, pn: np.ndarray) -> Errors:
    seeds = run.seeds
    de = pe - np.array([s.east for s in seeds])
    dn = pn - np.array([s.north for s in seeds])
    _e, _n, h, _v, _hi = run.drive.at(np.array([s.t_land for s in seeds]))
    psi = np.radians(h)
    return Errors(de * np.sin(psi) + dn * np.cos(psi), de * np.cos(psi) - dn * np.sin(psi))


def landing_errors(run: FieldRun, landings: list[Landing]) -> Errors:
    for la, s in zip(landings, run.seeds, strict=True):
        if la.drop.row != s.row:
            raise RuntimeError("positioned seeds out of order")
    lat = np.array([la.drop.lat for la in landings])
    lon = np.array([la.drop.lon for la in landings])
    pe, pn = run.to_enu(lat, lon)
    return _decompose(run, pe, pn)


def oracle_errors(run: FieldRun) -> Errors:
    errs = [EpochError(ep.t, ep.err_east_m, ep.err_north_m, ep.err_heading_deg)
            for ep in run.epochs]
    t = np.array([s.expected_t_land for s in run.seeds])
    ge, gn = run.antenna_ground_at(t)
    times = [x.t for x in errs]
    pts = [
        oracle_landing((s.expected_east, s.expected_north), (float(e), float(n)), s.expected_t_land,
                       errs, times)
        for s, e, n in zip(run.seeds, ge.tolist(), gn.tolist(), strict=True)
    ]
    return _decompose(run, np.array([p[0] for p in pts]), np.array([p[1] for p in pts]))


@dataclass(frozen=True)
class Stats:
    n: int
    mean_mm: float
    p95_mm: float
    along_mean_mm: float
    along_sd_mm: float
    across_mean_mm: float
    across_sd_mm: float

    @classmethod
    def of(cls, err: Errors, mask: np.ndarray) -> Stats:
        tot = err.total[mask] * 1000.0
        al, ac = err.along[mask] * 1000.0, err.across[mask] * 1000.0
        if len(tot) == 0:
            nan = math.nan
            return cls(0, nan, nan, nan, nan, nan, nan)
        return cls(len(tot), float(tot.mean()), float(np.percentile(tot, 95)),
                   float(al.mean()), float(al.std()), float(ac.mean()), float(ac.std()))


# ------------------------------------------------------------------ survey hook (issue 16 §3)


@dataclass(frozen=True)
class SurveyPair:
    """One surveyed seed: the record sowgate stored for it and where a surveyor found it."""

    record: SeedDrop
    edge_t_mono: float  # the raw host stamp of its edge (records keep it, §3)
    surveyed_lat: float
    surveyed_lon: float


def survey_pairs(
    run: FieldRun, landings: list[Landing], n: int = SURVEY_SEEDS, seed: int = 16,
    *, sigma_m: float = 0.005, passes: Sequence[int] | None = None,
) -> tuple[list[SurveyPair], np.ndarray]:
    """``n`` seeds surveyed after the drive (RTK rover, ``sigma_m`` a pole placement), spread
    evenly over the passes (``passes``: only those, e.g. one speed), RTK-fixed only; and the
    mask of the seeds not surveyed.

    Fit on these pairs (``calibrate``), re-position the landings, evaluate on the returned
    mask like every other row.
    """
    rng = np.random.default_rng(seed)
    clean = ~run.config.receiver.degraded(np.array([s.t_land for s in run.seeds]))
    pass_of = np.array([s.pass_index for s in run.seeds])
    chosen: list[int] = []
    which = list(range(len(SPEEDS_KMH))) if passes is None else list(passes)
    groups = [np.flatnonzero(clean & (pass_of == p)) for p in which]
    for i, idx in enumerate(groups):
        k = n // len(groups) + (1 if i < n % len(groups) else 0)
        chosen += rng.choice(idx, size=k, replace=False).tolist()
    chosen.sort()
    where = survey(run, [run.seeds[i] for i in chosen], sigma_m=sigma_m)
    pairs = [
        SurveyPair(landings[i].drop, run.seeds[i].t_host, lat, lon)
        for i, (lat, lon) in zip(chosen, where, strict=True)
    ]
    held_out = np.ones(len(run.seeds), bool)
    held_out[chosen] = False
    return pairs, held_out


@dataclass(frozen=True)
class Calibrated:
    """The survey calibration's result: the gateway's fit and the re-positioned seeds."""

    fit: SurveyFit
    errors: Errors
    not_repositionable: int  # records kept where they were stored (no raw data)


def calibrate(run: FieldRun, landings: list[Landing], settings: PositioningSection,
              pairs: Sequence[SurveyPair], *, fit_delay: bool = True) -> Calibrated:
    """What ``sowgate calibrate positions --survey`` then ``export --reposition`` do: the
    gateway's ``fit_survey`` on the stored records of the surveyed seeds and their surveyed
    lat/lon, the fit laid over ``settings`` (``SurveyFit.settings``, as the calibration file
    does), every record re-positioned with it (``reposition``)."""
    # the records' attitude estimated again with the records after each (as the CLI does)
    drops = list(smooth_attitude([la.drop for la in landings], settings,
                                 baseline_offset_deg(run)))
    by_id = {id(la.drop): d for la, d in zip(landings, drops, strict=True)}
    sown = Sown.empty(settings)  # with a hitch: the implement's heading along the records
    for d in drops:
        sown.add(d)
        sown.keep(d)
    fit = fit_survey([by_id[id(p.record)] for p in pairs],
                     [(p.surveyed_lat, p.surveyed_lon) for p in pairs], settings,
                     fit_delay=fit_delay, sown=sown)
    new = fit.settings(settings)
    lat, lon, kept = [], [], 0
    track = ImplementTrack(new, made_with=new)  # read back at restarts, as export does
    for d in drops:
        implement = track.heading(d)
        if repositionable(d):
            a, b = reposition(d, new, implement)
        else:
            a, b, kept = d.lat, d.lon, kept + 1
        lat.append(a)
        lon.append(b)
    pe, pn = run.to_enu(np.array(lat), np.array(lon))
    return Calibrated(fit, _decompose(run, pe, pn), kept)


# ------------------------------------------------------------------ runs


def field_config(seed: int = 1) -> FieldConfig:
    """The benchmark's field: defaults of ``simulator.field_truth``, a 6 s float period in
    the 8 km/h pass and a 1.5 s dropout in the 12 km/h pass."""
    base = FieldConfig(seed=seed)
    drive = FieldDrive(base.drive, base.machine)
    (a1, b1), (a2, b2) = drive.pass_times[1], drive.pass_times[2]
    rx = replace(base.receiver, float_windows=(((a1 + b1) / 2 - 3.0, 6.0),),
                 dropout_windows=(((a2 + b2) / 2, 1.5),))
    return replace(base, receiver=rx)


def _methods(run: FieldRun, inputs: GatewayInputs, fitter: FitterErrors,
             fall_table: Sequence[tuple[float, float]] | None = None,
             which: Sequence[str] = (PAPER, NO_TERRAIN, ROLL_ONLY, CONFIGURED, EXACT, ORACLE),
             *, terrain: bool = True, pitch_track_m: float = PITCH_TRACK_M,
             ) -> tuple[dict[str, Errors], dict[str, list[Landing]]]:
    cfg = run.config
    conf = fitter.configured(cfg.machine, cfg.timing)
    exact = FitterErrors().configured(cfg.machine, cfg.timing)
    offset = baseline_offset_deg(run)
    out: dict[str, Errors] = {}
    landings: dict[str, list[Landing]] = {}
    for m in which:
        if m == ORACLE:
            out[m] = oracle_errors(run)
            continue
        c = exact if m == EXACT else conf
        if m == PAPER:
            settings = section(c, fall_table, terrain=False, hitch=False)
        else:
            settings = section(c, fall_table, terrain=terrain and m != NO_TERRAIN,
                               pitch_track_m=0.0 if m == ROLL_ONLY else pitch_track_m)
        method = "paper" if m == PAPER else "interpolated"
        landings[m] = replay(settings, method, inputs, offset)
        out[m] = landing_errors(run, landings[m])
    return out, landings


def measured_fall_table(cfg: FieldConfig) -> list[tuple[float, float]]:
    """A perfectly measured table for this lot (for the sensitivity's clean baseline)."""
    speeds = np.arange(2.0, 19.0, 1.0)
    return [(float(v), float(t) * 1000.0)
            for v, t in zip(speeds, mean_fall_time_s(cfg, speeds), strict=True)]


def clean_config(seed: int = 1) -> FieldConfig:
    """The field with every error source off: flat, straight passes, a mounted implement,
    no free fall below the outlet, no slide or bounce, no scatter between seeds, a silent
    receiver, no jitter or drift."""
    base = FieldConfig(seed=seed)
    return replace(
        base,
        drive=replace(base.drive, weave_deg=0.0),
        terrain=FLAT,
        machine=replace(base.machine, trailed=False),
        lot=replace(base.lot, diameter_cv=0.0, wall_friction_sd=0.0),
        tube=replace(base.tube, outlet_height_m=0.0),
        furrow=Furrow(retained=(0.0, 0.0), bounce_along_sd_m=0.0, bounce_across_sd_m=0.0),
        receiver=Receiver(rtk_sigma_m=0.0, white_sigma_m=0.0, vertical_white_sigma_m=0.0,
                          heading_sigma_deg=0.0, pitch_sigma_deg=0.0, speed_sigma_kmh=0.0),
        timing=Timing(host_drift_ppm=0.0, gnss_latency_spread_s=0.0, usb_jitter_mean_s=0.0,
                      burst_prob=0.0, sensor_latency_s=0.0, edge_jitter_s=0.0),
    )


@dataclass(frozen=True)
class Source:
    name: str
    unit: str
    magnitude: float  # in units
    cfg: FieldConfig
    fitter: FitterErrors = field(default_factory=FitterErrors)
    table_shift_ms: float = 0.0
    terrain: bool = True  # the gateway's terrain compensation (antenna height, dual antenna)
    pitch_track_m: float = PITCH_TRACK_M


def sources(seed: int = 1) -> list[Source]:
    c = clean_config(seed)
    lot = c.lot
    return [
        Source("seed bounce along the furrow, σ 20 mm", "mm σ", 20.0,
               replace(c, furrow=replace(c.furrow, bounce_along_sd_m=0.02))),
        Source("slide in the furrow (default furrow; unit: mean slide at 4–16 km/h)",
               "mm slide", math.nan, replace(c, furrow=Furrow(bounce_along_sd_m=0.0,
                                                             bounce_across_sd_m=0.0))),
        Source("free fall 3 cm below the outlet (the seed leaves the tube moving back)",
               "mm fall", 30.0, replace(c, tube=replace(c.tube, outlet_height_m=0.03))),
        Source("fall-time table 10 ms too long", "ms", 10.0, c, table_shift_ms=10.0),
        Source("fall-time scatter of the lot (size cv 8 %, friction sd 0.15)",
               "ms σ", math.nan,
               replace(c, lot=replace(lot, diameter_cv=SeedLot().diameter_cv,
                                      wall_friction_sd=SeedLot().wall_friction_sd))),
        Source("receiver latency configured 10 ms short", "ms", 10.0, c,
               fitter=FitterErrors(gnss_latency_s=-0.010)),
        Source("lever arm configured 3 cm long", "cm", 3.0, c,
               fitter=FitterErrors(behind_m=0.03)),
        Source("lever arm configured 3 cm to the right", "cm", 3.0, c,
               fitter=FitterErrors(lateral_m=0.03)),
        Source("cross slope 3°, antenna 2.5 m up, no terrain compensation", "° roll", 3.0,
               replace(c, terrain=Terrain(cross_slope_deg=3.0, along_slope_deg=0.0,
                                          undulation_m=0.0)), terrain=False),
        Source("same, terrain compensation on (antenna_height_m, dual antenna, #HEADINGA "
               "pitch σ 0.15°; what is left: the hitch, 0.5 m up, swings 26 mm downhill)",
               "° roll", 3.0,
               replace(c, terrain=Terrain(cross_slope_deg=3.0, along_slope_deg=0.0,
                                          undulation_m=0.0),
                       receiver=replace(c.receiver, pitch_sigma_deg=0.15))),
        Source("along slope 3°, pitch from the track (pitch_from_track_m = 4; what is left: "
               "the hitch, 0.5 m up, swings 26 mm downhill as on the cross slope)", "° pitch",
               3.0,
               replace(c, terrain=Terrain(cross_slope_deg=0.0, along_slope_deg=3.0,
                                          undulation_m=0.0))),
        Source("same, pitch_from_track_m = 0 (side-by-side antennas see roll only)",
               "° pitch", 3.0,
               replace(c, terrain=Terrain(cross_slope_deg=0.0, along_slope_deg=3.0,
                                          undulation_m=0.0)), pitch_track_m=0.0),
        Source("RTK height noise: white σ 15 mm (pitch from the track reads it)", "mm σ", 15.0,
               replace(c, receiver=replace(c.receiver, vertical_white_sigma_m=0.015))),
        Source("rolling ground (3 waves of 5 cm, 40 m), antenna 2.5 m up: pitch and roll",
               "° rms", math.nan,
               replace(c, terrain=Terrain(cross_slope_deg=0.0, along_slope_deg=0.0))),
        Source("same, pitch_from_track_m = 0", "° rms", math.nan,
               replace(c, terrain=Terrain(cross_slope_deg=0.0, along_slope_deg=0.0)),
               pitch_track_m=0.0),
        Source("RTK error Gauss–Markov σ 12 mm (height 24 mm), τ 60 s (+3 mm white, height "
               "6 mm)", "mm σ", 12.0,
               replace(c, receiver=replace(c.receiver, rtk_sigma_m=0.012, white_sigma_m=0.003,
                                           vertical_white_sigma_m=0.006))),
        Source("heading noise σ 0.08°", "° σ", 0.08,
               replace(c, receiver=replace(c.receiver, heading_sigma_deg=0.08))),
        Source("trailed implement, straight passes (still swung out after the headland)",
               "° artic.", math.nan, replace(c, machine=replace(c.machine, trailed=True))),
        Source("trailed implement, contour passes of radius 40 m", "° artic.", math.nan,
               replace(c, machine=replace(c.machine, trailed=True),
                       drive=replace(c.drive, pass_curvature_per_m=1 / 40.0))),
        Source("receiver latency spread 4 ms + USB jitter (3 ms, 5 % bursts 5–30 ms)",
               "ms mean", 2.0 + 3.0 + 0.05 * 17.5,
               replace(c, timing=replace(c.timing, gnss_latency_spread_s=0.004,
                                         usb_jitter_mean_s=0.003, burst_prob=0.05))),
        Source("host clock 50 ppm fast", "ppm", 50.0,
               replace(c, timing=replace(c.timing, host_drift_ppm=50.0))),
    ]


def _one(src: Source) -> tuple[dict[str, Stats], FieldRun]:
    run = simulate(src.cfg)
    inputs = gateway_inputs(run)
    table = [(v, t + src.table_shift_ms) for v, t in measured_fall_table(src.cfg)]
    errs, _ = _methods(run, inputs, src.fitter, table, (PAPER, CONFIGURED), terrain=src.terrain,
                       pitch_track_m=src.pitch_track_m)
    mask = np.ones(len(run.seeds), bool)
    return {
        "paper C": Stats.of(errs[PAPER], mask),
        "sowgate": Stats.of(errs[CONFIGURED], mask),
    }, run


def _sensitivity_row(src: Source) -> dict[str, Any]:
    stats, run = _one(src)
    magnitude = src.magnitude
    if math.isnan(magnitude):  # measured from the truth of this run
        seeds = run.seeds
        if src.unit == "mm slide":
            magnitude = float(np.mean(np.abs([s.slide_m for s in seeds]))) * 1000.0
        elif src.unit == "ms σ":
            fall = np.array([s.t_land - s.t_edge for s in seeds])
            xfall = np.array([s.expected_t_land - s.t_edge for s in seeds])
            magnitude = float(np.std(fall - xfall)) * 1000.0
        elif src.unit == "° rms":
            e, n, h, _v, _hi = run.drive.at(np.array([s.t_land for s in seeds]))
            pitch, roll = src.cfg.terrain.attitude(e, n, h)
            magnitude = float(np.sqrt(np.mean(pitch**2 + roll**2)))
        else:
            magnitude = float(np.mean(np.abs([s.articulation_deg for s in seeds])))
    return {"source": src.name, "unit": src.unit, "magnitude": magnitude,
            **{m: dataclasses.asdict(s) for m, s in stats.items()}}


def sensitivity(seed: int = 1) -> list[dict[str, Any]]:
    rows = _pool_map(_sensitivity_row, [Source("clean", "", 0.0, clean_config(seed)),
                                        *sources(seed)])
    rows[0]["source"] = "clean field (baseline)"
    return rows


def _masks(run: FieldRun, held_out: np.ndarray) -> dict[str, np.ndarray]:
    degraded = run.config.receiver.degraded(np.array([s.t_land for s in run.seeds]))
    passes = np.array([s.pass_index for s in run.seeds])
    good = held_out & ~degraded
    masks: dict[str, np.ndarray] = {
        f"{v:g} km/h": good & (passes == i) for i, v in enumerate(SPEEDS_KMH)
    }
    masks["4–12 km/h"] = good & (passes >= 0) & (passes <= 2)
    masks["4–16 km/h"] = good & (passes >= 0)
    masks["float/dropout ±0.5 s"] = held_out & degraded
    return masks


@dataclass(frozen=True)
class Variant:
    """One way of surveying for the calibration's sensitivity table."""

    name: str
    n: int = SURVEY_SEEDS
    sigma_m: float = 0.005
    passes: tuple[int, ...] | None = None
    fit_delay: bool = True


VARIANTS = (
    Variant("20 surveyed seeds (the minimum)", n=20),
    Variant("50 surveyed seeds (the headline)"),
    Variant("100 surveyed seeds", n=100),
    Variant("50 seeds, surveyor's pole σ 10 mm", sigma_m=0.010),
    Variant("50 seeds, surveyor's pole σ 20 mm", sigma_m=0.020),
    Variant("50 seeds from the 8 km/h pass only", passes=(1,)),
    Variant("50 seeds from the 8 km/h pass only, --lever-only", passes=(1,), fit_delay=False),
    Variant("50 seeds from 4 and 8 km/h only", passes=(0, 1)),
)


def calibration_sensitivity(truth: FieldRun, landings: list[Landing],
                            settings: PositioningSection) -> list[dict[str, Any]]:
    """The survey calibration refitted on other surveys of the same drive (fresh pole
    errors per survey); each evaluated on the seeds it did not survey."""
    rows: list[dict[str, Any]] = []
    for v in VARIANTS:
        pairs, held_out = survey_pairs(truth, landings, v.n, sigma_m=v.sigma_m,
                                       passes=v.passes)
        row: dict[str, Any] = {"survey": v.name}
        try:
            cal = calibrate(truth, landings, settings, pairs, fit_delay=v.fit_delay)
        except SurveyError as exc:
            row["refused"] = str(exc)
            rows.append(row)
            continue
        masks = _masks(truth, held_out)
        if cal.fit.problems() or cal.fit.coverage_warnings:
            row["cli"] = ("refuses: " if cal.fit.problems() else "warns: ") + "; ".join(
                cal.fit.problems() or cal.fit.coverage_warnings)
        row["fit"] = {"delay_ms": cal.fit.delay_ms, "behind_mm": cal.fit.behind_m * 1000.0,
                      "right_mm": cal.fit.right_m * 1000.0,
                      "ms_per_kmh": cal.fit.delay_ms_per_kmh, "ref_kmh": cal.fit.speed_ref_kmh}
        row["stats"] = {k: dataclasses.asdict(Stats.of(cal.errors, masks[k]))
                        for k in ("4–12 km/h", "16 km/h", "4–16 km/h")}
        rows.append(row)
    return rows


def run(seed: int = 1) -> dict[str, Any]:
    cfg = field_config(seed)
    truth = simulate(cfg)
    inputs = gateway_inputs(truth)
    errs, landings = _methods(truth, inputs, FITTER)
    configured = section(FITTER.configured(cfg.machine, cfg.timing), pitch_track_m=PITCH_TRACK_M)
    pairs, held_out = survey_pairs(truth, landings[CONFIGURED])
    cal = calibrate(truth, landings[CONFIGURED], configured, pairs)
    errs[CALIBRATED] = cal.errors
    masks = _masks(truth, held_out)
    # the same survey (the same seeds) on the roll-only records: what pitch from the track buys
    roll_pairs, _ = survey_pairs(truth, landings[ROLL_ONLY])
    roll_cal = calibrate(truth, landings[ROLL_ONLY],
                         section(FITTER.configured(cfg.machine, cfg.timing)), roll_pairs)
    roll_only_cal = Stats.of(roll_cal.errors, masks["4–12 km/h"]).mean_mm
    table = {m: {k: Stats.of(errs[m], mk) for k, mk in masks.items()} for m in METHODS}
    degraded = cfg.receiver.degraded(np.array([s.t_land for s in truth.seeds]))
    flagged = sum(
        1 for la, d in zip(landings[CONFIGURED], degraded.tolist(), strict=True)
        if d and (la.drop.extrapolated or la.drop.fix != "rtk_fixed")
    )
    paper_412 = table[PAPER]["4–12 km/h"].mean_mm
    cal_412 = table[CALIBRATED]["4–12 km/h"].mean_mm
    target_mm = min(TARGET_ABS_MM, TARGET_VS_PAPER * paper_412)
    fall = {v: float(mean_fall_time_s(cfg, np.array([v]))[0]) * 1000.0 for v in SPEEDS_KMH}
    result: dict[str, Any] = {
        "seeds": len(truth.seeds),
        "epochs": len(inputs.epochs),
        "survey_pairs": len(pairs),
        "degraded_seeds": int((held_out & degraded).sum()),
        "degraded_flagged_by_sowgate": flagged,
        "stats": {m: {k: dataclasses.asdict(s) for k, s in d.items()} for m, d in table.items()},
        "true_fall_ms": fall,
        "fit": {"delay_ms": cal.fit.delay_ms, "behind_mm": cal.fit.behind_m * 1000.0,
                "right_mm": cal.fit.right_m * 1000.0, "outliers": cal.fit.outliers,
                "before_mm": cal.fit.before.mean_m * 1000.0,
                "after_mm": cal.fit.after.mean_m * 1000.0,
                "not_repositionable": cal.not_repositionable},
        "calibrated_roll_only_mm": roll_only_cal,
        "calibration_target_mm": target_mm,
        "calibrated_vs_paper": cal_412 / paper_412,
        "calibrated_distance_to_target_mm": cal_412 - target_mm,
        "one_draw_target_met": cal_412 <= target_mm,
        "calibration_sensitivity": calibration_sensitivity(truth, landings[CONFIGURED],
                                                           configured),
        "sensitivity": sensitivity(seed),
    }
    n = int(os.environ.get("SOWGATE_POSITION_DRAWS",
                           os.environ.get("SOWGATE_BENCH_DRAWS", str(DRAWS))))
    od = over_draws(n)
    head, met = draws_markdown(od)
    from benchmarks import positioning_sensitivity as ps  # it imports this module

    conditions = ps.over_draws(n, _pool_map)
    result["over_draws"] = od
    result["conditions"] = conditions
    result["targets_met"] = met
    result["markdown"] = (head + "\n" + ps.markdown(conditions, od["draws"]) + "\n"
                          + _markdown(result, truth))
    return result


def _fmt(x: float) -> str:
    return "–" if math.isnan(x) else f"{x:.1f}"


def _markdown(result: dict[str, Any], truth: FieldRun) -> str:
    st = result["stats"]
    cfg = truth.config
    keys = [f"{v:g} km/h" for v in SPEEDS_KMH] + ["4–12 km/h", "4–16 km/h"]
    fall = ", ".join(f"{v:g} km/h {t:.0f} ms" for v, t in result["true_fall_ms"].items())
    lines = [
        "#### One draw in detail (field seed 1, the benchmark's historical drive)",
        "",
        f"`simulator.field_truth` (shares no code or table with the position model): "
        f"{result['seeds']} seeds in {len(cfg.machine.row_lateral_m)} rows of 0.75 m, passes "
        f"at 4/8/12/16 km/h with accelerations, autosteer weave, ground rolling "
        f"{cfg.terrain.cross_slope_deg:g}° cross slope + waves (roll ±2–4°), antenna "
        f"{cfg.machine.antenna_height_m:g} m up, trailed implement, this lot's fall time "
        f"{fall} (paper C's table: 114→104 ms), slide + bounce in the furrow, RTK error "
        f"Gauss–Markov σ {cfg.receiver.rtk_sigma_m * 1000:g} mm τ {cfg.receiver.rtk_tau_s:g} s "
        f"(height: twice that, + {cfg.receiver.vertical_white_sigma_m * 1000:g} mm white), "
        f"{result['epochs']} epochs decoded from UM982 sentences. Fitter's errors in "
        f"\"as configured\": drawbar (hitch → outlets) +{FITTER.behind_m * 100:g} cm, centre "
        f"line +{FITTER.lateral_m * 100:g} cm right, hitch {FITTER.hitch_behind_m * 100:+g} cm "
        f"along and {FITTER.hitch_height_m * 100:+g} cm in height, "
        f"antenna height {FITTER.antenna_height_m * 100:+g} cm, receiver latency "
        f"{FITTER.gnss_latency_s * 1000:g} ms, paper C's fall-time table. Sowgate runs as "
        f"the daemon would: `antenna_height_m`, `attitude_source = \"dual_antenna\"` (roll "
        f"from the decoded #HEADINGA pitch, `gnss.heading_offset_deg = -90`), "
        f"`pitch_from_track_m = {PITCH_TRACK_M:g}` (pitch from the antenna's climb), "
        f"`[positioning.hitch]` with its height; paper C's method: a rigid lever arm on "
        f"level ground. "
        f"Error = predicted − true rest point; along + = ahead, across + = right. "
        f"Excluded from the speed columns: the {SURVEY_SEEDS} surveyed seeds, and seeds within "
        f"0.5 s of float/dropout (in the last column).",
        "",
        "Mean error, mm (p95):",
        "",
        "| method | " + " | ".join(keys) + " | float/dropout |",
        "|---|" + "---:|" * (len(keys) + 1),
    ]
    for m in METHODS:
        cells = [f"{_fmt(st[m][k]['mean_mm'])} ({_fmt(st[m][k]['p95_mm'])})" for k in keys]
        deg = st[m]["float/dropout ±0.5 s"]
        cells.append(f"{_fmt(deg['mean_mm'])} (n={deg['n']})")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    fit = result["fit"]
    lines += [
        "",
        f"Survey calibration: `fit_survey` on the stored records of {result['survey_pairs']} "
        f"surveyed seeds (RTK-fixed, spread over the four passes, pole σ 5 mm) with "
        f"\"as configured\"'s settings: delay {fit['delay_ms']:+.1f} ms, outlets "
        f"{fit['behind_mm']:+.1f} mm behind, {fit['right_mm']:+.1f} mm right "
        f"({fit['outliers']} down-weighted); surveyed seeds {fit['before_mm']:.1f} → "
        f"{fit['after_mm']:.1f} mm. The other seeds re-positioned with `reposition` "
        f"({fit['not_repositionable']} without raw data kept as stored).",
        "",
        "Along / across components at 4–16 km/h, mm (mean ± SD):",
        "",
        "| method | along | across |",
        "|---|---:|---:|",
    ]
    for m in METHODS:
        s = st[m]["4–16 km/h"]
        lines.append(f"| {m} | {s['along_mean_mm']:+.1f} ± {s['along_sd_mm']:.1f} | "
                     f"{s['across_mean_mm']:+.1f} ± {s['across_sd_mm']:.1f} |")
    paper = st[PAPER]["4–12 km/h"]["mean_mm"]
    cal = st[CALIBRATED]["4–12 km/h"]["mean_mm"]
    verdict = ("met" if result["one_draw_target_met"] else
               f"not met: {result['calibrated_distance_to_target_mm']:.1f} mm above it")
    lines += [
        "",
        f"Targets (after survey calibration, 4–12 km/h): mean ≤ {TARGET_VS_PAPER} × paper C "
        f"= {TARGET_VS_PAPER * paper:.1f} mm and ≤ {TARGET_ABS_MM:g} mm, i.e. ≤ "
        f"{result['calibration_target_mm']:.1f} mm. Sowgate after survey calibration: "
        f"{cal:.1f} mm ({result['calibrated_vs_paper']:.2f} × paper C): {verdict}; "
        f"the same survey and fit on the roll-only records (`pitch_from_track_m = 0`): "
        f"{result['calibrated_roll_only_mm']:.1f} mm. "
        f"Float/dropout seeds: {result['degraded_seeds']}, of which sowgate flagged "
        f"{result['degraded_flagged_by_sowgate']} (fix not RTK-fixed, or extrapolated).",
        "",
        "Survey calibration sensitivity (same drive, other surveys; each evaluated on the "
        "seeds it did not survey), mean mm (p95):",
        "",
        "| survey | fit: delay (with a speed slope: at the surveyed median speed) / behind / "
        "right | 4–12 km/h | 16 km/h | 4–16 km/h |",
        "|---|---|---:|---:|---:|",
    ]
    for row in result["calibration_sensitivity"]:
        if "refused" in row:
            lines.append(f"| {row['survey']} | refused: {row['refused']} | | | |")
            continue
        f = row["fit"]
        cells = [f"{_fmt(row['stats'][k]['mean_mm'])} ({_fmt(row['stats'][k]['p95_mm'])})"
                 for k in ("4–12 km/h", "16 km/h", "4–16 km/h")]
        name = row["survey"] + (f" (`calibrate positions` {row['cli']})" if "cli" in row else "")
        delay = f"{f['delay_ms']:+.1f} ms"
        if f.get("ms_per_kmh"):
            delay += f" at {f['ref_kmh']:.0f} km/h, {f['ms_per_kmh']:+.2f} ms per km/h"
        lines.append(f"| {name} | {delay} / {f['behind_mm']:+.0f} mm"
                     f" / {f['right_mm']:+.0f} mm | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Sensitivity of sowgate as configured (terrain compensation on unless a row says "
        "otherwise): from a clean field (flat, straight, mounted implement, exact lever arm "
        "and latency, a "
        "perfectly measured fall-time table, no receiver noise, no jitter) one source at a "
        "time, all 4–16 km/h seeds. Δ = mean error minus the clean run's; per unit = Δ / "
        "magnitude (random sources add in quadrature, so per unit is only a guide there).",
        "",
        "| source | magnitude | sowgate mean (mm) | Δ | Δ per unit | paper C mean (mm) | Δ |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    sens = result["sensitivity"]
    b_sow = sens[0]["sowgate"]["mean_mm"]
    b_pap = sens[0]["paper C"]["mean_mm"]
    for row in sens:
        sow_m = row["sowgate"]["mean_mm"]
        pap_m = row["paper C"]["mean_mm"]
        mag = row["magnitude"]
        per = (sow_m - b_sow) / mag if mag else math.nan
        mag_s = f"{mag:.2f} {row['unit']}" if row["unit"] else "–"
        lines.append(
            f"| {row['source']} | {mag_s} | {sow_m:.1f} | {sow_m - b_sow:+.1f} | "
            f"{_fmt(per)} mm/{row['unit'] or '–'} | {pap_m:.1f} | {pap_m - b_pap:+.1f} |"
        )
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    out = run()
    print(out["markdown"])


# ------------------------------------------------------------------ over truth draws (issue 25)


def _mean_mm(err: Errors, mask: np.ndarray) -> float:
    return Stats.of(err, mask).mean_mm


def evaluate_draw(d: Draw, *, float_fraction: float = 0.0) -> dict[str, Any]:
    """One truth draw: sowgate as configured, after the survey calibration (50 seeds over the
    four passes), after a survey of one half of the field (the 12 and 16 km/h passes), and
    the oracle; mean errors of the held-out seeds by speed, RTK-fixed and all."""
    cfg = d.config if not float_fraction else with_outages(d.config, float_fraction)
    run_ = simulate(cfg)
    inputs = gateway_inputs(run_)
    errs, landings = _methods(run_, inputs, d.fitter, which=(CONFIGURED, ORACLE))
    settings = section(d.fitter.configured(cfg.machine, cfg.timing), pitch_track_m=PITCH_TRACK_M)
    out: dict[str, Any] = {"draw": d.index, "seeds": len(run_.seeds)}
    degraded = cfg.receiver.degraded(np.array([s.t_land for s in run_.seeds]))
    passes = np.array([s.pass_index for s in run_.seeds])
    stored = np.array([la.drop.fix != "rtk_fixed" or la.drop.extrapolated
                       for la in landings[CONFIGURED]])

    def rows(err: Errors, held: np.ndarray) -> dict[str, float]:
        m = _masks(run_, held)
        r = {k: _mean_mm(err, m[k]) for k in ("4–12 km/h", "16 km/h", "4–16 km/h")}
        r["all seeds 4–12 km/h"] = _mean_mm(err, held & (passes >= 0) & (passes <= 2))
        r["all seeds 16 km/h"] = _mean_mm(err, held & (passes == 3))
        r["float/dropout"] = _mean_mm(err, held & degraded)
        return r

    pairs, held = survey_pairs(run_, landings[CONFIGURED])
    cal = calibrate(run_, landings[CONFIGURED], settings, pairs)
    out["configured"] = rows(errs[CONFIGURED], held)
    out["calibrated"] = rows(cal.errors, held)
    out["oracle"] = rows(errs[ORACLE], held)
    out["fit"] = cal.fit.settings(settings)
    out["float/dropout seeds"] = int((held & degraded).sum())
    out["flagged"] = int((held & degraded & stored).sum())
    acc = [la.drop.accuracy_m for la, h, g in zip(landings[CONFIGURED], held, degraded,
                                                    strict=True) if h and g]
    known = [a for a in acc if a is not None]
    out["stated accuracy mm"] = float(np.median(known)) * 1000.0 if known else math.nan
    err = cal.errors.total[held & degraded]
    within = [e <= a for e, a in zip(err.tolist(), acc, strict=True) if a is not None]
    out["within stated"] = float(np.mean(within)) * 100.0 if within else math.nan
    half_pairs, half_held = survey_pairs(run_, landings[CONFIGURED], passes=(2, 3))
    try:
        half = calibrate(run_, landings[CONFIGURED], settings, half_pairs)
        out["one half"] = rows(half.errors, half_held)
        out["one half"]["cli refused"] = bool(half.fit.problems())  # plausibility
        out["one half"]["cli warned"] = bool(half.fit.coverage_warnings)
    except SurveyError as exc:
        out["one half"] = {"refused": str(exc)}
    return out


def apply_calibration(d: Draw, fitted: PositioningSection) -> dict[str, float]:
    """A later drive of the same drill sown with the calibration of an earlier one."""
    run_ = simulate(d.config)
    inputs = gateway_inputs(run_)
    err = landing_errors(run_, replay(fitted, "interpolated", inputs, baseline_offset_deg(run_)))
    m = _masks(run_, np.ones(len(run_.seeds), bool))
    return {k: _mean_mm(err, m[k]) for k in ("4–12 km/h", "16 km/h")}


def _jobs() -> int:
    return max(1, min(int(os.environ.get("SOWGATE_BENCH_JOBS", "2")), os.cpu_count() or 1))


def _pool_map(fn: Any, items: Sequence[Any]) -> list[Any]:
    if _jobs() == 1:
        return [fn(x) for x in items]
    with ProcessPoolExecutor(_jobs()) as pool:
        return list(pool.map(fn, items))


def _float20(d: Draw) -> dict[str, Any]:
    return evaluate_draw(d, float_fraction=0.2)


def _carry(job: tuple[Draw, PositioningSection]) -> dict[str, float]:
    return apply_calibration(*job)


def over_draws(n: int = DRAWS, carried: int = 4) -> dict[str, Any]:
    """The headline over ``n`` draws, the RTK-float-20 % row over the same draws, and the
    calibration of the first ``carried`` draws applied to their next five drives each."""
    ds = draws(n)
    base = _pool_map(evaluate_draw, ds)
    flt = _pool_map(_float20, ds)
    jobs = [(nd, r["fit"]) for d, r in zip(ds[:carried], base, strict=False)
            for nd in next_drives(d)]
    carry = _pool_map(_carry, jobs)
    for r in base + flt:
        r.pop("fit")
    return {"draws": base, "float 20 %": flt, "next drives": carry}


TARGET_P90_MM = {"4–12 km/h": 25.0, "16 km/h": 30.0}


def draws_markdown(od: dict[str, Any]) -> tuple[str, bool]:
    """The headline table over the draws and its sensitivity rows; and whether the targets
    (p90 over the draws, RTK-fixed seeds, after the survey calibration) are met."""
    base, flt, carry = od["draws"], od["float 20 %"], od["next drives"]

    def cells(rows: list[dict[str, Any]], part: str, key: str) -> tuple[str, dict[str, float]]:
        s = summary([r[part].get(key, math.nan) for r in rows])
        if s["n"] == 0:
            return "– | – | – | –", s
        return f"{s['median']:.1f} | {s['p90']:.1f} | {s['worst']:.1f} | {s['n']}", s

    lines = [
        "### Seed landing-position error against an independent truth (paper C, issues 16, 25)",
        "",
        f"#### Over {len(base)} independent truth draws (issue 25)",
        "",
        "Each draw (`benchmarks.positioning_draws`) is another field, drill, seed lot, "
        "receiver and fitter's tape, each parameter from a stated physical range (slopes "
        "0–4°, lot 6.5–9.5 mm with friction 0.40–0.70, RTK σ 8–16 mm τ 30–120 s, latency "
        "25–60 ms, lever arm and latency entered ±3 cm / ±12 ms off, ...), with a 6 s float "
        "period and a 1.5 s dropout. Per draw: the mean error of the seeds not surveyed; "
        "over the draws: median, p90 and worst (the target is judged on p90). \"RTK-fixed "
        "seeds\" leaves out seeds sown within 0.5 s of float or dropout; \"all seeds\" keeps "
        "them (each such record carries the receiver's stated accuracy, `accuracy_m`).",
        "",
        "| row | median mm | p90 mm | worst mm | draws |",
        "|---|---:|---:|---:|---:|",
    ]
    met = True
    for part, label in (("calibrated", "after survey calibration"),
                        ("configured", "as configured (no survey)"), ("oracle", "oracle")):
        for key, name in (("4–12 km/h", "RTK-fixed seeds, 4–12 km/h"),
                          ("16 km/h", "RTK-fixed seeds, 16 km/h"),
                          ("all seeds 4–12 km/h", "all seeds, 4–12 km/h"),
                          ("all seeds 16 km/h", "all seeds, 16 km/h")):
            text, s = cells(base, part, key)
            target = TARGET_P90_MM.get(key) if part == "calibrated" else None
            verdict = ""
            if target is not None:
                ok = s["p90"] <= target
                met &= ok
                verdict = f" (target p90 ≤ {target:g}: {'met' if ok else 'NOT met'})"
            lines.append(f"| {label}, {name}{verdict} | {text} |")
    text, _ = cells(base, "calibrated", "float/dropout")
    lines.append(f"| after survey calibration, float/dropout seeds only | {text} |")
    acc = summary([r.get("stated accuracy mm", math.nan) for r in base])
    if acc["n"]:
        lines.append(f"| their stated accuracy (`accuracy_m`, median of the draw) | "
                     f"{acc['median']:.0f} | {acc['p90']:.0f} | {acc['worst']:.0f} | "
                     f"{acc['n']} |")
    within = summary([r.get("within stated", math.nan) for r in base])
    if within["n"]:
        lines.append(f"| float/dropout seeds within their stated accuracy, % (median of the "
                     f"draw) | {within['median']:.0f} | p10 "
                     f"{float(np.percentile([r['within stated'] for r in base], 10)):.0f} | "
                     f"{within['best']:.0f} (lowest) | {within['n']} |")
    flagged = sum(r["flagged"] for r in base)
    total = sum(r["float/dropout seeds"] for r in base)
    lines += [
        "",
        f"Float/dropout seeds: {total} over the draws, {flagged} of them stored as not "
        "RTK-fixed or extrapolated (the others lie within the ±0.5 s margin, sown on a fix).",
        "",
        "Sensitivity (same statistics; each row changes one thing):",
        "",
        "| row | median mm | p90 mm | worst mm | draws |",
        "|---|---:|---:|---:|---:|",
    ]
    refused = [r for r in base if "refused" in r["one half"] or r["one half"]["cli refused"]]
    warned = [r for r in base if r["one half"].get("cli warned")]
    for key in ("4–12 km/h", "16 km/h"):
        text, _ = cells([r for r in base if "refused" not in r["one half"]], "one half", key)
        lines.append(f"| survey of one half of the field (12 and 16 km/h passes only), "
                     f"applied anyway, {key} | {text} |")
    lines.append(f"| ... `calibrate positions` on that survey: refused in {len(refused)}, "
                 f"warned (saying what to survey next) in {len(warned)} of {len(base)} draws "
                 "| | | | |")
    for key, name in (("4–12 km/h", "RTK-fixed seeds, 4–12 km/h"),
                      ("all seeds 4–12 km/h", "all seeds, 4–12 km/h"),
                      ("16 km/h", "RTK-fixed seeds, 16 km/h"),
                      ("float/dropout", "float/dropout seeds only")):
        text, _ = cells(flt, "calibrated", key)
        lines.append(f"| RTK float 20 % of the time, {name} | {text} |")
    for key in ("4–12 km/h", "16 km/h"):
        s = summary([r[key] for r in carry])
        lines.append(f"| calibration of one drive applied to the next five (same drill, "
                     f"other fields and days), all RTK-fixed seeds, {key} | "
                     f"{s['median']:.1f} | {s['p90']:.1f} | {s['worst']:.1f} | {s['n']} |")
    lines.append("")
    return "\n".join(lines), met

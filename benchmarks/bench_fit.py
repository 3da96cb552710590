"""Landmark fitting: accuracy against the Cramér–Rao bound, and speed against error.

Four parts, all on readings simulated from the physics functions
(:mod:`sonarloc.fit.synth`: eq. 3 / piston / waveform delays, log-normal amplitude,
5 us jitter, 2 us counter) so the truth is known exactly:

1. *Accuracy*: Monte-Carlo bearing and range RMSE of poles and rods through the whole
   pipeline (segmenter, fit, model selection) against the Cramér–Rao bound of the same
   scan geometry (:func:`sonarloc.fit.crlb.crlb`, with the echo/no-echo information the
   fitter uses); also the bound from the TOF curve alone (PHYSICS.md's numbers).
2. *Methods side by side* on the same segments: the conventional reading (object on the
   beam axis at the minimum TOF), a plain ``scipy.optimize.curve_fit`` of eq. 3 per
   segment (the paper's inverse problem), the batch fitter alone and the full pipeline:
   CPU time per segment, errors, failures.
3. *Batch throughput*: segments per second of ``fit_batch`` by segment size, one core.
4. *A large scan CSV through ``sonarloc fit``*: parsing, segmentation and fitting time.

Times are CPU seconds of this process (the machine is shared; CPU time is what one core
spends), medians of repeated runs. Run: ``python benchmarks/bench_fit.py [--quick]``;
writes benchmarks/results/fit.md and fit.png.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")   # one core (effective when run as a script)

import argparse  # noqa: E402
import datetime  # noqa: E402
import math  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable, Sequence  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from scipy.optimize import OptimizeWarning, curve_fit  # noqa: E402

from benchmarks._machine import SHARED, machine_line  # noqa: E402
from sonarloc.fit.crlb import crlb  # noqa: E402
from sonarloc.fit.landmarks import conventional, fit_segments  # noqa: E402
from sonarloc.fit.lsq import FitConfig, fit_batch, pack_segments  # noqa: E402
from sonarloc.fit.segment import Segment, Segmenter  # noqa: E402
from sonarloc.fit.synth import Reflector, pan_scan, rotation_scan, simulate_readings  # noqa: E402
from sonarloc.io.scancsv import ScanReadings, write_scan_csv  # noqa: E402
from sonarloc.physics.tof import ModuleParams  # noqa: E402

MOD = ModuleParams()
C = MOD.c_mps
SIGMA = math.radians(MOD.sigma_deg)


def cpu_median(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """Median CPU time [s] of ``fn()`` over ``repeats`` runs, and its last result."""
    times = []
    out: object = None
    for _ in range(repeats):
        t0 = time.process_time()
        out = fn()
        times.append(time.process_time() - t0)
    return float(np.median(times)), out


# ---------------------------------------------------------------- 1. accuracy vs CRB

@dataclass(frozen=True)
class Scenario:
    name: str
    kappa: float
    range_m: float
    step_deg: float       # pan step; 0 = drive-by with a side-looking sensor
    tier: str             # data tier (the simulator's)
    fit_tier: str         # the fitter's model for the bound


SCENARIOS = [
    Scenario("pole, 1.5 m, pan 0.3 deg (paper)", 0.67, 1.5, 0.3, "gauss", "gauss"),
    Scenario("rod, 1.5 m, pan 0.3 deg (paper)", 2.68, 1.5, 0.3, "gauss", "gauss"),
    Scenario("pole, 2.5 m, pan 2 deg", 0.67, 2.5, 2.0, "gauss", "gauss"),
    Scenario("rod, 2.5 m, pan 2 deg", 2.68, 2.5, 2.0, "gauss", "gauss"),
    Scenario("pole, 1.2 m, drive-by", 0.67, 1.2, 0.0, "gauss", "gauss"),
    Scenario("pole, 1.5 m, pan 0.3 deg, simulator auto tier", 0.67, 1.5, 0.3, "auto",
             "waveform"),
    Scenario("rod, 1.5 m, pan 0.3 deg, simulator auto tier", 2.68, 1.5, 0.3, "auto",
             "waveform"),
]


def scenario_scan(sc: Scenario, rng: np.random.Generator
                  ) -> tuple[ScanReadings, Reflector, float, float]:
    """One scan of the scenario: readings, the reflector, true range and bearing."""
    if sc.step_deg > 0:
        bearing = float(rng.uniform(-10.0, 10.0))
        refl = Reflector.polar(sc.range_m, bearing, sc.kappa)
        scan = pan_scan([refl], rng, -40.0, 40.0, sc.step_deg, tier=sc.tier)
        return scan, refl, sc.range_m, bearing
    # side-looking sensor on a robot driving along +x at 0.3 m/s, 20 pings/s
    t = np.arange(0.0, 8.0, 0.05)
    x = -1.2 + 0.3 * t + float(rng.uniform(-0.1, 0.1))
    refl = Reflector.point(0.0, sc.range_m, sc.kappa)
    scan = simulate_readings(t, x, 0.0, np.full_like(t, math.pi / 2), [refl], rng,
                             tier=sc.tier)
    return scan, refl, sc.range_m, 90.0


def accuracy(n_trials: int, rng: np.random.Generator) -> list[dict[str, float | str]]:
    rows: list[dict[str, float | str]] = []
    for sc in SCENARIOS:
        segs: list[Segment] = []
        owner: list[int] = []
        truth = []
        for k in range(n_trials):
            scan, refl, r, b = scenario_scan(sc, rng)
            truth.append((scan, refl, r, b))
            for s in Segmenter().feed(scan):
                segs.append(s)
                owner.append(k)
        # the simulated poses are exact: no odometry error to add to the covariance
        lms = fit_segments(segs, odometry_sd_deg_per_m=0.0)
        eb, er, ek, sdb, crb_b, crb_r, tof_b, fails = [], [], [], [], [], [], [], 0
        for k, (scan, refl, _r, _b) in enumerate(truth):
            cand = [lm for lm, o in zip(lms, owner, strict=True) if o == k and lm.ok]
            # the reflecting point seen from the landmark's reference position
            best = None
            for lm in cand:
                rx, ry = lm.ref_pose[0], lm.ref_pose[1]
                tr = math.hypot(refl.a - rx, refl.b - ry)
                tb = math.degrees(math.atan2(refl.b - ry, refl.a - rx))
                d_b = (math.degrees(lm.bearing_rad) - tb + 180.0) % 360.0 - 180.0
                if abs(lm.range_m - tr) < 0.02 and (best is None or abs(d_b) < abs(best[0])):
                    best = (d_b, lm.range_m - tr, lm, (rx, ry))
            if best is None or abs(best[0]) > 5.0:
                fails += 1
                continue
            d_b, d_r, lm, ref = best
            eb.append(d_b)
            er.append(d_r)
            ek.append(lm.kappa_us - sc.kappa)
            sdb.append(float(lm.extra["bearing_sd_deg"]))
            full = crlb("point", [refl.a, refl.b, sc.kappa], scan.x_m, scan.y_m,
                        scan.yaw_rad, tier=sc.fit_tier, ref_index=_ref_index(scan, ref))
            tof_only = crlb("point", [refl.a, refl.b, sc.kappa], scan.x_m, scan.y_m,
                            scan.yaw_rad, tier=sc.fit_tier, detection=False,
                            ref_index=_ref_index(scan, ref))
            crb_b.append(float(full.bearing_sd_rad) ** 2)
            crb_r.append(float(full.range_sd_m) ** 2)
            tof_b.append(float(tof_only.bearing_sd_rad) ** 2)
        rmse_b = float(np.sqrt(np.mean(np.square(eb))))
        rmse_r = float(np.sqrt(np.mean(np.square(er))))
        bound_b = math.degrees(math.sqrt(np.mean(crb_b)))
        bound_r = math.sqrt(np.mean(crb_r))
        rows.append(dict(
            name=sc.name, n=len(eb), fail=fails / n_trials,
            rmse_b=rmse_b, crb_b=bound_b, ratio_b=rmse_b / bound_b,
            tof_b=math.degrees(math.sqrt(np.mean(tof_b))),
            rmse_r_mm=1e3 * rmse_r, crb_r_mm=1e3 * bound_r, ratio_r=rmse_r / bound_r,
            bias_b=float(np.mean(eb)), bias_r_mm=1e3 * float(np.mean(er)),
            rmse_k=float(np.sqrt(np.mean(np.square(ek)))), sd_over_rmse=float(
                np.sqrt(np.mean(np.square(sdb)))) / rmse_b))
        print(f"  {sc.name}: bearing RMSE {rmse_b:.3f} deg (CRB {bound_b:.3f}), range "
              f"{1e3 * rmse_r:.3f} mm (CRB {1e3 * bound_r:.3f})", file=sys.stderr)
    return rows


def _ref_index(scan: ScanReadings, ref: tuple[float, float]) -> int:
    """Index of the reading at the landmark's reference position (last one there)."""
    d = np.hypot(scan.x_m - ref[0], scan.y_m - ref[1])
    return int(np.flatnonzero(d == d.min())[-1])


# ---------------------------------------------------------------- 2. methods side by side

def method_segments(n: int, rng: np.random.Generator
                    ) -> tuple[list[Segment], list[tuple[float, float, float]]]:
    """Pan segments of single poles and rods (1-3 m, 0.3 or 1 deg steps) with truth."""
    segs: list[Segment] = []
    truth = []
    while len(segs) < n:
        kappa = float(rng.choice([0.67, 2.68]))
        r = float(rng.uniform(1.0, 3.0))
        b = float(rng.uniform(-10.0, 10.0))
        step = float(rng.choice([0.3, 1.0]))
        scan = pan_scan([Reflector.polar(r, b, kappa)], rng, -40.0, 40.0, step)
        found = list(Segmenter().feed(scan))
        if not found:
            continue
        segs.append(max(found, key=lambda s: s.n_echo))
        truth.append((r, b, kappa))
    return segs, truth


def _eq3(yaw: np.ndarray, to_us: float, theta0: float, kappa: float) -> np.ndarray:
    return to_us + kappa * np.exp((yaw - theta0) ** 2 / (2.0 * SIGMA * SIGMA))


def curve_fit_segment(seg: Segment) -> tuple[float, float, float] | None:
    """The paper's inverse problem by plain curve_fit: (range_m, bearing_deg, kappa)."""
    r = seg.readings
    ok = np.isfinite(r.tof_us)
    yaw, tof = r.yaw_rad[ok], r.tof_us[ok]
    i = int(np.argmin(tof))
    p0 = (float(tof[i]) - 1.0, float(yaw[i]), 1.0)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", OptimizeWarning)
            p, _ = curve_fit(_eq3, yaw, tof, p0=p0, maxfev=2000)
    except (RuntimeError, ValueError):
        return None
    if not np.all(np.isfinite(p)):
        return None
    to_us = p[0] - 0.5 * MOD.count_period_us
    return to_us * C / 2e6, math.degrees(p[1]), float(p[2])


SMALL_CALL = 400
"""Segments per call of the batch methods' small-batch timing (fixed per-call costs)."""


def methods(n: int, repeats: int, rng: np.random.Generator) -> list[dict[str, float | str]]:
    segs, truth = method_segments(n, rng)
    arrays = [s.arrays() for s in segs]
    small = arrays[:SMALL_CALL]

    def run_conventional() -> list[tuple[float, float, float] | None]:
        out: list[tuple[float, float, float] | None] = []
        for t, x, y, yaw, tof in arrays:
            rr, bb, _ = conventional(t, x, y, yaw, tof)
            out.append((rr, math.degrees(bb), math.nan))
        return out

    def run_curve_fit() -> list[tuple[float, float, float] | None]:
        return [curve_fit_segment(s) for s in segs]

    def run_batch() -> list[tuple[float, float, float] | None]:
        f = fit_batch(pack_segments(arrays), "point", "gauss")
        return [(float(p[0]), math.degrees(float(p[1])), float(p[2])) for p in f.local]

    # reported SDs of the batch methods: bearing [deg], range [m], kappa [us]
    sds: dict[str, np.ndarray] = {}
    sds_rk: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def run_cfg(cfg: FitConfig | None, segments: Sequence[Any] = arrays, name: str = ""
                ) -> Callable[[], list[tuple[float, float, float] | None]]:
        def run() -> list[tuple[float, float, float] | None]:
            f = fit_batch(pack_segments(segments), "point", "gauss", cfg)
            if name:
                sds[name] = np.rad2deg(np.sqrt(f.cov[:, 1, 1]))
                sds_rk[name] = (np.sqrt(f.cov[:, 0, 0]), np.sqrt(f.cov[:, 2, 2]))
            return [(float(p[0]), math.degrees(float(p[1])), float(p[2])) for p in f.local]
        return run

    def run_full() -> list[tuple[float, float, float] | None]:
        return [(lm.range_m, math.degrees(lm.bearing_rad), lm.kappa_us) if lm.ok else None
                for lm in fit_segments(segs)]

    rows: list[dict[str, float | str]] = []
    n_profile = ("sonarloc fit_batch, `FitConfig.profile()` (12 deg grid on <= 16 echoes, "
                 "bearing on the echoes' profiled LS cost: 3 stencils; echoes only)")
    n_fast = ("sonarloc fit_batch, `FitConfig.fast()` (start from the arc's edges where it "
              "is whole, one guarded step; else 12 deg grid on <= 16 echoes, two; "
              "derivatives at the result; float32)")
    n_fast_grid = ("sonarloc fit_batch, `FitConfig.fast(start=\"grid\", arc_iterations=None)` "
                   "(the earlier `fast()` preset: 12 deg grid on <= 16 echoes for all, two guarded "
                   "steps)")
    n_batch = ("sonarloc fit_batch, `FitConfig.batch()` (6 deg grid, one reweighted round; "
               "float32)")
    n_default = "sonarloc fit_batch (default)"
    small_cfg = {n_profile: FitConfig.profile(), n_fast: FitConfig.fast(),
                 n_fast_grid: FitConfig.fast(start="grid", arc_iterations=None),
                 n_batch: FitConfig.batch(), n_default: None}
    runners = [("conventional (beam axis at min TOF)", run_conventional),
               ("scipy curve_fit per segment (eq. 3)", run_curve_fit),
               *((name, run_cfg(cfg, name=name)) for name, cfg in small_cfg.items()),
               ("sonarloc fit_segments (default, with model selection)", run_full)]
    results = []
    t_small: dict[str, float] = {}
    for name, fn in runners:
        fn()   # warm-up (tables, imports)
        t, res = cpu_median(fn, repeats)
        results.append((name, t, res if isinstance(res, list) else []))
        if name in small_cfg and len(small) < n:
            # the same fitter called on SMALL_CALL segments at a time
            t_small[name] = cpu_median(run_cfg(small_cfg[name], small), 3 * repeats)[0] / len(
                small)
    # the segments curve_fit handled (no failure, no divergence): errors compared there too
    cf_ok = np.array([_within(est, tr) for est, tr in zip(results[1][2], truth, strict=True)])
    for name, t, out in results:
        eb, er, ek, eb_cf, fails, diverged = [], [], [], [], 0, 0
        for k, (est, (r, b, kap)) in enumerate(zip(out, truth, strict=True)):
            if est is None:
                fails += 1
                continue
            if not _within(est, (r, b, kap)):
                diverged += 1
                continue
            d_b = (est[1] - b + 180.0) % 360.0 - 180.0
            eb.append(d_b)
            if cf_ok[k]:
                eb_cf.append(d_b)
            er.append(est[0] - r)
            if math.isfinite(est[2]):
                ek.append(est[2] - kap)
        sd_ratio = z_rms = sd_ratio_r = sd_ratio_k = math.nan
        if name in sds:
            # reported bearing SD against the error, over the segments not diverged whose
            # SD is below the FLAT threshold (those a pipeline would report as OK)
            ok = np.array([_within(est, tr) for est, tr in zip(out, truth, strict=True)])
            ok &= sds[name] < FitConfig().flat_bearing_sd_deg
            d = np.array([(est[1] - tr[1] + 180.0) % 360.0 - 180.0 if est is not None
                          else math.nan for est, tr in zip(out, truth, strict=True)])[ok]
            sd_ratio = float(np.sqrt(np.mean(sds[name][ok] ** 2)) / np.sqrt(np.mean(d ** 2)))
            z_rms = float(np.sqrt(np.mean((d / sds[name][ok]) ** 2)))
            # range and kappa likewise
            est = np.array([e if e is not None else (math.nan,) * 3 for e in out])[ok]
            tru = np.array(truth)[ok]
            for j, sd_j in ((0, sds_rk[name][0][ok]), (2, sds_rk[name][1][ok])):
                rat = float(np.sqrt(np.mean(sd_j ** 2) / np.mean((est[:, j] - tru[:, j]) ** 2)))
                if j == 0:
                    sd_ratio_r = rat
                else:
                    sd_ratio_k = rat
        rows.append(dict(
            name=name, us_per_seg=1e6 * t / n, sd_ratio=sd_ratio, z_rms=z_rms,
            sd_ratio_r=sd_ratio_r, sd_ratio_k=sd_ratio_k,
            flat=float(np.mean(sds[name] >= FitConfig().flat_bearing_sd_deg))
            if name in sds else math.nan,
            us_per_seg_small=1e6 * t_small[name] if name in t_small else math.nan,
            rmse_b=float(np.sqrt(np.mean(np.square(eb)))) if eb else math.nan,
            rmse_b_cf=float(np.sqrt(np.mean(np.square(eb_cf)))) if eb_cf else math.nan,
            rmse_r_mm=1e3 * float(np.sqrt(np.mean(np.square(er)))) if er else math.nan,
            rmse_k=float(np.sqrt(np.mean(np.square(ek)))) if ek else math.nan,
            fail=(fails + diverged) / n, diverged=diverged / n))
        print(f"  {name}: {1e6 * t / n:.0f} us/segment", file=sys.stderr)
    return rows


def _small_cell(r: dict[str, float | str], curve: dict[str, float | str]) -> str:
    t = float(r["us_per_seg_small"])
    if math.isnan(t):
        return ""
    return f"{t:.0f} ({float(curve['us_per_seg']) / t:.1f}x)"


def _calib_cell(r: dict[str, float | str]) -> str:
    if math.isnan(float(r["sd_ratio"])):
        return " |  | "
    return (f"{float(r['sd_ratio']):.2f}; {float(r['z_rms']):.2f} | "
            f"{float(r['sd_ratio_r']):.2f}; {float(r['sd_ratio_k']):.2f} | "
            f"{100 * float(r['flat']):.1f} %")


def _within(est: tuple[float, float, float] | None, truth: tuple[float, float, float]
            ) -> bool:
    """A result within 10 deg and 5 cm of the truth (otherwise a failure or divergence)."""
    if est is None:
        return False
    d_b = (est[1] - truth[1] + 180.0) % 360.0 - 180.0
    return bool(math.isfinite(est[0]) and abs(d_b) < 10.0 and abs(est[0] - truth[0]) < 0.05)


# ---------------------------------------------------------------- 3. throughput

def throughput(n: int, repeats: int, rng: np.random.Generator
               ) -> list[dict[str, float | str]]:
    rows: list[dict[str, float | str]] = []
    for step in (2.0, 1.0, 0.3):
        arrays = []
        while len(arrays) < n:
            r = float(rng.uniform(1.0, 3.0))
            scan = pan_scan([Reflector.polar(r, float(rng.uniform(-10, 10)),
                                             float(rng.choice([0.67, 2.68])))],
                            rng, -40.0, 40.0, step)
            found = list(Segmenter().feed(scan))
            if found:
                arrays.append(max(found, key=lambda s: s.n_echo).arrays())
        batch = pack_segments(arrays)
        fit_batch(batch, "point", "gauss")
        t_b, _ = cpu_median(lambda b=batch: fit_batch(b, "point", "gauss"), repeats)
        t_p, _ = cpu_median(lambda b=batch: fit_batch(b, "point", "gauss", FitConfig.batch()),
                            repeats)
        t_f, _ = cpu_median(lambda b=batch: fit_batch(b, "point", "gauss", FitConfig.fast()),
                            repeats)
        t_pr, _ = cpu_median(
            lambda b=batch: fit_batch(b, "point", "gauss", FitConfig.profile()), repeats)
        t_w, _ = cpu_median(lambda b=batch: fit_batch(b, "point", "waveform"), repeats)
        rows.append(dict(step=step, echoes=float(batch.valid.sum(1).mean()),
                         noecho=float(batch.ne_valid.sum(1).mean()), segs_s=n / t_b,
                         segs_s_batch=n / t_p, segs_s_fast=n / t_f, segs_s_profile=n / t_pr,
                         segs_s_waveform=n / t_w))
        print(f"  pan {step} deg: {n / t_b:.0f} segments/s", file=sys.stderr)
    return rows


# ---------------------------------------------------------------- 4. large CSV

BASELINE_REV = "0eca529"
"""main on 2026-11-29, before the pair search's grouping by
motion alone and the segmenter's skipped pairs: section 4's "before" columns, run from
a `git archive` of it."""

_STAGES = r"""
import json, sys, time
import numpy as np
from sonarloc.fit.landmarks import _resolve, fit_segments
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.segment import Segmenter
from sonarloc.io.scancsv import read_scan_csv

path, repeats = sys.argv[1], int(sys.argv[2])
times = {"parse": [], "segment": [], "fit": [], "resolve": []}
for _ in range(repeats):
    t0 = time.process_time()
    scan = read_scan_csv(path)
    t1 = time.process_time()
    seg = Segmenter()   # as fit_scan does (feed_block)
    segs = seg.feed_block(scan) if hasattr(seg, "feed_block") else list(seg.feed(scan))
    t2 = time.process_time()
    lms = fit_segments(segs)
    t3 = time.process_time()
    out = _resolve(segs, lms, FitConfig())
    t4 = time.process_time()
    for k, v in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
        times[k].append(v)
res = {k: float(np.median(v)) for k, v in times.items()}
# the first fit stage also sets up the waveform tier (template and tables, imports)
res["fit_first_extra"] = times["fit"][0] - res["fit"]
# each round's own fitting side / parse (its stages back to back: the load the two
# share), the median over the rounds after the first (the set-up's)
ratios = [(times["segment"][i] + times["fit"][i] + times["resolve"][i]) / times["parse"][i]
          for i in range(min(1, repeats - 1), repeats)]
res["round_ratio"] = float(np.median(ratios))
res.update(segments=len(segs), ok=sum(lm.ok for lm in lms), landmarks=len(out))
print(json.dumps(res))
"""


_DRIVE_STAGES = r"""
import json, sys, time
from sonarloc.fit.landmarks import _split_groups, fit_segments
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.pair import resolve_pair_groups
from sonarloc.fit.result import FitStatus
from sonarloc.fit.segment import Segmenter
from sonarloc.io.scancsv import read_scan_csv

path = sys.argv[1]
cfg = FitConfig()
t0 = time.process_time()
scan = read_scan_csv(path)
t1 = time.process_time()
segs = Segmenter().feed_block(scan)
t2 = time.process_time()
lms = fit_segments(segs, cfg)
t3 = time.process_time()
groups = resolve_pair_groups(segs, lms, cfg)
t4 = time.process_time()
todo = [k for k, g in enumerate(groups) if len(g) == 1 and g[0].status is FitStatus.UNRESOLVED]
parts = _split_groups([segs[k] for k in todo], [groups[k][0] for k in todo], cfg)
t5 = time.process_time()
for k, p in zip(todo, parts):
    groups[k] = p
final = [lm for g in groups for lm in g]
print(json.dumps({"readings": len(scan), "parse": t1 - t0, "segment": t2 - t1, "fit": t3 - t2,
                  "pairs": t4 - t3, "split": t5 - t4, "segments": len(segs),
                  "unresolved": sum(lm.status is FitStatus.UNRESOLVED for lm in lms),
                  "split_tried": len(todo), "split_done": sum(len(p) == 2 for p in parts),
                  "landmarks": len(final), "ok": sum(lm.ok for lm in final),
                  "echoes": int((scan.tof_us == scan.tof_us).sum())}))
"""


def drive_csv(duration_s: float, repeats: int) -> dict[str, float]:
    """Section 4's second table: `sonarloc fit`'s stages on the scan CSV of a moving ring
    (the room, 16 transducers, poses from odometry: what a robot logs), *now* and
    *before* (:data:`BASELINE_REV`), ``repeats`` fresh processes each, alternating
    (medians); keys ``now_*`` / ``before_*``."""
    import json

    from sonarloc.maps import load_map
    from sonarloc.world.rig import rig_by_name
    from sonarloc.world.simulate import simulate_scan

    sim = simulate_scan(load_map(ROOT / "maps" / "room.geojson"), rig_by_name("ring16"),
                        frame="odom", duration_s=duration_s, seed=3)
    runs: dict[str, list[float]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "drive.csv"
        write_scan_csv(path, sim.readings)
        roots = _roots(Path(tmp))
        for _ in range(repeats):           # alternating, so both see the same load
            for name, root in roots.items():
                res = json.loads(_run_root(root, ["-c", _DRIVE_STAGES, str(path)]).stdout)
                for k, v in res.items():
                    runs.setdefault(f"{name}_{k}", []).append(float(v))
    return {"duration_s": duration_s, "repeats": float(repeats),
            **{k: float(np.median(v)) for k, v in runs.items()}}


def _roots(tmp: Path) -> dict[str, Path]:
    """Code versions to run: ``now`` (this tree) and ``before`` (a `git archive` of
    :data:`BASELINE_REV` under ``tmp``, when git can make one)."""
    roots = {"now": ROOT}
    base = tmp / "base"
    if base.is_dir():
        return {**roots, "before": base}
    try:
        arch = subprocess.run(["git", "-C", str(ROOT), "archive", BASELINE_REV, "sonarloc"],
                              capture_output=True, check=True)
        base.mkdir()
        subprocess.run(["tar", "-x", "-C", str(base)], input=arch.stdout, check=True)
        roots["before"] = base
    except (OSError, subprocess.CalledProcessError):
        print("  (no baseline: git archive failed)", file=sys.stderr)
    return roots


_SAME_INPUT = r"""
import pickle, sys
import numpy as np
from sonarloc.fit.landmarks import _resolve, fit_segments
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.segment import Segmenter
from sonarloc.io.scancsv import read_scan_csv

mode, path, data, out = sys.argv[1:5]


def plain(a):
    # the values as a flat list, NaN as None (so that equal means equal)
    return [None if v != v else v for v in np.asarray(a, dtype=float).ravel().tolist()]


if mode == "make":          # segments and single fits of this version: the shared input
    segs = list(Segmenter().feed(read_scan_csv(path)))
    pickle.dump((segs, fit_segments(segs)), open(data, "wb"))
segs, lms = pickle.load(open(data, "rb"))
res = _resolve(segs, lms, FitConfig())
seg_rows = [(s.seg_id, s.closed_by, s.occluded,
             [plain(a) for a in (s.readings.t_s, s.readings.x_m, s.readings.y_m,
                                 s.readings.yaw_rad, s.readings.tof_us, s.readings.sensor)])
            for s in Segmenter().feed(read_scan_csv(path))]
lm_rows = [(lm.kind, plain(lm.params), plain(lm.cov), plain(lm.range_m), plain(lm.bearing_rad),
            lm.status.value, lm.reason, lm.n_readings, lm.tier) for lm in res]
pickle.dump((seg_rows, lm_rows), open(out, "wb"))
"""


def _same_input_check(roots: dict[str, Path], path: Path, tmp: Path) -> dict[str, float]:
    """The segmenter and the pair/cut stage of both versions on the same input (this
    version's segments and single fits): how many segments and landmarks differ. Keeps
    what the fit stage (`fit_segments`, changed by others since the baseline) does out
    of the comparison."""
    import pickle
    data, out_now, out_b = tmp / "input.pkl", tmp / "now.pkl", tmp / "before.pkl"
    _run_root(roots["now"], ["-c", _SAME_INPUT, "make", str(path), str(data), str(out_now)])
    _run_root(roots["before"], ["-c", _SAME_INPUT, "use", str(path), str(data), str(out_b)])
    (seg_n, lm_n), (seg_b, lm_b) = (pickle.loads(f.read_bytes()) for f in (out_now, out_b))
    same_len = len(seg_n) == len(seg_b) and len(lm_n) == len(lm_b)
    return {"seg_diff": float(sum(a != b for a, b in zip(seg_n, seg_b, strict=False))
                              + abs(len(seg_n) - len(seg_b))),
            "resolve_diff": float(sum(a[:5] + a[7:] != b[:5] + b[7:]
                                      for a, b in zip(lm_n, lm_b, strict=False))
                                  + abs(len(lm_n) - len(lm_b))),
            "resolve_reason_diff": float(sum(a[6] != b[6] for a, b in zip(lm_n, lm_b,
                                                                           strict=False))),
            "same_len": float(same_len), "n_resolved": float(len(lm_n))}


def _run_root(root: Path, args: list[str]) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(root))
    return subprocess.run([sys.executable, *args], capture_output=True, text=True, env=env,
                          check=True, cwd=tempfile.gettempdir())


def _children_cpu_s() -> float:
    """CPU seconds (user + system) of this process's finished children so far."""
    import resource
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return float(ru.ru_utime + ru.ru_stime)


def _landmark_diff(a: dict[str, object], b: dict[str, object]) -> dict[str, float]:
    """Landmarks of two `fit --json` outputs: how many differ in (kind, range, bearing,
    kappa, status, covariance, n_readings, position, tier), how many only in their
    reason, how many in kind or status, and the median / largest change of bearing
    [deg] and range [mm] (NaN if the lists differ in length)."""
    la, lb = a["landmarks"], b["landmarks"]
    assert isinstance(la, list) and isinstance(lb, list)
    keys = ("kind", "range_m", "bearing_deg", "kappa_us", "status", "cov", "n_readings",
            "x_m", "y_m", "rho_m", "alpha_deg", "tier")
    if len(la) != len(lb):
        return {"diff_fields": float(max(len(la), len(lb))), "diff_reasons": math.nan,
                "diff_kind_status": math.nan, "dbear_med": math.nan, "dbear_max": math.nan,
                "drange_med_mm": math.nan, "drange_max_mm": math.nan}
    pairs = list(zip(la, lb, strict=True))
    db = [abs((float(x["bearing_deg"]) - float(y["bearing_deg"]) + 180.0) % 360.0 - 180.0)
          for x, y in pairs if x.get("bearing_deg") is not None
          and y.get("bearing_deg") is not None]
    dr = [1e3 * abs(float(x["range_m"]) - float(y["range_m"])) for x, y in pairs
          if x.get("range_m") is not None and y.get("range_m") is not None]
    return {
        "diff_fields": float(sum(any(x.get(k) != y.get(k) for k in keys) for x, y in pairs)),
        "diff_reasons": float(sum(x.get("reason") != y.get("reason") and all(
            x.get(k) == y.get(k) for k in keys) for x, y in pairs)),
        "diff_kind_status": float(sum(x.get("kind") != y.get("kind")
                                      or x.get("status") != y.get("status")
                                      for x, y in pairs)),
        "dbear_med": float(np.median(db)) if db else math.nan,
        "dbear_max": float(np.max(db)) if db else math.nan,
        "drange_med_mm": float(np.median(dr)) if dr else math.nan,
        "drange_max_mm": float(np.max(dr)) if dr else math.nan}


def large_csv(n_readings: int, repeats: int, rng: np.random.Generator
              ) -> dict[str, float]:
    """Section 4: the stages of `sonarloc fit` on a large scan CSV, now and (same run,
    alternating) at :data:`BASELINE_REV`; each stage in its own process."""
    import json
    scan = rotation_scan(n_readings, rng)
    out: dict[str, float] = {"readings": n_readings}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.csv"
        write_scan_csv(path, scan)
        roots = _roots(Path(tmp))
        walls: dict[str, list[float]] = {k: [] for k in roots}
        cpus: dict[str, list[float]] = {k: [] for k in roots}
        starts: dict[str, list[float]] = {k: [] for k in roots}
        outputs: dict[str, dict[str, object]] = {}
        for _ in range(repeats):           # alternating, so both see the same load
            for name, root in roots.items():
                t0, c0 = time.perf_counter(), _children_cpu_s()
                proc = _run_root(root, ["-m", "sonarloc", "fit", str(path), "--json"])
                walls[name].append(time.perf_counter() - t0)
                cpus[name].append(_children_cpu_s() - c0)
                outputs[name] = json.loads(proc.stdout)
                t0 = time.perf_counter()
                _run_root(root, ["-c", "import sonarloc.commands.fit"])
                starts[name].append(time.perf_counter() - t0)
        for name, root in roots.items():
            st = json.loads(_run_root(root, ["-c", _STAGES, str(path), str(repeats)]).stdout)
            for k, v in st.items():
                out[f"{name}_{k}"] = float(v)
            out[f"{name}_cli_wall"] = float(np.median(walls[name]))
            out[f"{name}_cli_cpu"] = float(np.median(cpus[name]))
            out[f"{name}_import_wall"] = float(np.median(starts[name]))
        if "before" in outputs:
            out.update(_landmark_diff(outputs["before"], outputs["now"]))
            out.update(_same_input_check(roots, path, Path(tmp)))
        out["n_landmarks"] = len(outputs["now"]["landmarks"])  # type: ignore[arg-type]
    side = out["now_segment"] + out["now_fit"] + out["now_resolve"]
    print(f"  large CSV: fitting side {side:.2f} s, parse {out['now_parse']:.2f} s",
          file=sys.stderr)
    return out


def large_csv_lines(csv: dict[str, float], q: bool) -> list[str]:
    """Section 4 of the report."""
    has_before = "before_parse" in csv
    rows = [("parse (`read_scan_csv`)", "parse"),
            ("segment (`Segmenter.feed_block`, as `fit_scan`)", "segment"),
            ("fit + model selection (`fit_segments`)", "fit"),
            ("overlapping-reflector pair fits and cuts (`_resolve`, as `fit_scan`)",
             "resolve")]
    lines = [
        "",
        f"## 4. `sonarloc fit` on a large scan CSV ({int(csv['readings'])} readings, "
        f"continuous rotation at 1 deg per ping over 8 reflectors: "
        f"{int(csv['now_segments'])} segments, {int(csv['now_ok'])} fitted ok, "
        f"{int(csv['n_landmarks'])} landmarks)",
        "",
        "CPU seconds of each stage (medians of "
        f"{'1' if q else '3'} in a fresh process per code version), *now* and *before* "
        f"(main at {BASELINE_REV}, 2026-11-29, before the pair search's grouping by motion "
        "alone and the segmenter's skipped pairs, run from a `git archive` of it "
        "in the same run, alternating with *now*); CPU and wall clock of the whole "
        "command (`python -m sonarloc fit SCAN.csv --json`, medians) and the wall clock of "
        "its start-up (`import sonarloc.commands.fit`). With the machine shared, wall "
        "clock runs well above CPU time. The first fit stage of a process also sets up the "
        "waveform tier (its template and tables; formerly ~0.4 s of it importing "
        "scipy.signal and scipy.optimize, which a fit no longer imports): the stage "
        "medians leave it out, its row below and the command include it.",
        "",
        "| stage | before (s) | now (s) | speed-up | share now |",
        "|---|---:|---:|---:|---:|",
    ]
    total = sum(csv[f"now_{k}"] for _, k in rows)
    for label, k in rows:
        now = csv[f"now_{k}"]
        b = csv.get(f"before_{k}", math.nan)
        lines.append(f"| {label} | {b:.2f} | {now:.2f} | "
                     f"{b / now if has_before else math.nan:.1f}x | {100 * now / total:.0f} % |")
    side_now = sum(csv[f"now_{k}"] for k in ("segment", "fit", "resolve"))
    side_b = sum(csv.get(f"before_{k}", math.nan) for k in ("segment", "fit", "resolve"))
    b_parse = csv.get("before_parse", math.nan)
    b_wall = csv.get("before_cli_wall", math.nan)
    b_cpu = csv.get("before_cli_cpu", math.nan)
    lines += [
        f"| **fitting side** (segment + fit + pairs) / parse | {side_b / b_parse:.2f} | "
        f"**{side_now / csv['now_parse']:.2f}** | | |",
        f"| the same, each round's own (its parse and fitting back to back in one process; "
        f"median over the rounds after the first) | "
        f"{csv.get('before_round_ratio', math.nan):.2f} | "
        f"**{csv['now_round_ratio']:.2f}** | | |",
        f"| fitting side with the set-up below / parse | "
        f"{(side_b + csv.get('before_fit_first_extra', math.nan)) / b_parse:.2f} | "
        f"{(side_now + csv['now_fit_first_extra']) / csv['now_parse']:.2f} | | |",
        f"| whole command, CPU (user + system) | {b_cpu:.2f} | {csv['now_cli_cpu']:.2f} | "
        f"{b_cpu / csv['now_cli_cpu']:.1f}x | |",
        f"| whole command, wall clock | {b_wall:.2f} | {csv['now_cli_wall']:.2f} | "
        f"{b_wall / csv['now_cli_wall']:.1f}x | |",
        f"| of which start-up (imports), wall clock | "
        f"{csv.get('before_import_wall', math.nan):.2f} | {csv['now_import_wall']:.2f} | | |",
        f"| of which the waveform tier's set-up (first fit stage less the median), CPU | "
        f"{csv.get('before_fit_first_extra', math.nan):.2f} | "
        f"{csv['now_fit_first_extra']:.2f} | | |",
        "",
    ]
    if has_before:
        lines.append(
            f"Landmarks of the command, before against now: {int(csv['diff_fields'])} of "
            f"{int(csv['n_landmarks'])} differ in kind, range, bearing, kappa, status, "
            f"covariance, n_readings or tier ({int(csv['diff_kind_status'])} in kind or "
            f"status; bearing changes median {csv['dbear_med']:.2g} deg, largest "
            f"{csv['dbear_max']:.2g} deg; range median {csv['drange_med_mm']:.2g} mm, largest "
            f"{csv['drange_max_mm']:.2g} mm"
            + (f": the fit stage, `fit_segments`, changed since {BASELINE_REV}"
               if csv["diff_fields"] else "")
            + f"); {int(csv['diff_reasons'])} only in their "
            "reason text. The segmenter and the pair/cut stage alone, both versions on the "
            "same input (*now*'s segments and single fits, so changes of `fit_segments` "
            f"since {BASELINE_REV} stay out): {int(csv['seg_diff'])} of "
            f"{int(csv['now_segments'])} segments and {int(csv['resolve_diff'])} of "
            f"{int(csv['n_resolved'])} landmarks differ (kind, parameters, covariance, "
            f"range, bearing, status, n_readings, tier), {int(csv['resolve_reason_diff'])} "
            "in their reason.")
    drives = []
    for i in range(len(DRIVE_S)):
        p = f"drive{i}_"
        if p + "now_readings" in csv:
            drives.append({k[len(p):]: v for k, v in csv.items() if k.startswith(p)})
    if drives:
        lines += _drive_lines(drives)
    return lines


def _drive_lines(drives: list[dict[str, float]]) -> list[str]:
    """Section 4's second table (:func:`drive_csv` of each log)."""
    lines = [
        "",
        "The same command's stages on a moving ring's scan CSV (the room, `ring16`, "
        "transducer poses from odometry, as a robot logs them), a short log and one as "
        "large as the rotation scan above; CPU s, medians of "
        f"{int(drives[0]['repeats'])} fresh processes per code version, alternating. "
        "`UNRESOLVED`: segments no single landmark explains; the cuts are tried on those "
        "still unresolved after the pair stage. *fit ms / segment*: the fitting side "
        "less the segmenter, per segment.",
        "",
        "| log | code | parse | segment | fit + model selection | pairs | cuts of "
        "`UNRESOLVED` segments | fitting side / parse | fit ms / segment | `UNRESOLVED` | "
        "cuts tried / made | landmarks (OK) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for d in drives:
        n = {k[len("now_"):]: v for k, v in d.items() if k.startswith("now_")}
        log = (f"{d['duration_s']:.0f} s: {int(n['readings'])} readings, "
               f"{int(n['echoes'])} echoes, {int(n['segments'])} segments")
        for name in (k for k in ("before", "now") if f"{k}_parse" in d):
            v = {k[len(name) + 1:]: x for k, x in d.items() if k.startswith(name + "_")}
            fit = v["fit"] + v["pairs"] + v["split"]
            side = v["segment"] + fit
            kept = (f"{int(v['landmarks'])} ({int(v['ok'])})" if "landmarks" in v else "-")
            lines.append(
                f"| {log} | {name} | {v['parse']:.2f} | {v['segment']:.2f} | "
                f"{v['fit']:.2f} | {v['pairs']:.2f} | {v['split']:.2f} | "
                f"**{side / v['parse']:.0f}** | {1e3 * fit / v['segments']:.2f} | "
                f"{int(v['unresolved'])} | {int(v['split_tried'])} / "
                f"{int(v['split_done'])} | {kept} |")
    return lines


# ---------------------------------------------------------------- report

def plot(acc: list[dict[str, float | str]], meth: list[dict[str, float | str]],
         path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2), dpi=120)
    names = [str(r["name"]) for r in acc]
    y = np.arange(len(names))
    a1.barh(y - 0.2, [float(r["ratio_b"]) for r in acc], 0.4, label="bearing")
    a1.barh(y + 0.2, [float(r["ratio_r"]) for r in acc], 0.4, label="range")
    a1.axvline(1.0, color="k", lw=0.8)
    a1.axvline(1.2, color="r", ls="--", lw=0.8, label="target 1.2")
    a1.set_yticks(y, names, fontsize=7)
    a1.invert_yaxis()
    a1.set_xlabel("RMSE / Cramér–Rao bound")
    a1.set_title("Monte-Carlo accuracy against the bound", fontsize=9)
    a1.legend(fontsize=7, loc="lower right")
    markers = ["s", "^", "P", "v", "X", "<", "o", "D"]
    for r, m in zip(meth, markers, strict=False):
        a2.loglog(float(r["us_per_seg"]), float(r["rmse_b"]), m, ms=8, label=str(r["name"]))
    a2.set_xlabel("CPU time per segment [us]")
    a2.set_ylabel("bearing RMSE [deg]")
    a2.set_title("Speed against error (same segments)", fontsize=9)
    a2.grid(True, which="both", alpha=0.3)
    a2.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer trials and repeats (smoke run)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "fit.md"))
    ap.add_argument("--only-large-csv", action="store_true",
                    help="rerun section 4 only and replace it in the existing results file")
    ap.add_argument("--skip-large-csv", action="store_true",
                    help="run sections 1-3 only; keep section 4 of the existing results file")
    args = ap.parse_args(argv)
    q = args.quick
    n_trials, n_meth, n_thr, n_csv, repeats = ((40, 60, 1024, 20_000, 1) if q
                                              else (400, 2000, 8192, 200_000, 3))
    if args.only_large_csv:
        return _only_large_csv(Path(args.out), n_csv, repeats, q)
    rng = np.random.default_rng(2003)
    t_start = time.perf_counter()
    print("accuracy ...", file=sys.stderr)
    acc = accuracy(n_trials, rng)
    print("methods ...", file=sys.stderr)
    meth = methods(n_meth, repeats, rng)
    print("throughput ...", file=sys.stderr)
    thr = throughput(n_thr, repeats, rng)
    kept_csv: list[str] | None = None
    if args.skip_large_csv:
        kept_csv = _kept_large_csv(Path(args.out))
    else:
        print("large CSV ...", file=sys.stderr)
        csv = large_csv(n_csv, repeats, np.random.default_rng(2003))
        csv.update(_drive_part(q))

    curve = next(r for r in meth if "curve_fit" in str(r["name"]))
    lines = [
        "# Landmark fitting: accuracy against the Cramér–Rao bound, speed against error",
        "",
        "Readings simulated from the physics functions (`sonarloc.fit.synth`): eq. 3 delays "
        "with a log-normal amplitude (SD 0.25), 5 us jitter, the 2 us counter; *auto* = the "
        "simulator's default tier (piston beam, waveform delays for weak echoes). Every "
        "scan goes through the segmenter, the fit and model selection (`fit_segments`). "
        "Bound: `crlb()` for the same scan geometry with the echo/no-echo information the "
        "fitter uses (model of the row's tier); *TOF-only bound*: from the TOF curve "
        "alone (PHYSICS.md's numbers). Pans run -40..40 deg around a reflector at a random "
        "bearing within +-10 deg; the drive-by is a side-looking sensor on a robot at "
        "0.3 m/s pinging at 20 Hz. The poses are exact, so section 1 fits with "
        "`odometry_sd_deg_per_m=0` (no odometry term in the covariance).",
        "",
        "## 1. Accuracy (Monte Carlo)",
        "",
        "| scenario | trials | fail | bearing RMSE (deg) | bound (deg) | RMSE/bound | "
        "TOF-only bound (deg) | range RMSE (mm) | bound (mm) | RMSE/bound | bias bearing "
        "(deg) / range (mm) | kappa RMSE (us) | reported SD / RMSE |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in acc:
        lines.append(
            f"| {r['name']} | {r['n']} | {100 * float(r['fail']):.1f} % | "
            f"{float(r['rmse_b']):.3f} | {float(r['crb_b']):.3f} | **{float(r['ratio_b']):.2f}** | "
            f"{float(r['tof_b']):.3f} | {float(r['rmse_r_mm']):.3f} | {float(r['crb_r_mm']):.3f} | "
            f"**{float(r['ratio_r']):.2f}** | {float(r['bias_b']):+.3f} / "
            f"{float(r['bias_r_mm']):+.3f} | {float(r['rmse_k']):.3f} | "
            f"{float(r['sd_over_rmse']):.2f} |")
    lines += [
        "",
        f"## 2. Methods side by side ({n_meth} pan segments: poles and rods at 1-3 m, "
        "0.3 or 1 deg steps, eq. 3 data)",
        "",
        "*fail* counts no result, an exception, or an answer off by more than 10 deg or "
        "5 cm (a divergence); errors are over the rest, and (*on curve_fit's*) over the "
        "segments curve_fit itself handled, for a like-for-like comparison. Times include "
        f"packing the segments into a batch; the batch methods fit all {n_meth} segments in "
        f"one call, and (last column) the first {SMALL_CALL} per call (fixed per-call "
        "costs weigh more). *Bearing SD / RMSE*: RMS of the reported bearing SD over the "
        "RMSE, and RMS of error / SD, over the segments not diverged whose bearing SD is "
        "below `flat_bearing_sd_deg` (3 deg; above it `fit_segments` says `FLAT`: their "
        "share is *flat*); *range; kappa SD / RMSE* the same ratio for range and kappa "
        "(reported SDs that match the errors: near 1).",
        "",
        "| method | CPU us / segment | speed vs curve_fit | bearing RMSE (deg) | "
        "bearing RMSE on curve_fit's (deg) | range RMSE (mm) | kappa RMSE (us) | fail | "
        f"of which diverged | CPU us / segment, {SMALL_CALL} per call (speed vs curve_fit) "
        "| bearing SD / RMSE; RMS error/SD | range; kappa SD / RMSE | flat |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in meth:
        k = float(r["rmse_k"])
        lines.append(
            f"| {r['name']} | {float(r['us_per_seg']):.0f} | "
            f"{float(curve['us_per_seg']) / float(r['us_per_seg']):.1f}x | "
            f"{float(r['rmse_b']):.3f} | {float(r['rmse_b_cf']):.3f} | "
            f"{float(r['rmse_r_mm']):.3f} | "
            f"{'n/a' if math.isnan(k) else f'{k:.3f}'} | {100 * float(r['fail']):.1f} % | "
            f"{100 * float(r['diverged']):.1f} % | {_small_cell(r, curve)} | "
            f"{_calib_cell(r)} |")
    lines += [
        "",
        f"## 3. Batch throughput (`fit_batch`, {n_thr} segments, one core)",
        "",
        "Segments/s of the gauss tier with the default settings, `FitConfig.batch()`, "
        "`FitConfig.fast()` and `FitConfig.profile()` (echoes only), and of the waveform "
        "tier (default settings); a pre-packed batch.",
        "",
        "| pan step (deg) | echoes / segment | no-echo readings / segment | default | "
        "`batch()` | `fast()` | `profile()` | waveform tier |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in thr:
        lines.append(f"| {float(r['step']):g} | {float(r['echoes']):.1f} | "
                     f"{float(r['noecho']):.1f} | **{float(r['segs_s']):.0f}** | "
                     f"**{float(r['segs_s_batch']):.0f}** | {float(r['segs_s_fast']):.0f} | "
                     f"{float(r['segs_s_profile']):.0f} | "
                     f"{float(r['segs_s_waveform']):.0f} |")
    if kept_csv is not None:
        lines += ["", *kept_csv, "",
                  f"Sections 1-3 rerun on their own ({datetime.date.today().isoformat()}, "
                  f"`--skip-large-csv`, {'--quick' if q else 'full'}); section 4 above is "
                  "kept from its own run."]
    else:
        lines += large_csv_lines(csv, q)
    lines += [
        "",
        machine_line("seed 2003", f"{time.perf_counter() - t_start:.0f} s",
                     "CPU times of this process", SHARED, "absolute numbers are noisy, the "
                     "ratios (measured in the same run) less so", quick=q),
    ]
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    plot(acc, meth, out.with_suffix(".png"))
    print("\n".join(lines))
    return 0


DRIVE_S = (300.0, 1500.0)
"""Section 4's moving-ring logs (s driven): 40,000 readings, and 200,000 (as many as the
rotation scan: the fixed costs of a batch, the lockstep tails of its fits, weigh less in a
larger one)."""


def _drive_part(q: bool) -> dict[str, float]:
    """:func:`drive_csv` of each log of :data:`DRIVE_S` (``--quick``: one 30 s log), keys
    ``drive{i}_*``."""
    out: dict[str, float] = {}
    for i, dur in enumerate((30.0,) if q else DRIVE_S):
        print(f"drive CSV, {dur:.0f} s ...", file=sys.stderr)
        out.update({f"drive{i}_{k}": v for k, v in drive_csv(dur, 1 if q else 3).items()})
    return out


def _kept_large_csv(out: Path) -> list[str]:
    """Section 4 of the existing results file (its heading up to the machine line)."""
    text = out.read_text(encoding="utf-8") if out.exists() else ""
    if "## 4. " not in text or "\nMachine: " not in text:
        return ["## 4. `sonarloc fit` on a large scan CSV", "",
                "(not run: `--skip-large-csv` and no earlier results file)"]
    a = text.index("## 4. ")
    b = text.index("\nMachine: ", a)
    # without the notes of earlier sections-1-3 reruns (the new run adds its own)
    kept = [ln for ln in text[a:b].rstrip("\n").split("\n")
            if not ln.startswith("Sections 1-3 rerun on their own")]
    while len(kept) > 1 and kept[-1] == "" and kept[-2] == "":
        kept.pop()
    return kept


def _only_large_csv(out: Path, n_csv: int, repeats: int, q: bool) -> int:
    """Rerun section 4 and put it in place of the one in ``out`` (a note says so)."""
    t0 = time.perf_counter()
    csv = large_csv(n_csv, repeats, np.random.default_rng(2003))
    csv.update(_drive_part(q))
    sec = large_csv_lines(csv, q)[1:] + [
        "",
        f"Section 4 rerun on its own ({datetime.date.today().isoformat()}, "
        f"{'--quick' if q else 'full'}, {time.perf_counter() - t0:.0f} s; sections 1-3 and "
        "the machine line below are from the last full run). Other jobs were running on "
        "the 2 shared cores: the before/now ratios (same run, alternating) are the "
        "numbers to read.",
    ]
    text = out.read_text(encoding="utf-8")
    a = text.index("## 4. ")
    b = text.index("\nMachine: ", a)
    out.write_text(text[:a] + "\n".join(sec) + "\n" + text[b:], encoding="utf-8")
    print("\n".join(sec))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

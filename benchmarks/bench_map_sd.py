"""How honest are the ``sd_m`` of built maps? Normalized errors against the true map.

Simulates drives of ``maps/room.geojson`` (ring16, the map-building drive of
``bench_localize.py``), builds maps with ``sonarloc map build`` from odometry alone
(``--method odometry``), from the odometry corrected by SLAM (``--method slam``, the
default without poses) and from the poses of ``sonarloc localize`` (kuc, against the
true map), and compares every built feature with the nearest true one of its geometry:

* point (pole, rod, corner, edge, point): distance between centres (a pole's or rod's
  centre; a true point within ``--gate`` metres);
* wall: the larger distance of its two ends from the nearest true wall's line (within
  ``--gate`` of it and 10 deg of its direction).

Each error divided by the feature's ``sd_m`` is its normalized error ``z``. Reported per
build: features matched, NEES = mean ``z^2`` (points and walls apart), median and
largest ``z``, the share with ``z > 3``, and the median error and ``sd_m`` (mm). A point's
``sd_m`` is its larger position SD and its error is 2-D: an honest point has mean ``z^2``
between 1 and 2 (2 when isotropic); a wall's end error is 1-D (about 1 when honest).

The map frame is the log's ``init`` pose's, and the simulator's ``init`` record is the
true start pose plus noise of 5 cm / 2 deg SD: every build without a pose track carries
that error whole (a rotation of 2 deg moves a feature 5 m away by 17 cm), and its
``sd_m`` says so. The column "aligned" gives the median error after the best rigid
motion of the built map onto the true one (least squares over the matched points'
centres), the map's own shape error. CPU: seconds of the builds, per seed.

A SLAM build also writes each feature's SD relative to the map frame, ``sd_rel_m``
(the frame's error against the world, which all the features share, taken out): a
second table divides the aligned errors by it (NEES aligned; honest: points 1-2,
walls about 1).

``--localize-seed S``: a second drive (seed S) is localized (``sonarloc localize``,
kuc) against every built map, its init record in the true frame: position RMSE against
the simulator's truth and the mean pose NEES (x, y, yaw: 3 when honest). The Localizer
takes a feature's ``sd_rel_m`` as its map error where the map gives one, else its
``sd_m``: rows "``sd_m`` only" localize against the same map without ``sd_rel_m`` (as
before it was written).

``--sd-rel-scale F``: the built maps' ``sd_rel_m`` multiplied by F before they are
localized against (the SDs SLAM writes are conservative: F about 0.2 makes them honest).

Run: ``python benchmarks/bench_map_sd.py [--seeds 200 201] [--duration 174] [--quick]
[--localize-seed 202] [--sd-rel-scale 0.22]``
``--map-error-memory S``: localize with ``LocalizerConfig.map_error_memory_s = S``.

(writes ``benchmarks/results/map_sd.md``; a 60 s drive builds in ~20 s per seed and
pose source).
"""

from __future__ import annotations

import argparse
import copy
import io
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, machine_line  # noqa: E402
from sonarloc import se2  # noqa: E402
from sonarloc.io.logfile import LogWriter, TruthRecord, iter_log  # noqa: E402
from sonarloc.io.posescsv import PoseTrack  # noqa: E402
from sonarloc.localize.features import FeatureMap  # noqa: E402
from sonarloc.localize.localizer import LocalizerConfig  # noqa: E402
from sonarloc.localize.replay import replay_log  # noqa: E402
from sonarloc.maps import compare as maps_compare  # noqa: E402
from sonarloc.maps.build import BuiltFeature, build_from_log  # noqa: E402
from sonarloc.maps.geojson import Map, load_map, map_from_geojson  # noqa: E402
from sonarloc.world.rig import ring16  # noqa: E402
from sonarloc.world.simulate import simulate_records  # noqa: E402


def simulate(world: Map, seed: int, duration_s: float) -> str:
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(world, ring16(), duration_s=duration_s, seed=seed))
    return buf.getvalue()


def truth_track(text: str) -> PoseTrack:
    tr = [r for r in iter_log(io.StringIO(text)) if isinstance(r, TruthRecord)]
    n = len(tr)
    return PoseTrack(np.array([r.t_s for r in tr]), np.array([r.x_m for r in tr]),
                     np.array([r.y_m for r in tr]), np.radians([r.yaw_deg for r in tr]),
                     np.zeros((n, 3, 3)))


def localized_track(text: str, world: Map) -> PoseTrack:
    rows: list[tuple[float, np.ndarray, np.ndarray]] = []
    replay_log(io.StringIO(text), FeatureMap.from_map(world),
               on_estimate=lambda r, e: rows.append((r.t_s, e.state.mean, e.state.cov)))
    return PoseTrack(np.array([r[0] for r in rows]), np.array([r[1][0] for r in rows]),
                     np.array([r[1][1] for r in rows]), np.array([r[1][2] for r in rows]),
                     np.array([r[2] for r in rows]))


def by_kind(pairs: list[tuple[BuiltFeature, float]], sd: str = "sd_m"
            ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """(error, SD) of the matched built points and of the walls
    (:func:`sonarloc.maps.compare.feature_errors`' pairs), the SD their attribute ``sd``
    (``sd_m`` or ``sd_rel_m``); features without that SD (NaN) left out."""
    kept = [(e, float(getattr(f, sd)), f.kind) for f, e in pairs
            if np.isfinite(getattr(f, sd))]
    return ([(e, v) for e, v, k in kept if k != "wall"],
            [(e, v) for e, v, k in kept if k == "wall"])


def rel_row(label: str, errs: list[tuple[float, float]]) -> str:
    if not errs:
        return f"| {label} | 0 | - | - | - | - | - | - |"
    e = np.array([x[0] for x in errs])
    sd = np.array([x[1] for x in errs])
    z = e / np.maximum(sd, 1e-12)
    return (f"| {label} | {len(e)} | {np.mean(z**2):.2f} | {np.median(z):.2f} | "
            f"{np.max(z):.2f} | {100 * np.mean(z > 3):.0f} % | {1000 * np.median(e):.1f} | "
            f"{1000 * np.median(sd):.1f} |")


def without_rel(built: dict[str, Any]) -> dict[str, Any]:
    """The GeoJSON map without its ``sd_rel_m`` properties (what the Localizer used
    before they were written: ``sd_m``)."""
    out = copy.deepcopy(built)
    for f in out["features"]:
        f["properties"].pop("sd_rel_m", None)
    return out


def scaled_rel(built: dict[str, Any], factor: float) -> dict[str, Any]:
    """The GeoJSON map with its ``sd_rel_m`` properties multiplied by ``factor``."""
    if factor == 1.0:
        return built
    out = copy.deepcopy(built)
    for f in out["features"]:
        if "sd_rel_m" in f["properties"]:
            f["properties"]["sd_rel_m"] *= factor
    return out


def row(label: str, errs: list[tuple[float, float]], errs_aligned: list[tuple[float, float]],
        cpu_s: float) -> str:
    if not errs:
        return f"| {label} | 0 | - | - | - | - | - | - | - | - |"
    e = np.array([x[0] for x in errs])
    sd = np.array([x[1] for x in errs])
    z = e / np.maximum(sd, 1e-12)
    ea = np.array([x[0] for x in errs_aligned]) if errs_aligned else np.array([np.nan])
    return (f"| {label} | {len(e)} | {np.mean(z**2):.2f} | {np.median(z):.2f} | "
            f"{np.max(z):.2f} | {100 * np.mean(z > 3):.0f} % | {1000 * np.median(e):.1f} | "
            f"{1000 * np.median(ea):.1f} | {1000 * np.median(sd):.1f} | {cpu_s:.1f} |")


#: ``sd_rel_m`` times this is about honest against the aligned errors (NEES 1-2); the
#: localize table also shows maps scaled so, with and without ``map_error_memory_s``
HONEST_SCALE = 0.22
#: the ``map_error_memory_s`` [s] of those rows
HONEST_MEMORY_S = 10.0

#: the "steady" columns leave out the localizer's first minute (its init record is in
#: the true frame: the estimate moves into the built map's frame, centimetres away)
STEADY_AFTER_S = 60.0


def localize_against(built: dict[str, Any], text: str, motion: np.ndarray,
                     config: LocalizerConfig | None = None
                     ) -> tuple[float, float, float, float, float, float]:
    """Position RMSE [m] and mean pose NEES (x, y, yaw) of a drive localized (kuc)
    against the built map (GeoJSON object); then the same with the estimates moved by
    ``motion`` (the map's alignment onto the true one: errors relative to the map),
    over the whole drive and after :data:`STEADY_AFTER_S`."""
    truth = {r.t_s: np.array([r.x_m, r.y_m, np.radians(r.yaw_deg)])
             for r in iter_log(io.StringIO(text)) if isinstance(r, TruthRecord)}
    rows: list[tuple[float, np.ndarray, np.ndarray]] = []
    replay_log(io.StringIO(text), FeatureMap.from_map(map_from_geojson(built)), config=config,
               on_estimate=lambda r, e: rows.append((r.t_s, e.state.mean, e.state.cov)))
    err = np.array([m - truth[t] for t, m, _ in rows if t in truth])
    err[:, 2] = se2.wrap_angle(err[:, 2])
    cov = np.array([c for t, _, c in rows if t in truth])
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    est = np.array([m for t, m, _ in rows if t in truth])
    tru = np.array([truth[t] for t, _, _ in rows if t in truth])
    err_a = se2.compose(motion, est) - tru
    err_a[:, 2] = se2.wrap_angle(err_a[:, 2])
    j = se2.compose_jacobians(motion, est)[1]
    cov_a = j @ cov @ np.swapaxes(j, 1, 2)
    nees_a = np.einsum("ni,ni->n", err_a, np.linalg.solve(cov_a, err_a[..., None])[..., 0])
    t = np.array([t for t, _, _ in rows if t in truth])
    late = t >= t[0] + STEADY_AFTER_S
    return (float(np.sqrt(np.mean(np.sum(err[:, :2] ** 2, axis=1)))), float(np.mean(nees)),
            float(np.sqrt(np.mean(np.sum(err_a[:, :2] ** 2, axis=1)))),
            float(np.mean(nees_a)),
            float(np.sqrt(np.mean(np.sum(err_a[late, :2] ** 2, axis=1)))) if late.any()
            else math.nan, float(np.mean(nees_a[late])) if late.any() else math.nan)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one 30 s drive (smoke run)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[200, 201])
    ap.add_argument("--duration", type=float, default=174.0,
                    help="drive length [s] (default 174: three laps)")
    ap.add_argument("--gate", type=float, default=1.5,
                    help="largest error [m] of a built feature matched to a true one "
                         "(odometry-only maps are off by decimetres: a smaller gate "
                         "leaves out their worst features)")
    ap.add_argument("--sources", nargs="+", default=["odometry", "slam", "localize"],
                    choices=["odometry", "slam", "localize", "truth"])
    ap.add_argument("--localize-seed", type=int, default=None, metavar="S",
                    help="localize a drive of seed S against every built map")
    ap.add_argument("--sd-rel-scale", type=float, default=1.0, metavar="F",
                    help="multiply the built maps' sd_rel_m by F before localizing")
    ap.add_argument("--map-error-memory", type=float, default=0.0, metavar="S",
                    help="LocalizerConfig.map_error_memory_s of the localized drives")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "map_sd.md"))
    args = ap.parse_args(argv)
    if args.quick:
        args.seeds, args.duration = args.seeds[:1], 30.0
    world = load_map(ROOT / "maps" / "room.geojson")
    cfg = LocalizerConfig(map_error_memory_s=args.map_error_memory)
    acc: dict[str, tuple[list[tuple[float, float]], list[tuple[float, float]]]] = {
        s: ([], []) for s in args.sources}
    acc_al: dict[str, tuple[list[tuple[float, float]], list[tuple[float, float]]]] = {
        s: ([], []) for s in args.sources}
    cpu: dict[str, float] = {s: 0.0 for s in args.sources}
    loc: dict[str, list[tuple[int, float, float, float, float, float, float]]] = {
        s: [] for s in args.sources}
    # rows of maps with sd_rel_m localized otherwise: (source, label) -> rows
    loc_var: dict[tuple[str, str], list[tuple[int, float, float, float, float, float,
                                              float]]] = {}
    honest = f"`sd_rel_m` x{HONEST_SCALE:g}"
    variants = (("`sd_m` only", without_rel, cfg), (honest, None, cfg),
                (f"{honest}, `map_error_memory_s` {HONEST_MEMORY_S:g} s", None,
                 LocalizerConfig(map_error_memory_s=HONEST_MEMORY_S)))
    acc_rel: dict[str, tuple[list[tuple[float, float]], list[tuple[float, float]]]] = {
        s: ([], []) for s in args.sources}
    second = simulate(world, args.localize_seed, args.duration) \
        if args.localize_seed is not None else None
    notes: list[str] = []
    for seed in args.seeds:
        text = simulate(world, seed, args.duration)
        for src in args.sources:
            poses = None if src in ("odometry", "slam") else truth_track(text) \
                if src == "truth" else localized_track(text, world)
            t0 = time.process_time()
            res = build_from_log(io.StringIO(text), poses,
                                 method=src if src in ("odometry", "slam") else None)
            cpu[src] += (time.process_time() - t0) / len(args.seeds)
            if res.slam is not None:
                notes.append(f"seed {seed}, {src}: {res.slam.summary()}")
            feats = res.builder.features()
            p, w = by_kind(maps_compare.feature_errors(feats, world, args.gate))
            acc[src][0].extend(p)
            acc[src][1].extend(w)
            motion = maps_compare.rigid_alignment(feats, world, args.gate)
            aligned = maps_compare.feature_errors(maps_compare.moved(feats, motion), world,
                                                  args.gate)
            p, w = by_kind(aligned)
            acc_al[src][0].extend(p)
            acc_al[src][1].extend(w)
            p, w = by_kind(aligned, "sd_rel_m")
            acc_rel[src][0].extend(p)
            acc_rel[src][1].extend(w)
            if second is not None:
                built = scaled_rel(res.geojson(), args.sd_rel_scale)
                loc[src].append((seed, *localize_against(built, second, motion, cfg)))
                if any("sd_rel_m" in f["properties"] for f in built["features"]):
                    for label, change, conf in variants:
                        other = change(built) if change is not None else \
                            scaled_rel(res.geojson(), HONEST_SCALE)
                        loc_var.setdefault((src, label), []).append(
                            (seed, *localize_against(other, second, motion, conf)))
    lines = [
        "# Built maps: is their `sd_m` honest?",
        "",
        f"Room, ring16, {args.duration:.0f} s drives, seeds "
        f"{' '.join(map(str, args.seeds))}; each built feature against the nearest true "
        f"one within {args.gate} m (`benchmarks/bench_map_sd.py`). z = error / `sd_m`: an "
        "honest point (2-D error, `sd_m` its larger SD) has NEES (mean z^2) between 1 and 2, "
        "an honest wall end about 1.",
        "",
        "| build | n | NEES (mean z^2) | median z | max z | z > 3 | median error (mm) | "
        "aligned (mm) | median sd_m (mm) | CPU (s) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for src, (p, w) in acc.items():
        pa, wa = acc_al[src]
        lines += [row(f"{src}: points", p, pa, cpu[src]), row(f"{src}: walls", w, wa, cpu[src])]
    if any(p or w for p, w in acc_rel.values()):
        lines += ["", "The SD relative to the map frame, `sd_rel_m` (written by SLAM builds: "
                  "the optimized poses' covariance less the rigid motion of the frame that "
                  "best fits the landmarks), against the errors after the map's best rigid "
                  "alignment onto the true one: z = aligned error / `sd_rel_m`.", "",
                  "| build | n | NEES aligned | median z | max z | z > 3 | median aligned "
                  "error (mm) | median sd_rel_m (mm) |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for src, (p, w) in acc_rel.items():
            if p or w:
                lines += [rel_row(f"{src}: points", p), rel_row(f"{src}: walls", w)]
    if second is not None:
        lines += ["", f"A second drive (seed {args.localize_seed}, {args.duration:.0f} s) "
                  "localized (kuc) against each built map: position RMSE against the truth, "
                  "mean pose NEES (x, y, yaw; 3 when honest); then the same with the "
                  "estimates moved by the map's best rigid alignment onto the true map "
                  "(errors relative to the map: its frame's error, from the init prior, "
                  "taken out). The Localizer uses a feature's `sd_rel_m` where the map has "
                  "one" + (f" (here multiplied by {args.sd_rel_scale:g})"
                           if args.sd_rel_scale != 1.0 else "") +
                  (f", `map_error_memory_s` {args.map_error_memory:g} s"
                   if args.map_error_memory else "") +
                  ", else its `sd_m`; rows \"`sd_m` only\": the same map without "
                  f"`sd_rel_m`; rows \"{honest}\": its `sd_rel_m` scaled to about honest "
                  "(the table above), with and without `map_error_memory_s` (a feature's map "
                  "error as one constant its readings share). Steady: from "
                  f"{STEADY_AFTER_S:.0f} s on (the localizer starts "
                  "in the true frame, centimetres from the built map's).", "",
                  "| map | built from seed | RMSE (mm) | NEES | RMSE aligned (mm) | "
                  "NEES aligned | steady: RMSE aligned (mm) | NEES aligned |",
                  "|---|---:|---:|---:|---:|---:|---:|---:|"]
        for src, rows_ in loc.items():
            for label, rr in ((src, rows_), *((f"{src}, {v}", loc_var.get((src, v), []))
                                              for v, _, _ in variants)):
                lines += [f"| {label} | {s_} | {1000 * r_:.1f} | {n_:.1f} | "
                          f"{1000 * ra:.1f} | {na:.1f} | {1000 * rs:.1f} | {ns:.1f} |"
                          for s_, r_, n_, ra, na, rs, ns in rr]
    if notes:
        lines += [""] + [f"* {n}" for n in notes]
    lines += [
        "",
        machine_line(f"seeds {' '.join(map(str, args.seeds))}", f"{args.duration:g} s drives",
                     SHARED + " (CPU times are indicative)", quick=args.quick),
    ]
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

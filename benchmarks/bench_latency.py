"""Latency of one Localizer call: fits in the call against fits in a background worker.

A robot's navigation stack calls the online Localizer once per sonar reading and per
odometry record. Without workers, the call that closes a batch of segments fits them
and fuses them before it returns; with ``LocalizerConfig.fit_workers`` the fit runs in
a worker thread or process and the finished landmarks are fused over the next calls
(``fuse_per_call``), each at its own reference time.

Each run feeds one lap of the room's route (ring of 16, maps/room.geojson, 57.8 s
simulated; the log simulated once per seed) to a :class:`~sonarloc.api.LocalizerNode`
in real time (each record handed over when the wall clock reaches its log time, as a
robot's driver would; ``--fast``: as fast as possible) and measures the calling
thread's CPU time of every call (``time.thread_time``: the worker's share of the cores
does not count; the wall time of the call is reported too, since a thread worker holds
the interpreter lock while it runs Python code). Rows: no workers, 1 thread worker,
1 process worker. Medians over seeds 0-2.

Run: ``python benchmarks/bench_latency.py [--quick] [--fast]``; writes
benchmarks/results/latency.md.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, load_average, machine_line  # noqa: E402
from sonarloc.api import LocalizerNode  # noqa: E402
from sonarloc.io.logfile import TruthRecord  # noqa: E402
from sonarloc.localize.features import FeatureMap  # noqa: E402
from sonarloc.localize.localizer import LocalizerConfig  # noqa: E402
from sonarloc.maps.geojson import load_map  # noqa: E402
from sonarloc.report.drive import WARMUP_S  # noqa: E402
from sonarloc.report.metrics import track_error  # noqa: E402
from sonarloc.world.rig import rig_by_name  # noqa: E402
from sonarloc.world.robot import Route  # noqa: E402
from sonarloc.world.simulate import default_duration_s, simulate_records  # noqa: E402

ROWS: list[tuple[str, int, str]] = [  # (label, fit_workers, fit_executor)
    ("in the call (fit_workers=0)", 0, "thread"),
    ("1 thread worker", 1, "thread"),
    ("1 process worker", 1, "process"),
]


@dataclass
class Run:
    p50_ms: float
    p99_ms: float
    p999_ms: float
    max_ms: float
    wall_p99_ms: float
    wall_max_ms: float
    total_cpu_s: float
    steady_mm: float
    fused: int
    rejected: int
    fit_waits: int


def feed(fmap: FeatureMap, records: list[Any], truth: np.ndarray, workers: int,
         executor: str, real_time: bool) -> Run:
    """One run: every record to a fresh node, the caller's CPU and wall time per call."""
    config = LocalizerConfig(fit_workers=workers, fit_executor=executor)  # type: ignore[arg-type]
    cpu: list[float] = []
    wall: list[float] = []
    est_rows = []
    with LocalizerNode(fmap, config=config) as node:
        if workers:
            time.sleep(1.0)   # the pool warms up as a robot's node would before it drives
        t_log0 = records[0].t_s
        t_wall0 = time.perf_counter()
        for rec in records:
            if real_time:
                lag = t_wall0 + (rec.t_s - t_log0) - time.perf_counter()
                if lag > 0:
                    time.sleep(lag)
            w0, c0 = time.perf_counter(), time.thread_time()
            est = node.feed(rec)
            cpu.append(time.thread_time() - c0)
            wall.append(time.perf_counter() - w0)
            if est is not None:
                est_rows.append((est.t_s, est.x_m, est.y_m, est.yaw_rad))
        w0, c0 = time.perf_counter(), time.thread_time()
        node.finish()
        cpu.append(time.thread_time() - c0)
        wall.append(time.perf_counter() - w0)
        st = node.stats
    track = np.array(est_rows, dtype=float)
    track[:, 3] = np.unwrap(track[:, 3])
    steady = track_error(track, truth, t_from_s=float(truth[0, 0]) + WARMUP_S)
    c = np.array(cpu) * 1e3
    w = np.array(wall) * 1e3
    skipped = st.skipped["no_motion_since_fused"]
    return Run(float(np.percentile(c, 50)), float(np.percentile(c, 99)),
               float(np.percentile(c, 99.9)), float(c.max()), float(np.percentile(w, 99)),
               float(w.max()), float(c.sum()) / 1e3, steady.rmse_m * 1e3, st.accepted,
               st.observations - st.accepted - skipped, st.fit_waits)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 seed, 20 s drives")
    parser.add_argument("--fast", action="store_true",
                        help="feed the records as fast as possible, not in real time")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(list(argv) if argv is not None else None)
    seeds = [0] if args.quick else [0, 1, 2]
    world = load_map(ROOT / "maps" / "room.geojson")
    rig = rig_by_name("ring16")
    assert world.route is not None
    duration = 20.0 if args.quick else default_duration_s(rig, True, Route(world.route))
    fmap = FeatureMap.from_map(world)
    load = load_average()

    runs: dict[str, list[Run]] = {label: [] for label, _, _ in ROWS}
    for seed in seeds:
        recs = list(simulate_records(world, rig, duration_s=duration, seed=seed))
        truth = np.array([(r.t_s, r.x_m, r.y_m, math.radians(r.yaw_deg)) for r in recs
                          if isinstance(r, TruthRecord)], dtype=float)
        truth[:, 3] = np.unwrap(truth[:, 3])
        fed = [r for r in recs if not isinstance(r, TruthRecord)]
        for label, workers, executor in ROWS:
            r = feed(fmap, fed, truth, workers, executor, not args.fast)
            runs[label].append(r)
            print(f"seed {seed} {label:28}: cpu p50/p99/p99.9/max {r.p50_ms:.2f}/"
                  f"{r.p99_ms:.1f}/{r.p999_ms:.1f}/{r.max_ms:.1f} ms, wall p99/max "
                  f"{r.wall_p99_ms:.1f}/{r.wall_max_ms:.1f} ms, steady {r.steady_mm:.2f} mm, "
                  f"fused {r.fused}, rejected {r.rejected}, waits {r.fit_waits}, total "
                  f"{r.total_cpu_s:.1f} s", file=sys.stderr)

    lines = []
    for label, _, _ in ROWS:
        rs = runs[label]

        def med(name: str, rs: list[Run] = rs) -> float:
            return statistics.median(getattr(x, name) for x in rs)

        lines.append(
            f"| {label} | {med('p50_ms'):.2f} | {med('p99_ms'):.1f} | {med('p999_ms'):.1f} | "
            f"{med('max_ms'):.1f} | {med('wall_p99_ms'):.1f} | {med('wall_max_ms'):.1f} | "
            f"{med('steady_mm'):.2f} | {med('fused'):.0f} | {med('rejected'):.0f} | "
            f"{med('fit_waits'):.0f} | {med('total_cpu_s'):.1f} |")
    pace = "as fast as possible" if args.fast else "in real time"
    text = "\n".join([
        "# Latency of one Localizer call: fits in the call or in a background worker",
        "",
        "One lap of the room's route (maps/room.geojson, ring of 16, "
        + (f"{duration:.0f} s" if args.quick else f"{duration:.1f} s") + " simulated) "
        f"fed record by record to a `LocalizerNode` {pace}. *CPU per call*: the calling "
        "thread's CPU time (`time.thread_time`) of one call (a reading, an odometry "
        "record, the final `finish()`): 50th, 99th, 99.9th percentile and worst call of "
        "each run; *wall*: the same call's wall time (a thread worker shares the "
        "interpreter lock, and with it the caller's wall clock). *after warm-up*: pose "
        "RMSE of the estimates reported online, from 5 s on. *fused / rejected*: "
        "observations (segments) fused and rejected by the map. *waits*: calls that "
        "waited for a fit older than `fit_max_lag_s` (2 s of log time). *total CPU*: the "
        "calling thread's CPU over the run (the worker's is not in it). Medians over "
        f"seeds {seeds}; `LocalizerConfig` defaults otherwise (`fuse_per_call=1`); a "
        "node with a worker is made 1 s before its first record (the worker warms up).",
        "",
        "| fits | CPU p50 (ms) | CPU p99 (ms) | CPU p99.9 (ms) | CPU max (ms) | "
        "wall p99 (ms) | wall max (ms) | after warm-up (mm) | fused | rejected | waits | "
        "total CPU (s) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        *lines,
        "",
        machine_line(f"seeds {seeds}", f"records fed {pace}",
                     SHARED, quick=args.quick, load=load),
        "",
    ])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "latency.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

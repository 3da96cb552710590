"""End to end: `sonarloc drive` speed against error, by rig, observation model and wire.

Each row is a full drive of the room's route (one lap, 57.8 s simulated): simulator ->
simulated module on a python-can virtual bus (or a pseudo-terminal) -> the robot's
driver -> Localizer -> report. Rows differ only in the rig, the Localizer's observation
model (``kuc``: fitted landmarks; ``conventional``: each reading a range along the beam
axis with a beam-wide bearing SD; ``odometry``: readings ignored) and the wire. Medians
over seeds; *x odometry* is the odometry-only pose RMSE over the row's, seed by seed.
Compute per reading is the Localizer's time (fit + filter) per sonar reading, and the
worst calls its CPU time for one record (99th percentile, maximum); the
real-time factor is simulated time over the wall time of the whole stream (simulator,
wire, decoder and Localizer share the machine's cores).

Run: ``python benchmarks/bench_drive.py [--quick]``; writes benchmarks/results/drive.md.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks._machine import SHARED, load_average, machine_line  # noqa: E402
from sonarloc.report.pipeline import DriveConfig, run_drive  # noqa: E402

ROWS: list[tuple[str, str, str]] = [  # (rig, method, device)
    ("ring16", "kuc", "can"),
    ("ring16", "conventional", "can"),
    ("ring16", "odometry", "can"),
    ("ring16", "kuc", "serial"),
    ("pan", "kuc", "can"),
    ("pan", "conventional", "can"),
]


def _fmt(v: float, nd: int = 1) -> str:
    return f"{v:.{nd}f}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 seed, 20 s drives")
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results")
    args = parser.parse_args(list(argv) if argv is not None else None)
    seeds = [0] if args.quick else [0, 1, 2, 3, 4]
    duration = 20.0 if args.quick else None
    load = load_average()

    lines = []
    for rig, method, device in ROWS:
        reps = []
        for seed in seeds:
            r = run_drive(DriveConfig(rig=rig, method=method, device=device, seed=seed,
                                      duration_s=duration)).report
            reps.append(r)
            print(f"{rig:6} {method:12} {device:6} seed {seed}: pose {100 * r.pose_rmse_m:.1f} "
                  f"cm, odometry {100 * r.odom_pose_rmse_m:.1f} cm, "
                  f"{r.compute_per_reading_us:.0f} us/reading, {r.realtime_factor:.1f}x",
                  file=sys.stderr)

        def med(name: str, rs: list = reps) -> float:  # type: ignore[type-arg]
            return statistics.median(getattr(x, name) for x in rs)

        gain = statistics.median(x.odom_pose_rmse_m / x.pose_rmse_m for x in reps)
        lines.append(
            f"| {rig} | {method} | {device} | {_fmt(100 * med('pose_rmse_m'))} | "
            f"{_fmt(med('yaw_rmse_deg'), 2)} | {_fmt(1000 * med('steady_pose_rmse_m'))} | "
            f"{_fmt(med('steady_yaw_rmse_deg'), 2)} | {_fmt(100 * med('pose_max_m'))} | "
            f"{_fmt(gain)}x | {_fmt(med('landmarks_fitted'), 0)} | "
            f"{_fmt(med('landmarks_matched'), 0)} | "
            f"{_fmt(med('compute_per_reading_us'), 0)} | {_fmt(med('call_p99_ms'))} | "
            f"{_fmt(med('call_max_ms'))} | {_fmt(med('realtime_factor'))}x |")
    text = "\n".join([
        "# End to end: `sonarloc drive` speed against error",
        "",
        "One lap of the room's route (maps/room.geojson, "
        + ("20 s" if args.quick else "57.8 s") + " simulated) per run, through the device "
        "protocol: simulator -> simulated module on a python-can virtual bus (`can`) or a "
        "pseudo-terminal (`serial`) -> driver -> Localizer. Medians over seeds "
        f"{seeds}. *x odometry*: odometry-only pose RMSE (dead reckoning from the same "
        "prior) over the row's; *after warm-up*: from 5 s on (the prior is off by ~5 cm). "
        "*us/reading*: Localizer time (segmenting, fitting, EKF) "
        "per sonar reading (wall time). *call p99 / max*: the Localizer's CPU time for one "
        "record (the calling thread's time, so the simulator's share of the cores does not "
        "count), 99th percentile and worst call of each run, medians over the seeds: what "
        "a control loop calling it must allow for. *real time*: simulated seconds per wall "
        "second of the whole stream, simulator included (it shares the cores).",
        "",
        "| rig | method | wire | pose RMSE (cm) | yaw RMSE (deg) | after warm-up (mm) | "
        "yaw after warm-up (deg) | max error (cm) | x odometry | segments | "
        "observations fused | us/reading | call p99 (ms) | call max (ms) | real time |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
        *lines,
        "",
        machine_line(f"seeds {seeds}", SHARED,
                     quick=args.quick, load=load),
        "",
    ])
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "drive.md").write_text(text, encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

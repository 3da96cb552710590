"""The main job: a simulated drive, end to end through the device protocol.

A robot with a ring of 16 sonar transducers drives the route of a map (default: the
room in maps/room.geojson). A simulated sonar module streams the readings and the wheel
odometry over a CAN bus (python-can virtual) or a pseudo-terminal, in the module
protocol (docs/PROTOCOL.md); the host reads them with the same driver a robot uses,
fits landmarks to the TOF curves online (Kuc's forward model) and localizes the robot
with an EKF against the map. Prints a short report (pose and yaw RMSE against truth and
against odometry only, landmarks, compute per reading, real-time factor) and writes a
PNG (map, paths, fitted landmarks with uncertainty, TOF curves with their fits).
"""

from __future__ import annotations

import argparse
import json
import math
import time

from sonarloc.commands._args import accept_negative_values, refuse_overwrite

# Values such as "-180:180:3" start with "-": let argparse take them as values.

def _positive_number(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return v


def _positive(text: str) -> float:
    return _positive_number(text, "a number of seconds")


def _rate(text: str) -> float:
    return _positive_number(text, "a multiple of real time")


def _integer(text: str, what: str, lo: int, hi: int | None = None) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if v < lo or (hi is not None and v > hi):
        raise argparse.ArgumentTypeError(
            f"must be non-negative, got {text!r}" if hi is None
            else f"must be {lo} to {hi}, got {text!r}")
    return v


def _seed(text: str) -> int:
    return _integer(text, "a non-negative integer", 0)


def _workers(text: str) -> int:
    return _integer(text, "a number of workers", 0, 64)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    accept_negative_values(parser)
    parser.add_argument("--map", default="room", metavar="MAP",
                        help="map GeoJSON with a route, or a name in maps/ (default room)")
    parser.add_argument("--rig", default="ring16", metavar="ring16|pan|RIG.json",
                        help="sonar rig (default ring16)")
    parser.add_argument("--pan", metavar="START:STOP:STEP",
                        help="pan schedule of the pan rig in degrees (default -180:180:3)")
    parser.add_argument("--device", default="can", choices=("can", "serial"),
                        help="wire between module and host: CAN virtual bus or a "
                             "pseudo-terminal (default can)")
    parser.add_argument("--seed", type=_seed, default=0, help="random seed (default 0)")
    parser.add_argument("--duration", type=_positive, metavar="S",
                        help="simulated seconds (default: one lap of the route)")
    parser.add_argument("--tier", default="auto", metavar="gauss|piston|waveform|auto",
                        help="sonar model tier of the simulator (default auto)")
    parser.add_argument("--method", default="kuc", choices=("kuc", "conventional", "odometry"),
                        help="observation model of the localizer (default kuc)")
    parser.add_argument("--plot", default="out/drive.png", metavar="PNG",
                        help="figure to write (default out/drive.png)")
    parser.add_argument("--no-plot", action="store_true", help="do not draw the figure")
    parser.add_argument("--poses", metavar="POSES.csv",
                        help="also write the estimated poses (FORMATS.md section 5)")
    parser.add_argument("--json", action="store_true",
                        help="print the report as one JSON object")
    parser.add_argument("--fit-workers", type=_workers, default=0, metavar="N",
                        help="fit landmarks in N background workers, off the calling "
                             "thread (default 0: in the call)")
    parser.add_argument("--fit-executor", default="thread", choices=("thread", "process"),
                        help="background fit workers: threads or processes (default thread)")
    parser.add_argument("--rate", type=_rate, metavar="R",
                        help="pace the simulated module at R times real time (1: as a live "
                             "robot; default: as fast as the host reads, several times real "
                             "time, which background fit workers fall behind)")


def run(args: argparse.Namespace) -> int:
    from sonarloc.report.drive import drive_figure
    from sonarloc.report.pipeline import DriveConfig, run_drive
    from sonarloc.report.progress import Progress

    refuse_overwrite({"--poses": args.poses, "--plot": None if args.no_plot else args.plot},
                     {"--map": args.map, "--rig": args.rig})
    t0 = time.perf_counter()
    from sonarloc.world.rig import parse_pan_schedule

    pan = parse_pan_schedule(args.pan) if args.pan else None
    config = DriveConfig(map=args.map, rig=args.rig, device=args.device, seed=args.seed,
                         duration_s=args.duration, tier=args.tier, method=args.method,
                         pan_deg=pan, fit_workers=args.fit_workers,
                         fit_executor=args.fit_executor, rate=args.rate)
    bar = Progress(1.0, "sonarloc drive", unit="s")
    try:
        def progress(t: float, total: float) -> None:
            bar.total = total
            bar.update(t)

        result = run_drive(config, progress)
    finally:
        bar.close()
    report = result.report
    if args.poses:
        from sonarloc.io.posescsv import PoseTrack, write_poses_csv

        e = result.estimate
        write_poses_csv(args.poses, PoseTrack(e[:, 0], e[:, 1], e[:, 2], e[:, 3],
                                              result.covariance))
    if not args.no_plot:
        from sonarloc.report.plots import matplotlib_available

        if matplotlib_available():
            path = drive_figure(args.plot, map_source=result.map_path,
                                tracks={"truth": result.truth, "odometry": result.odometry,
                                        "estimate": result.estimate},
                                landmarks=result.landmarks, segments=result.segments,
                                report=report)
            report.plot = str(path)
        else:
            report.notes.append("no plot: matplotlib is not installed "
                                "(pip install 'sonarloc[plot]')")
    report.wall_time_s = time.perf_counter() - t0
    if args.json:
        print(json.dumps(report.to_json()))
    else:
        print(report.text())
    return 0 if report.readings > 0 else 1


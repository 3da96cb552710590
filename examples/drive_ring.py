"""Drive a robot with a ring of 16 sonars around the room and localize it (the library way).

The same run as `sonarloc drive`: simulator -> simulated sonar module on a CAN bus
(python-can virtual) or a pseudo-terminal -> the robot's driver -> online fitting ->
EKF. Prints the report and writes the figure.

    python examples/drive_ring.py [--duration 30] [--device serial] [--out out/ring.png]
"""

from __future__ import annotations

import argparse

from sonarloc.report.drive import drive_figure
from sonarloc.report.pipeline import DriveConfig, run_drive
from sonarloc.report.plots import matplotlib_available


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=30.0,
                        help="simulated seconds (default %(default)s)")
    parser.add_argument("--device", choices=("can", "serial"), default="can",
                        help="wire between module and host (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default %(default)s)")
    parser.add_argument("--out", default="out/drive_ring.png",
                        help="figure, PNG (default %(default)s)")
    args = parser.parse_args(argv)

    result = run_drive(DriveConfig(map="room", rig="ring16", device=args.device,
                                   seed=args.seed, duration_s=args.duration))
    if matplotlib_available():
        result.report.plot = str(drive_figure(
            args.out, map_source=result.map_path,
            tracks={"truth": result.truth, "odometry": result.odometry,
                    "estimate": result.estimate},
            landmarks=result.landmarks, segments=result.segments, report=result.report))
    print(result.report.text())
    fused = sum(1 for _, f in result.landmarks if f)
    print(f"{len(result.estimate)} poses; {fused} of {len(result.landmarks)} landmarks fused")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

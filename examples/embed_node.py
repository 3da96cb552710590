"""Embed sonarloc in a robot node: feed readings and odometry, read pose and landmarks.

A stand-in for a ROS node's callbacks: the readings and wheel odometry come from the
simulator here (on a robot: your sonar driver and wheel encoders), one message at a
time. Every second the node's estimate is printed next to the simulator's truth.

    python examples/embed_node.py [--duration 20] [--seed 1] [--fit-workers 0]

On a robot, fit in a background worker (``--fit-workers 1``): a callback that closes
a segment then returns in a few ms instead of tens (benchmarks/results/latency.md).
Here the simulator runs faster than real time and the worker lags behind it, so the
default fits in the callback.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from sonarloc.api import LocalizerConfig, LocalizerNode
from sonarloc.io.logfile import InitRecord, OdomRecord, RigRecord, TofRecord, TruthRecord
from sonarloc.maps.geojson import Map, load_map
from sonarloc.world.rig import Rig, ring16
from sonarloc.world.simulate import simulate_records

ROOM = Path(__file__).resolve().parents[1] / "maps" / "room.geojson"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=20.0,
                        help="simulated seconds (default %(default)s)")
    parser.add_argument("--seed", type=int, default=1, help="random seed (default %(default)s)")
    parser.add_argument("--fit-workers", type=int, default=0, choices=(0, 1, 2),
                        help="background fit workers (default %(default)s: fit in the call)")
    args = parser.parse_args(argv)

    world = load_map(ROOM)
    rig = ring16()
    # 1. the node: map + transducer mounts (id, x_m, y_m, yaw_deg in base_link); `with`
    #    stops its fit workers at the end
    with LocalizerNode.from_map_file(
            ROOM, sensors=[(s.id, s.x_m, s.y_m, s.yaw_deg) for s in rig.sensors],
            config=LocalizerConfig(fit_workers=args.fit_workers)) as node:
        node.warm_up()  # the fitter's tables, built now rather than in the first callback
        run(node, world, rig, args.duration, args.seed)
    return 0


def run(node: LocalizerNode, world: Map, rig: Rig, duration_s: float, seed: int) -> None:
    """Feed the simulated robot's messages to the node, print what it says."""
    truth = (0.0, 0.0, 0.0)
    next_print = 0.0
    for rec in simulate_records(world, rig, duration_s=duration_s, seed=seed):
        if isinstance(rec, RigRecord):
            node.set_rig(rec.sensors, rec.speed_of_sound_mps)  # the module says c
        elif isinstance(rec, InitRecord):
            # 2. a prior (an operator's "2D pose estimate", or a global localizer)
            node.set_pose(rec.x_m, rec.y_m, math.radians(rec.yaw_deg), sd_xy_m=rec.sd_xy_m,
                          sd_yaw_rad=math.radians(rec.sd_yaw_deg), t_s=rec.t_s)
        elif isinstance(rec, TofRecord):
            # 3. every sonar reading: time, transducer id, TOF in us (None: no echo)
            node.reading(rec.t_s, rec.sensor, rec.tof_us)
        elif isinstance(rec, OdomRecord):
            # 4. wheel odometry: base_link in odom; returns the new estimate
            node.odometry(rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg))
        elif isinstance(rec, TruthRecord):  # only the simulator knows this
            truth = (rec.x_m, rec.y_m, rec.yaw_deg)
            if rec.t_s >= next_print:
                next_print += 1.0
                x, y, yaw = node.pose  # 5. read the outputs
                sd = math.sqrt(max(node.covariance[0, 0], node.covariance[1, 1]))
                err = math.hypot(x - truth[0], y - truth[1])
                print(f"t={rec.t_s:5.1f} s  pose ({x:6.3f}, {y:6.3f}, {math.degrees(yaw):7.2f}"
                      f" deg)  sd {100 * sd:4.1f} cm  error {100 * err:4.1f} cm  "
                      f"{node.status}")
    node.finish()
    fused = [r for r in node.landmarks() if r.fused]
    # A short segment (too few echoes for a fit) is fused reading by reading through the
    # model: its report has no fitted parameters (NaN), so show the fitted ones.
    fitted = [r for r in fused if r.landmark.ok]
    print(f"landmarks: {len(node.landmarks())} segments, {len(fused)} fused "
          f"({len(fitted)} of them fitted ok); the last fitted ones:")
    for r in fitted[-5:]:
        lm = r.in_map
        assert lm is not None
        what = (f"point ({lm.params[0]:.3f}, {lm.params[1]:.3f})" if lm.kind == "point" else
                f"wall rho={lm.params[0]:.3f} alpha={math.degrees(lm.params[1]):.1f} deg")
        print(f"  t={lm.ref_t_s:5.1f} s  {what}  kappa {lm.kappa_us:.2f} us  "
              f"({r.outcome})")
    mx, my, myaw = node.map_to_odom
    print(f"map->odom: ({mx:.3f}, {my:.3f}, {math.degrees(myaw):.2f} deg); "
          f"{node.stats.summary()}")


if __name__ == "__main__":
    raise SystemExit(main())

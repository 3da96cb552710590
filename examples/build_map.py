"""Build a landmark map from a logged drive, then localize against the built map.

1. simulate a drive around the room (a log, as `sonarloc simulate` or `record` writes);
2. localize it against the true map to get poses (`sonarloc localize`), or with
   `--slam` use no map at all: the odometry corrected by SLAM, as for a new place;
3. build a map from the log and those poses (`sonarloc map build`): walls from
   collinear wall fits, poles/rods/corners from clustered point fits, with uncertainty;
4. compare the built features with the true map, and localize again on the built map.

    python examples/build_map.py [--duration 58] [--slam] [--out out/built_room.geojson]
"""

from __future__ import annotations

import argparse
import io
import json
import math
from pathlib import Path

import numpy as np

from sonarloc.io.logfile import LogWriter, OdomRecord
from sonarloc.io.posescsv import PoseTrack
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import PoseEstimate
from sonarloc.localize.replay import replay_log
from sonarloc.maps.build import build_from_log
from sonarloc.maps.geojson import load_map, map_from_geojson
from sonarloc.report.logdata import load_log
from sonarloc.report.metrics import track_error
from sonarloc.world.rig import ring16
from sonarloc.world.simulate import simulate_records

ROOM = Path(__file__).resolve().parents[1] / "maps" / "room.geojson"


def _localize(log: str, fmap: FeatureMap) -> PoseTrack:
    rows: list[tuple[float, float, float, float]] = []
    covs: list[np.ndarray] = []

    def keep(_rec: OdomRecord, est: PoseEstimate) -> None:
        rows.append((est.t_s, est.x_m, est.y_m, est.yaw_rad))
        covs.append(est.state.cov)

    replay_log(io.StringIO(log), fmap, on_estimate=keep)
    a = np.array(rows)
    return PoseTrack(a[:, 0], a[:, 1], a[:, 2], a[:, 3], np.array(covs))


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=58.0,
                        help="simulated seconds (default %(default)s)")
    parser.add_argument("--seed", type=int, default=2, help="random seed (default %(default)s)")
    parser.add_argument("--slam", action="store_true",
                        help="build without poses: the odometry corrected by SLAM "
                             "(default off: poses from localizing on the true map)")
    parser.add_argument("--out", default="out/built_room.geojson",
                        help="built map (default %(default)s)")
    args = parser.parse_args(argv)

    truth_map = load_map(ROOM)
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(truth_map, ring16(), duration_s=args.duration,
                                     seed=args.seed))
    log = buf.getvalue()
    truth = load_log(io.StringIO(log)).truth

    if args.slam:  # a new place: no map to localize against
        built = build_from_log(io.StringIO(log), method="slam")
    else:
        poses = _localize(log, FeatureMap.from_map(truth_map))
        track = np.stack([poses.t_s, poses.x_m, poses.y_m, poses.yaw_rad], -1)
        print(f"localized on the true map: pose RMSE "
              f"{100 * track_error(track, truth).rmse_m:.1f} cm")
        built = build_from_log(io.StringIO(log), poses)
    print(f"built: {built.summary()}")
    gj = built.geojson()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(gj, indent=1))
    print(f"wrote {args.out}")

    # how close are the built point reflectors to the true ones?
    true_pts = [(r.geometry.x, r.geometry.y, r.kind) for r in truth_map.reflectors
                if r.kind in ("pole", "rod", "corner", "edge", "point")]
    for f in gj["features"]:
        if f["geometry"]["type"] != "Point":
            continue
        x, y = f["geometry"]["coordinates"]
        tx, ty, kind = min(true_pts, key=lambda p: math.hypot(p[0] - x, p[1] - y))
        print(f"  {f['properties']['kind']:6} at ({x:6.3f}, {y:6.3f}) sd "
              f"{100 * f['properties']['sd_m']:.1f} cm  n_obs {f['properties']['n_obs']:3}  "
              f"nearest true {kind:6} {100 * math.hypot(tx - x, ty - y):5.1f} cm away")

    again = _localize(log, FeatureMap.from_map(map_from_geojson(gj)))
    track2 = np.stack([again.t_s, again.x_m, again.y_m, again.yaw_rad], -1)
    print(f"localized on the built map: pose RMSE "
          f"{100 * track_error(track2, truth).rmse_m:.1f} cm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

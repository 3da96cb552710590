"""Landmark maps from logs: `sonarloc map build LOG [--poses POSES.csv] --out MAP.geojson`.

build: fits landmarks to the log's sonar readings (Kuc's forward model) with the
transducer poses taken from POSES.csv (e.g. the output of `sonarloc localize`,
interpolated to each reading) or, without --poses, from the odometry anchored at the
log's init pose, corrected by SLAM (--method slam, the default): the robot poses and
the landmarks are estimated together from the odometry and the landmarks seen again
(graph least squares), which takes the odometry's drift out of the map. A log SLAM
cannot correct (no landmark seen again, too few landmarks) is built from the odometry
alone and the summary says why; --method odometry always does (dead reckoning: it
drifts). The map frame is the init pose's: its error (the init record's SDs) is in
every feature's position and sd_m. Wall fits on one line are merged into walls, point fits
into poles, rods, corners, edges and points; each feature carries its uncertainty
(sd_m, and sd_alpha_deg for walls; with SLAM also sd_rel_m, the SD relative to the
map frame, its error taken out, which `sonarloc localize` uses) and how often it was
seen (n_obs). The map loads
with load_map and works in `sonarloc localize`. A summary goes to stderr; readings
without a pose (outside POSES.csv's time span, after the last odometry) are counted
there, never given the nearest pose. POSES.csv must be base_link poses: a scan CSV
(transducer poses, a tof_us column) is refused.
"""

from __future__ import annotations

import argparse
import sys

from sonarloc.commands._args import (
    add_reading_limit_options,
    reading_limit_options,
    refuse_overwrite,
    replace_options,
)
from sonarloc.errors import LogFormatError
from sonarloc.io.posescsv import read_poses_csv
from sonarloc.maps.build import BUILD_METHODS, BuildConfig, build_from_log
from sonarloc.maps.geojson import map_from_geojson, write_geojson


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="map_action", metavar="ACTION", required=True)
    b = sub.add_parser("build", help="build a landmark map from a log",
                       description=(__doc__ or "").strip(),
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    b.add_argument("log", metavar="LOG", help="log JSONL (rig, init, odom, tof records)")
    b.add_argument("--poses", metavar="POSES.csv",
                   help="base_link poses in map (default: odometry from the init pose)")
    b.add_argument("--method", choices=BUILD_METHODS, default=None,
                   help="without --poses: slam (odometry corrected with the landmarks seen "
                        "again) or odometry (dead reckoning alone); default "
                        f"{BuildConfig.method}")
    b.add_argument("--out", required=True, metavar="MAP.geojson", help="map GeoJSON to write")
    b.add_argument("--min-observations", type=int, default=BuildConfig.min_observations,
                   metavar="N", help="drop features seen fewer times (default %(default)s)")
    b.add_argument("--odom-gap", type=float, default=BuildConfig.odom_gap_s, metavar="S",
                   help="poses (odometry or POSES.csv) further apart than this are a gap: "
                        "the readings inside it, while the robot moved, are skipped and "
                        "counted (default %(default)s s, as `localize`; inf: no gaps)")
    add_reading_limit_options(b, like="localize")
    b.add_argument("--quiet", action="store_true", help="no summary on stderr")
    b.set_defaults(_map_run=_run_build)


def run(args: argparse.Namespace) -> int:
    return int(args._map_run(args))


def _run_build(args: argparse.Namespace) -> int:
    if args.min_observations < 1:
        raise ValueError(f"--min-observations must be at least 1, got {args.min_observations}")
    refuse_overwrite({"--out": args.out}, {"LOG": args.log, "--poses": args.poses})
    if args.poses and args.method is not None:
        raise ValueError(f"--method {args.method} is for a build without --poses (with "
                         "--poses the readings are placed by them)")
    poses = read_poses_csv(args.poses) if args.poses else None
    if not args.odom_gap > 0:
        raise ValueError(f"--odom-gap must be positive, got {args.odom_gap}")
    config = replace_options(BuildConfig(min_observations=args.min_observations,
                                         odom_gap_s=args.odom_gap),
                             reading_limit_options(args))
    result = build_from_log(args.log, poses, config, method=args.method)
    if result.readings == 0:
        # nothing to build from (no rig, no tof, or no pose for any reading): a failure,
        # not an empty map that a script would take for a successful run
        raise LogFormatError("; ".join([
            f"no sonar reading with a pose in {args.log} (it needs a rig record, tof records "
            "and odometry or --poses covering them)", f"log: {result.log.summary()}",
            *result.skipped_summary()]))
    obj = result.geojson()
    map_from_geojson(obj)  # what we write must load
    write_geojson(obj, args.out)
    if not args.quiet:
        print(f"sonarloc map build: {result.summary()}; wrote {args.out}", file=sys.stderr)
    return 0

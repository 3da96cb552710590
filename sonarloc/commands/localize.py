"""EKF localization of a logged drive against a landmark map (FORMATS.md section 5).

Reads a log (FORMATS.md section 4), fits landmarks to the sonar readings as they come
(Kuc's forward model), fuses them with the odometry in an EKF against the map, and
writes one pose row per odom record: t_s,x_m,y_m,yaw_deg and the covariance
cov_xx,cov_xy,cov_xt,cov_yy,cov_yt,cov_tt (m², m·rad, rad²; t = yaw) of base_link in
map. Without --out the rows go to stdout. A summary (malformed lines by line number,
unknown records, time going backwards, landmarks fused and rejected, final status)
goes to stderr. --method conventional uses each reading as a range along the beam
axis instead (the textbook sonar EKF: beam-wide bearing SD, walls ray-cast along the
axis); --method specular is that reading with walls seen at normal incidence;
--method odometry ignores the sonar. The kuc and odometry methods replay the log in
batches (landmarks fused at their reference readings, as if fitting took no time);
--online feeds the records one at a time, as a live robot would.
"""

from __future__ import annotations

import argparse
import sys

from sonarloc.commands._args import (
    accept_negative_values,
    add_reading_limit_options,
    parse_pose,
    reading_limit_options,
    refuse_overwrite,
    replace_options,
)
from sonarloc.errors import LogFormatError
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import LocalizerConfig
from sonarloc.localize.replay import Mode, PoseCsvWriter, replay_log
from sonarloc.maps.geojson import load_map

# "-1.5,2,90" starts with "-": let argparse take it as a value, not an option.



def add_arguments(parser: argparse.ArgumentParser) -> None:
    accept_negative_values(parser)
    parser.add_argument("log", metavar="LOG", help="log JSONL (rig, init, odom, tof records)")
    parser.add_argument("--map", required=True, metavar="MAP", help="map GeoJSON")
    parser.add_argument("--out", metavar="POSES.csv", help="pose CSV to write (default stdout)")
    parser.add_argument("--init", metavar="X,Y,YAW_DEG",
                        help="prior pose of base_link in map, overriding the log's init record")
    parser.add_argument("--method", default="kuc", choices=("kuc", "conventional", "specular",
                                                            "odometry"),
                        help="observation model (default kuc: fitted landmarks)")
    parser.add_argument("--status", action="store_true",
                        help="add a `status` column (tracking, dead_reckoning, lost)")
    parser.add_argument("--online", action="store_true",
                        help="feed the records one at a time as a live robot would (fits "
                             "fused when they complete); slower than the default batch "
                             "replay of the kuc and odometry methods")
    parser.add_argument("--relocalize", action="store_true",
                        help="when lost, relocalize globally from the landmarks fitted "
                             "recently (an unambiguous match to the map, else keep trying); "
                             "without an init record or --init, start that way (pose rows "
                             "begin at the first fix); runs record by record")
    parser.add_argument("--odom-gap", type=float, metavar="S", default=None,
                        help="odometry records further apart than this are a gap: the "
                             "readings inside it, while the robot moved, are skipped and "
                             "counted (default 1 s; raise it for odometry slower than 3 Hz; "
                             "inf: no gaps)")
    parser.add_argument("--map-sd", type=float, metavar="M", default=None,
                        help="SD of the map's feature positions in metres (a map measured "
                             "with a tape: 0.01), the map error shared by the readings of "
                             "an update; a feature's own sd_rel_m or else sd_m (written "
                             "by `map build`) is used where larger (default 0: the map "
                             "taken as exact unless it says otherwise)")
    parser.add_argument("--map-error-memory", type=float, metavar="S", default=None,
                        help="take a feature's map error as one constant its readings "
                             "share: its map variance grows with its fusions of the last "
                             "~S seconds (10 with honest map SDs; default 0: off, each "
                             "update takes the map variance as it is)")
    add_reading_limit_options(parser, like="fit")
    parser.add_argument("--quiet", action="store_true", help="no summary on stderr")


def run(args: argparse.Namespace) -> int:
    refuse_overwrite({"--out": args.out}, {"LOG": args.log, "--map": args.map})
    init = parse_pose(args.init, "--init") if args.init is not None else None
    fmap = FeatureMap.from_map(load_map(args.map))
    config = LocalizerConfig(method=args.method, relocalize=args.relocalize)
    config = replace_options(config, [("--odom-gap", "odom_gap_s", args.odom_gap),
                                      ("--map-sd", "map_sd_m", args.map_sd),
                                      ("--map-error-memory", "map_error_memory_s",
                                       args.map_error_memory),
                                      *reading_limit_options(args)])
    mode: Mode = "online" if args.online else "auto"
    if args.out:
        with open(args.out, "w", encoding="utf-8", newline="") as handle:
            writer = PoseCsvWriter(handle, args.status)
            result = replay_log(args.log, fmap, config=config, init=init,
                                on_estimate=writer.write, mode=mode)
    else:
        writer = PoseCsvWriter(sys.stdout, args.status)
        result = replay_log(args.log, fmap, config=config, init=init, on_estimate=writer.write,
                            mode=mode)
    if not args.quiet:
        print(f"sonarloc localize: {result.summary()}", file=sys.stderr)
        for lineno, msg in result.log.malformed[:10]:
            print(f"  line {lineno}: {msg}", file=sys.stderr)
        for lineno, prev, now in result.log.time_backwards[:10]:
            print(f"  line {lineno}: time went backwards ({now} after {prev})", file=sys.stderr)
    if result.log.records == 0:
        # not one usable line (an empty file, or every line malformed): a failure, not an
        # empty track that a script would take for a successful run
        raise LogFormatError(f"no usable record in {args.log} "
                             f"({result.log.malformed_count} malformed line(s))")
    return 0

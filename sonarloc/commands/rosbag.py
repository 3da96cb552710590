"""ROS bags without a ROS install: import Range/Odometry topics into a log, export poses.

  sonarloc rosbag import BAG --out LOG.jsonl [--sensor /sonar/0=0@0.2,0,0 ...] [--rig RIG.json]
  sonarloc rosbag export POSES.csv --out OUT.bag [--log LOG.jsonl]

Import reads sensor_msgs/msg/Range (one topic per transducer, or frame_ids on one
topic) and nav_msgs/msg/Odometry from a ROS 1 .bag or a ROS 2 bag directory; an
unindexed ROS 1 bag (the NAME.bag.active a killed recorder leaves) is read record by
record, and the summary says so and how many bytes at its end were lost. Mount
poses come from --sensor, a rig JSON, or the bag's /tf_static. Export writes
geometry_msgs/msg/PoseWithCovarianceStamped in `map` and, with --log, the map->odom
transform on /tf.
"""

from __future__ import annotations

import argparse
import math
import sys

from sonarloc.commands._args import refuse_overwrite
from sonarloc.io.logfile import InitRecord


def _init(text: str) -> InitRecord:
    parts = text.split(",")
    try:
        v = [float(p) for p in parts]
    except ValueError:
        v = []
    if len(v) not in (3, 5) or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(
            f"expected X,Y,YAW_DEG[,SD_XY_M,SD_YAW_DEG], got {text!r}")
    sd_xy, sd_yaw = (v[3], v[4]) if len(v) == 5 else (0.1, 5.0)
    return InitRecord(0.0, v[0], v[1], v[2], sd_xy, sd_yaw)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="rosbag_command", metavar="ACTION", required=True)
    imp = sub.add_parser("import", help="Range + Odometry topics of a bag -> log JSONL",
                         description="Convert sensor_msgs/msg/Range and nav_msgs/msg/Odometry "
                                     "topics of a ROS 1 or ROS 2 bag into a sonarloc log.")
    imp.add_argument("bag", help="a ROS 1 .bag file or a ROS 2 bag directory; an unindexed "
                                 "ROS 1 bag (NAME.bag.active of a killed `rosbag record`) "
                                 "is read sequentially, up to a truncated last record")
    imp.add_argument("--out", required=True, help="log JSONL to write")
    imp.add_argument("--sensor", action="append", default=[], metavar="NAME=ID[@X,Y,YAW_DEG]",
                     help="map a Range topic or frame_id to a sensor id, optionally with its "
                          "mount pose in base_link (repeat per transducer); without any, all "
                          "Range sources are numbered in natural order")
    imp.add_argument("--rig", help="rig JSON: {sensors: [{id, x_m, y_m, yaw_deg, "
                                   "[topic], [frame_id]}], speed_of_sound_mps}")
    imp.add_argument("--odom-topic", help="nav_msgs/msg/Odometry topic (default: the only one)")
    imp.add_argument("--truth-topic", help="ground-truth pose topic, written as truth records")
    imp.add_argument("--base-frame", help="frame of the mount poses (default: odometry "
                                          "child_frame_id, else base_link)")
    imp.add_argument("--speed-of-sound", type=float, metavar="MPS",
                     help="speed of sound the driver used to compute ranges (default 343)")
    imp.add_argument("--stamp", choices=("header", "bag"), default="header",
                     help="time source: message header stamps (default) or bag receive times")
    imp.add_argument("--init", type=_init, metavar="X,Y,YAW_DEG[,SD_XY,SD_YAW_DEG]",
                     help="also write an init record (prior of base_link in map)")
    imp.add_argument("--reorder-window", type=float, default=1.0, metavar="S",
                     help="sort records by stamp within this much bag time (default 1.0 s)")

    exp = sub.add_parser("export", help="POSES.csv -> PoseWithCovarianceStamped (+ map->odom tf)",
                         description="Write estimated poses (FORMATS.md section 5) into a bag "
                                     "as geometry_msgs/msg/PoseWithCovarianceStamped, and the "
                                     "map->odom transform as tf2_msgs/msg/TFMessage.")
    exp.add_argument("poses", help="pose CSV from `sonarloc localize --out`")
    exp.add_argument("--out", required=True, help="new bag: NAME.bag (ROS 1) or a directory "
                                                 "(ROS 2)")
    exp.add_argument("--log", help="the localized log: its odometry gives the map->odom tf")
    exp.add_argument("--ros", type=int, choices=(1, 2), help="bag version (default from --out)")
    exp.add_argument("--storage", choices=("sqlite3", "mcap"), default="sqlite3",
                     help="ROS 2 storage plugin (default sqlite3)")
    exp.add_argument("--pose-topic", default="/sonarloc/pose",
                     help="topic of the poses (default %(default)s)")
    exp.add_argument("--map-frame", default="map",
                     help="frame_id of the poses, parent of the tf (default %(default)s)")
    exp.add_argument("--odom-frame", default="odom",
                     help="child frame of the map->odom tf (default %(default)s)")


def run(args: argparse.Namespace) -> int:
    from sonarloc.io import rosbag

    if args.rosbag_command == "import":
        refuse_overwrite({"--out": args.out}, {"BAG": args.bag, "--rig": args.rig})
        rig, rig_names = (rosbag.load_rig_json(args.rig) if args.rig else (None, []))
        sensors = [rosbag.parse_sensor_spec(s) for s in args.sensor]
        stats = rosbag.import_bag(
            args.bag, args.out, sensors=sensors, rig=rig, rig_names=rig_names,
            odom_topic=args.odom_topic, truth_topic=args.truth_topic,
            base_frame=args.base_frame, speed_of_sound_mps=args.speed_of_sound,
            stamp=args.stamp, init=args.init, reorder_window_s=args.reorder_window)
        print(f"{args.out}: {stats.summary()}", file=sys.stderr)
        for sid in sorted(stats.sensors):
            print(f"  sensor {sid}: {stats.sensors[sid]} (mount from "
                  f"{stats.mount_from.get(sid, '?')})", file=sys.stderr)
        return 0
    from sonarloc.io.posescsv import read_poses_csv

    refuse_overwrite({"--out": args.out}, {"POSES": args.poses, "--log": args.log})
    track = read_poses_csv(args.poses)
    odometry = rosbag.odometry_from_log(args.log) if args.log else None
    done = rosbag.export_poses(track, args.out, odometry=odometry, ros_version=args.ros,
                                pose_topic=args.pose_topic, map_frame=args.map_frame,
                                odom_frame=args.odom_frame, storage=args.storage)
    print(f"{args.out}: {done.summary()}", file=sys.stderr)
    return 0

"""ROS bag import/export through real rosbags readers and writers (ROS 1 and ROS 2)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc import se2
from sonarloc.io import rosbag
from sonarloc.io.logfile import OdomRecord, RigRecord, TofRecord, TruthRecord, iter_log
from sonarloc.io.posescsv import PoseTrack, read_poses_csv, write_poses_csv

pytest.importorskip("rosbags")
from rosbags.rosbag1 import Writer as Writer1  # noqa: E402
from rosbags.rosbag2 import Writer as Writer2  # noqa: E402

C = 343.0
MOUNTS = [(0.2, 0.0, 0.0), (0.0, 0.2, 90.0), (-0.2, 0.0, 180.0)]


def _store(version: int):
    return rosbag.typestore(version)


def _header(ts, t_s: float, frame: str):
    ns = int(round(t_s * 1e9))
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
    fields = [n for n, _ in ts.fielddefs["std_msgs/msg/Header"][1]]
    kw = {"stamp": stamp, "frame_id": frame}
    if "seq" in fields:
        kw["seq"] = 0
    return ts.types["std_msgs/msg/Header"](**kw)


def _quat(ts, yaw: float):
    return ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                   w=math.cos(yaw / 2))


def write_test_bag(path: Path, version: int, *, ranges: list[tuple[float, int, float]],
                   odom: list[tuple[float, float, float, float]], tf_static: bool = True,
                   one_topic: bool = False, lag_s: float = 0.0, t0: float = 1_700_000_000.0,
                   truth: bool = False, compression: str | None = None,
                   chunk_bytes: int | None = None):
    """A bag with Range topics per sensor (or one topic with frame_ids), Odometry, /tf_static.

    ``ranges``: (t_s, sensor, range_m); ``odom``: (t_s, x, y, yaw_rad). Messages are
    written at bag time stamp + ``lag_s`` (receive delay). With ``truth``, a PoseStamped
    topic ``/gt`` carries the odometry poses shifted by +1 m in x. ROS 1 only:
    ``compression`` ``"bz2"`` or ``"lz4"`` compresses the chunks; ``chunk_bytes`` closes a
    chunk once it holds more than that many bytes (rosbags' default 1 MiB).
    """
    ts = _store(version)
    T = ts.types
    writer = Writer1(path) if version == 1 else Writer2(path, version=9)
    if compression is not None:
        writer.set_compression(Writer1.CompressionFormat[compression.upper()])
    if chunk_bytes is not None:
        writer.chunk_threshold = chunk_bytes
    ser = ts.serialize_ros1 if version == 1 else ts.serialize_cdr
    with writer:
        topics = ["/sonar"] if one_topic else [f"/sonar/{i}" for i in range(len(MOUNTS))]
        rconn = {t: writer.add_connection(t, "sensor_msgs/msg/Range", typestore=ts)
                 for t in topics}
        oconn = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=ts)
        gconn = (writer.add_connection("/gt", "geometry_msgs/msg/PoseStamped", typestore=ts)
                 if truth else None)
        if tf_static:
            sconn = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=ts)
            tfs = [T["geometry_msgs/msg/TransformStamped"](
                header=_header(ts, t0, "base_link"), child_frame_id=f"sonar_{i}",
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=mx, y=my, z=0.3),
                    rotation=_quat(ts, math.radians(myaw))))
                for i, (mx, my, myaw) in enumerate(MOUNTS)]
            msg = T["tf2_msgs/msg/TFMessage"](transforms=tfs)
            writer.write(sconn, int(t0 * 1e9), ser(msg, "tf2_msgs/msg/TFMessage"))
        events = [(t, "r", (s, r)) for t, s, r in ranges] + [(t, "o", (x, y, th))
                                                              for t, x, y, th in odom]
        events.sort(key=lambda e: e[0])
        for t, kind, data in events:
            if kind == "r":
                sid, r = data
                msg = T["sensor_msgs/msg/Range"](
                    header=_header(ts, t0 + t, f"sonar_{sid}"), radiation_type=0,
                    field_of_view=0.4, min_range=0.15, max_range=10.0, range=r)
                topic = topics[0] if one_topic else topics[sid]
                writer.write(rconn[topic], int((t0 + t + lag_s) * 1e9),
                             ser(msg, "sensor_msgs/msg/Range"))
            else:
                x, y, th = data
                pose = T["geometry_msgs/msg/Pose"](
                    position=T["geometry_msgs/msg/Point"](x=x, y=y, z=0.0),
                    orientation=_quat(ts, th))
                msg = T["nav_msgs/msg/Odometry"](
                    header=_header(ts, t0 + t, "odom"), child_frame_id="base_link",
                    pose=T["geometry_msgs/msg/PoseWithCovariance"](
                        pose=pose, covariance=np.zeros(36)),
                    twist=T["geometry_msgs/msg/TwistWithCovariance"](
                        twist=T["geometry_msgs/msg/Twist"](
                            linear=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0),
                            angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)),
                        covariance=np.zeros(36)))
                writer.write(oconn, int((t0 + t + lag_s) * 1e9), ser(msg, "nav_msgs/msg/Odometry"))
                if gconn is not None:
                    gt = T["geometry_msgs/msg/PoseStamped"](
                        header=_header(ts, t0 + t, "map"),
                        pose=T["geometry_msgs/msg/Pose"](
                            position=T["geometry_msgs/msg/Point"](x=x + 1.0, y=y, z=0.0),
                            orientation=_quat(ts, th)))
                    writer.write(gconn, int((t0 + t + lag_s) * 1e9),
                                 ser(gt, "geometry_msgs/msg/PoseStamped"))
    return t0


def _scenario():
    ranges = []
    for k in range(30):
        t = 0.05 * k
        sid = k % 3
        r = [1.5 + 0.01 * k, math.inf, 2.0][sid]  # sensor 1 never sees anything
        ranges.append((t, sid, r))
    ranges.append((1.6, 0, -math.inf))  # too close: skipped
    ranges.append((1.65, 2, float("nan")))  # invalid: skipped
    ranges.append((1.7, 2, 0.05))  # below min_range: skipped
    ranges.append((1.75, 0, 10.0))  # at max_range: no echo
    odom = [(0.1 * k, 0.05 * k, 0.01 * k, 0.02 * k) for k in range(18)]
    return ranges, odom


@pytest.mark.parametrize("version", [1, 2])
def test_import_ranges_odom_and_tf_static_mounts(tmp_path: Path, version: int):
    ranges, odom = _scenario()
    bag = tmp_path / ("in.bag" if version == 1 else "in_bag")
    t0 = write_test_bag(bag, version, ranges=ranges, odom=odom)
    log = tmp_path / "log.jsonl"
    stats = rosbag.import_bag(bag, log)
    recs = list(iter_log(log, strict=True))
    rig = recs[0]
    assert isinstance(rig, RigRecord)
    assert [(s.id, round(s.x_m, 9), round(s.y_m, 9), round(s.yaw_deg, 6)) for s in rig.sensors] \
        == [(i, m[0], m[1], m[2]) for i, m in enumerate(MOUNTS)]
    assert stats.mount_from == {0: "/tf_static", 1: "/tf_static", 2: "/tf_static"}
    tofs = [r for r in recs if isinstance(r, TofRecord)]
    odoms = [r for r in recs if isinstance(r, OdomRecord)]
    assert len(odoms) == 18 and stats.odom == 18
    assert len(tofs) == 31 == stats.tof
    assert stats.no_echo == 11 and stats.skipped_too_close == 2 and stats.skipped_invalid == 1
    by_t = {round(r.t_s - t0, 6): r for r in tofs}
    # range 1.5 m at t=0 from sensor 0: TOF = 2 r / c (float32 range in the message)
    assert by_t[0.0].sensor == 0
    assert by_t[0.0].tof_us == pytest.approx(2 * 1.5 / C * 1e6, abs=1e-3)
    assert by_t[0.05].sensor == 1 and by_t[0.05].tof_us is None
    assert by_t[1.75].tof_us is None
    o = odoms[5]
    assert o.t_s - t0 == pytest.approx(0.5, abs=1e-6)
    assert (o.x_m, o.y_m) == pytest.approx((0.25, 0.05))
    assert o.yaw_deg == pytest.approx(math.degrees(0.1))
    assert all(a.t_s <= b.t_s for a, b in zip(recs[1:], recs[2:], strict=False))


def test_import_one_topic_with_frame_ids_and_explicit_specs(tmp_path: Path):
    ranges, odom = _scenario()
    bag = tmp_path / "one.bag"
    write_test_bag(bag, 1, ranges=ranges, odom=odom, tf_static=False, one_topic=True)
    log = tmp_path / "log.jsonl"
    specs = [rosbag.parse_sensor_spec(s) for s in
             ("sonar_0=7@0.2,0,0", "sonar_1=3@0,0.2,90", "sonar_2=5@-0.2,0,180")]
    stats = rosbag.import_bag(bag, log, sensors=specs)
    recs = list(iter_log(log))
    assert [s.id for s in recs[0].sensors] == [3, 5, 7]
    assert {r.sensor for r in recs if isinstance(r, TofRecord)} == {3, 5, 7}
    assert stats.mount_from == {3: "command line", 5: "command line", 7: "command line"}


def test_import_without_mount_names_the_sensor(tmp_path: Path):
    ranges, odom = _scenario()
    bag = tmp_path / "nomount.bag"
    write_test_bag(bag, 1, ranges=ranges, odom=odom, tf_static=False)
    with pytest.raises(rosbag.RosbagError, match=r"no mount pose for sensor 0 \(topic /sonar/0"):
        rosbag.import_bag(bag, tmp_path / "x.jsonl")


def test_import_reorders_within_window_and_bag_stamps(tmp_path: Path):
    ranges, odom = _scenario()
    bag = tmp_path / "lag.bag"
    # receive times lag the header stamps by 0.3 s for everything; order by header kept
    t0 = write_test_bag(bag, 1, ranges=ranges, odom=odom, lag_s=0.3)
    log = tmp_path / "h.jsonl"
    rosbag.import_bag(bag, log)
    recs = list(iter_log(log, strict=True))[1:]
    assert recs[0].t_s == pytest.approx(t0)
    log2 = tmp_path / "b.jsonl"
    rosbag.import_bag(bag, log2, stamp="bag")
    recs2 = list(iter_log(log2, strict=True))[1:]
    assert recs2[0].t_s == pytest.approx(t0 + 0.3)


def test_rig_json_names_and_speed_of_sound(tmp_path: Path):
    ranges, odom = _scenario()
    bag = tmp_path / "rig.bag"
    write_test_bag(bag, 1, ranges=ranges, odom=odom, tf_static=False)
    rig_path = tmp_path / "rig.json"
    rig_path.write_text('{"speed_of_sound_mps": 340.0, "sensors": ['
                        '{"id": 0, "x_m": 0.2, "y_m": 0, "yaw_deg": 0, "topic": "/sonar/0"},'
                        '{"id": 1, "x_m": 0, "y_m": 0.2, "yaw_deg": 90, "topic": "/sonar/1"},'
                        '{"id": 2, "x_m": -0.2, "y_m": 0, "yaw_deg": 180, "frame_id": "sonar_2"}'
                        ']}')
    rig, names = rosbag.load_rig_json(rig_path)
    log = tmp_path / "log.jsonl"
    rosbag.import_bag(bag, log, rig=rig, rig_names=names)
    recs = list(iter_log(log))
    assert recs[0].speed_of_sound_mps == 340.0
    first = next(r for r in recs if isinstance(r, TofRecord))
    assert first.tof_us == pytest.approx(2 * 1.5 / 340.0 * 1e6, abs=1e-3)


def _track(n: int, seed: int) -> PoseTrack:
    rng = np.random.default_rng(seed)
    t = 10.0 + 0.1 * np.arange(n)
    a = rng.normal(size=(n, 3, 3)) * 0.01
    cov = a @ np.swapaxes(a, -1, -2) + np.eye(3) * 1e-6
    return PoseTrack(t, rng.uniform(-5, 5, n), rng.uniform(-5, 5, n),
                     rng.uniform(-math.pi, math.pi, n), cov)


@pytest.mark.parametrize("version,storage", [(1, "sqlite3"), (2, "sqlite3"), (2, "mcap")])
def test_export_poses_and_map_to_odom(tmp_path: Path, version: int, storage: str):
    track = _track(20, 1)
    # odometry = map pose seen through a fixed map->odom transform (1, -2, 30 deg)
    T = np.array([1.0, -2.0, math.radians(30.0)])
    c, s = math.cos(-T[2]), math.sin(-T[2])
    dx, dy = track.x_m - T[0], track.y_m - T[1]
    odo = np.stack([track.t_s, c * dx - s * dy, s * dx + c * dy, track.yaw_rad - T[2]], -1)
    out = tmp_path / ("poses.bag" if version == 1 else "poses_bag")
    stats = rosbag.export_poses(track, out, odometry=odo, storage=storage)
    assert stats.poses == 20 and stats.transforms == 20 and stats.ros_version == version
    poses, tfs = [], []
    for topic, t_ns, msg in rosbag.read_messages(out):
        if topic == "/sonarloc/pose":
            poses.append((t_ns, msg))
        else:
            tfs.append(msg)
    assert len(poses) == 20 and len(tfs) == 20
    for i, (t_ns, msg) in enumerate(poses):
        assert t_ns == int(round(track.t_s[i] * 1e9))
        assert msg.header.frame_id == "map"
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        assert (p.x, p.y) == pytest.approx((track.x_m[i], track.y_m[i]))
        yaw = rosbag.yaw_from_quaternion(q.x, q.y, q.z, q.w)
        assert math.remainder(yaw - track.yaw_rad[i], 2 * math.pi) == pytest.approx(0, abs=1e-9)
        cov = np.asarray(msg.pose.covariance).reshape(6, 6)
        assert cov[np.ix_([0, 1, 5], [0, 1, 5])] == pytest.approx(track.cov[i])
    for tf in tfs:
        (x,) = tf.transforms
        assert (x.header.frame_id, x.child_frame_id) == ("map", "odom")
        tr, q = x.transform.translation, x.transform.rotation
        assert (tr.x, tr.y, rosbag.yaw_from_quaternion(q.x, q.y, q.z, q.w)) == \
            pytest.approx(tuple(T), abs=1e-9)


@settings(max_examples=40, deadline=None)
@given(m=st.tuples(*[st.floats(-50, 50)] * 2, st.floats(-math.pi, math.pi)),
       o=st.tuples(*[st.floats(-50, 50)] * 2, st.floats(-math.pi, math.pi)))
def test_map_to_odom_composes_back(m, o):
    T = rosbag.map_to_odom(np.array(m), np.array(o))
    back = tuple(se2.compose(T, o))
    assert back[:2] == pytest.approx(m[:2], abs=1e-9)
    assert math.remainder(back[2] - m[2], 2 * math.pi) == pytest.approx(0, abs=1e-9)


@settings(max_examples=30, deadline=None)
@given(st.text(max_size=30))
def test_sensor_spec_parser_garbage(text):
    try:
        spec = rosbag.parse_sensor_spec(text)
    except ValueError as err:
        assert "--sensor" in str(err)
    else:
        assert spec.name and isinstance(spec.sensor, int)


def test_cli_import_then_export_roundtrip(tmp_path: Path, run_cli):
    ranges, odom = _scenario()
    bag = tmp_path / "in_bag"
    write_test_bag(bag, 2, ranges=ranges, odom=odom)
    log = tmp_path / "log.jsonl"
    proc = run_cli("rosbag", "import", str(bag), "--out", str(log), "--init", "1,2,30")
    assert proc.returncode == 0, proc.stderr
    assert "31 tof (11 no echo) from 3 sensors" in proc.stderr
    odo = [r for r in iter_log(log) if isinstance(r, OdomRecord)]
    # poses = odometry moved by a fixed transform; export recovers that transform
    track = PoseTrack(np.array([r.t_s for r in odo]), np.array([r.x_m + 1.0 for r in odo]),
                      np.array([r.y_m for r in odo]),
                      np.radians([r.yaw_deg for r in odo]), np.tile(np.eye(3) * 1e-4,
                                                                    (len(odo), 1, 1)))
    poses = tmp_path / "poses.csv"
    write_poses_csv(poses, track)
    assert len(read_poses_csv(poses)) == len(odo)
    out = tmp_path / "out.bag"
    proc = run_cli("rosbag", "export", str(poses), "--out", str(out), "--log", str(log))
    assert proc.returncode == 0, proc.stderr
    tfs = [m for topic, _, m in rosbag.read_messages(out, ["/tf"])]
    assert len(tfs) == len(odo)
    assert all(m.transforms[0].transform.translation.x == pytest.approx(1.0) for m in tfs)
    # exporting again onto the same path is refused with a one-line error
    proc = run_cli("rosbag", "export", str(poses), "--out", str(out))
    assert proc.returncode == 2 and "exists already" in proc.stderr


def test_cli_import_errors(tmp_path: Path, run_cli):
    proc = run_cli("rosbag", "import", str(tmp_path / "missing.bag"), "--out",
                   str(tmp_path / "x.jsonl"))
    assert proc.returncode == 2 and "does not exist" in proc.stderr
    proc = run_cli("rosbag", "import", "x.bag", "--out", "y", "--sensor", "bad")
    assert proc.returncode == 2 and "--sensor" in proc.stderr


def test_truth_topic(tmp_path: Path):
    ranges, odom = _scenario()
    bag = tmp_path / "truth.bag"
    t0 = write_test_bag(bag, 1, ranges=ranges, odom=odom, truth=True)
    with pytest.raises(rosbag.RosbagError, match="no truth topic '/nope'"):
        rosbag.import_bag(bag, tmp_path / "t.jsonl", truth_topic="/nope")
    out = tmp_path / "t2.jsonl"
    stats = rosbag.import_bag(bag, out, truth_topic="/gt")
    truth = [r for r in iter_log(out) if isinstance(r, TruthRecord)]
    assert len(truth) == stats.truth == 18
    assert truth[3].t_s - t0 == pytest.approx(0.3, abs=1e-6)
    assert (truth[3].x_m, truth[3].y_m) == pytest.approx((0.15 + 1.0, 0.03))


def test_import_refuses_a_speed_of_sound_that_is_not_air(tmp_path: Path):
    # the log's rig record would be refused when read (3 m/s: every reading unmatched)
    with pytest.raises(ValueError, match=r"`speed_of_sound_mps` must be within \[250, 450\]"):
        rosbag.import_bag(tmp_path / "none.bag", tmp_path / "out.jsonl", speed_of_sound_mps=3.0)
    assert not (tmp_path / "out.jsonl").exists()

"""ROS bags without a ROS install, through the ``rosbags`` library (optional extra ``ros``).

Import
    ``sensor_msgs/msg/Range`` topics (one per transducer, or one topic with a
    ``frame_id`` per transducer) and ``nav_msgs/msg/Odometry`` become a log JSONL
    (FORMATS.md section 4): a ``rig`` record first, then ``odom`` and ``tof``
    records in time order. Each Range source (a topic or a ``frame_id``) is mapped to a
    sensor id; its mount pose in ``base_link`` comes from the command line, a rig JSON,
    or the bag's ``/tf_static`` (projected onto the plane).

    Range semantics follow REP 117: ``+inf`` (or a value at or above ``max_range``) is
    "no echo" (``tof_us: null``); ``-inf``, NaN and values below ``min_range`` are not
    readings and are skipped and counted. ``tof_us = 2 range / c`` with the speed of
    sound ``c`` the device driver used to convert its time of flight into a range.

Export
    A pose CSV (FORMATS.md section 5) becomes ``geometry_msgs/msg/PoseWithCovarianceStamped``
    messages in ``map`` and, when the log's odometry is given, the ``map -> odom``
    transform as ``tf2_msgs/msg/TFMessage`` on ``/tf`` (REP-105: ``map -> odom ->
    base_link``), as a ROS 1 ``.bag`` file or a ROS 2 bag directory.
"""

from __future__ import annotations

import heapq
import itertools
import json
import math
import re
from collections import Counter
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, Literal

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.errors import LogFormatError, SonarlocError
from sonarloc.io.logfile import (
    InitRecord,
    LogWriter,
    OdomRecord,
    Record,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
    iter_log,
)
from sonarloc.io.posescsv import PoseTrack
from sonarloc.io.rosbag1_scan import BagScanError, ScanReport, UnindexedBag1Reader
from sonarloc.physics.sound import check_air_speed_of_sound

RANGE_TYPE = "sensor_msgs/msg/Range"
ODOM_TYPE = "nav_msgs/msg/Odometry"
TF_TYPE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = ("nav_msgs/msg/Odometry", "geometry_msgs/msg/PoseStamped",
              "geometry_msgs/msg/PoseWithCovarianceStamped")


class RosbagError(SonarlocError):
    """A ROS bag could not be read or written, or its contents do not fit the request."""


def _rosbags() -> Any:
    """Import rosbags lazily, with a clear message when the extra is missing."""
    try:
        import rosbags.highlevel  # noqa: F401
        import rosbags.rosbag1
        import rosbags.rosbag2
        import rosbags.typesys
    except ImportError as err:  # pragma: no cover - depends on the environment
        raise SonarlocError(
            "ROS bag support needs the `rosbags` package: pip install 'sonarloc[ros]'"
        ) from err
    return rosbags


def typestore(ros_version: int) -> Any:
    """The rosbags type store for ROS 1 (Noetic) or ROS 2 (Humble), with tf2_msgs/TFMessage.

    rosbags' Noetic store lacks ``tf2_msgs/msg/TFMessage``; it is registered from its
    message definition (md5 94810edda583a504dfda3829e70d7eec, as in ROS).
    """
    rb = _rosbags()
    if ros_version not in (1, 2):
        raise ValueError(f"`ros_version` must be 1 or 2, got {ros_version!r}")
    ts = rb.typesys.get_typestore(
        rb.typesys.Stores.ROS1_NOETIC if ros_version == 1 else rb.typesys.Stores.ROS2_HUMBLE)
    if TF_TYPE not in ts.fielddefs:
        ts.register(rb.typesys.get_types_from_msg(
            "geometry_msgs/TransformStamped[] transforms", TF_TYPE))
    return ts


# --------------------------------------------------------------------------- mapping

@dataclass(frozen=True)
class RangeSource:
    """How one Range source becomes a transducer.

    ``name`` matches a topic (``/sonar/3``) or a header ``frame_id`` (``sonar_3``);
    ``mount`` is (x_m, y_m, yaw_deg) in ``base_link``, or None to take it from a rig
    JSON or the bag's ``/tf_static``.
    """

    name: str
    sensor: int
    mount: tuple[float, float, float] | None = None


_SPEC = re.compile(r"^(?P<name>[^=]+)=(?P<id>-?\d+)(?:@(?P<pose>[^@]+))?$")


def parse_sensor_spec(text: str) -> RangeSource:
    """Parse ``NAME=ID`` or ``NAME=ID@X,Y,YAW_DEG`` (NAME: topic or frame_id)."""
    m = _SPEC.match(text.strip())
    if not m:
        raise ValueError(f"`--sensor` must look like NAME=ID or NAME=ID@X,Y,YAW_DEG, got {text!r}")
    mount = None
    if m["pose"] is not None:
        parts = m["pose"].split(",")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            values = []
        if len(values) != 3 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"`--sensor` pose must be X,Y,YAW_DEG (three numbers), got "
                             f"{m['pose']!r} in {text!r}")
        mount = (values[0], values[1], values[2])
    return RangeSource(m["name"], int(m["id"]), mount)


def load_rig_json(path: str | Path) -> tuple[RigRecord, list[RangeSource]]:
    """Read a rig JSON: ``{"sensors": [{id, x_m, y_m, yaw_deg, [topic], [frame_id]}, ...],
    "speed_of_sound_mps": ...}`` (the log's ``rig`` record, plus optional names).

    Returns the rig and the Range sources named by ``topic``/``frame_id`` keys.
    """
    from sonarloc.io.logfile import record_from_dict

    try:
        with open(path, encoding="utf-8") as handle:
            obj = json.load(handle)
    except OSError as err:
        raise LogFormatError(f"cannot open rig {path}: {err.strerror}") from err
    except json.JSONDecodeError as err:
        raise LogFormatError(f"rig {path}: line {err.lineno}: {err.msg}") from err
    if not isinstance(obj, dict):
        raise LogFormatError(f"rig {path}: expected a JSON object with `sensors`")
    try:
        rig = record_from_dict({**obj, "type": "rig"})
    except ValueError as err:
        raise LogFormatError(f"rig {path}: {err}") from err
    assert isinstance(rig, RigRecord)
    sources = []
    for s in obj["sensors"]:
        for key in ("topic", "frame_id"):
            if isinstance(s.get(key), str):
                sources.append(RangeSource(s[key], int(s["id"]),
                                           (float(s["x_m"]), float(s["y_m"]),
                                            float(s["yaw_deg"]))))
    return rig, sources


def _natural_key(text: str) -> list[object]:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", text)]


# --------------------------------------------------------------------------- geometry

def yaw_from_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Heading (rad) of a rotation, projected onto the plane (REP-103, z up)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def map_to_odom(map_pose: NDArray[np.float64], odom_pose: NDArray[np.float64]
                ) -> NDArray[np.float64]:
    """The ``map -> odom`` transform T with ``map_pose = T ⊕ odom_pose``.

    Parameters
    ----------
    map_pose, odom_pose : (..., 3) poses (x_m, y_m, yaw_rad) of ``base_link``.

    Returns
    -------
    (..., 3) transform (x_m, y_m, yaw_rad), yaw wrapped to [-pi, pi).
    """
    return se2.compose(map_pose, se2.inverse(odom_pose))


# --------------------------------------------------------------------------- import

@dataclass
class ImportStats:
    """What :func:`import_bag` found and wrote."""

    tof: int = 0
    no_echo: int = 0
    odom: int = 0
    truth: int = 0
    skipped_too_close: int = 0
    skipped_invalid: int = 0
    late: int = 0
    unmapped: Counter[str] = field(default_factory=Counter)
    sensors: dict[int, str] = field(default_factory=dict)
    mount_from: dict[int, str] = field(default_factory=dict)
    odom_topic: str | None = None
    base_frame: str = "base_link"
    unindexed: ScanReport | None = None

    def summary(self) -> str:
        parts = [f"{self.tof} tof ({self.no_echo} no echo) from {len(self.sensors)} sensors",
                 f"{self.odom} odom" + (f" from {self.odom_topic}" if self.odom_topic else "")]
        if self.truth:
            parts.append(f"{self.truth} truth")
        if self.skipped_too_close or self.skipped_invalid:
            parts.append(f"skipped {self.skipped_too_close} too close, "
                         f"{self.skipped_invalid} invalid ranges")
        if self.late:
            parts.append(f"dropped {self.late} records later than the reorder window")
        if self.unmapped:
            parts.append("unmapped Range sources: " + ", ".join(
                f"{k} ({v})" for k, v in sorted(self.unmapped.items())))
        if self.unindexed is not None:
            parts.append(self.unindexed.summary())
        return "; ".join(parts)


def _stamp_s(msg: Any) -> float:
    st = msg.header.stamp
    return float(st.sec) + float(st.nanosec) * 1e-9


def is_active_bag(bag: Path) -> bool:
    """True for ``NAME.bag.active``: the file ``rosbag record`` writes until it stops cleanly."""
    return bag.name.endswith(".bag.active") and bag.is_file()


#: rosbags' messages (rosbags 0.11) for a ROS 1 bag the sequential reader can still read:
#: never indexed (index_pos 0), or an index that points past a cut end
UNINDEXED_ERRORS = ("Bag is not indexed", "Bag index looks damaged")


@contextmanager
def _open_reader(bag: Path) -> Iterator[Any]:
    """An open bag reader: rosbags' AnyReader, or the sequential reader of an unindexed
    ROS 1 bag (``.bag.active``, or a ``.bag`` rosbags reports as not indexed)."""
    rb = _rosbags()
    if not bag.exists():
        raise RosbagError(f"bag {bag} does not exist")
    if is_active_bag(bag):
        reader: Any = _open_unindexed(bag)
    else:
        store = typestore(1 if bag.suffix == ".bag" else 2)
        try:
            reader = rb.highlevel.AnyReader([bag], default_typestore=store)
        except Exception as err:  # rosbags raises its own error classes
            raise RosbagError(f"cannot open bag {bag}: {_first_line(err)}") from err
        try:
            reader.open()
        except Exception as err:
            if not (bag.suffix == ".bag" and str(err).startswith(UNINDEXED_ERRORS)):
                raise
            reader = _open_unindexed(bag)
    try:
        yield reader
    finally:
        reader.close()


def _open_unindexed(bag: Path) -> UnindexedBag1Reader:
    reader = UnindexedBag1Reader(bag, default_typestore=typestore(1))
    try:
        reader.open()
    except BagScanError as err:
        raise RosbagError(f"bag {bag}: {err}") from err
    return reader


def _first_line(err: BaseException) -> str:
    """The first line of an error's message (rosbags quotes whole YAML parser reports)."""
    lines = str(err).strip().splitlines()
    return lines[0] if lines else type(err).__name__


def _static_transforms(reader: Any, conns: list[Any]) -> dict[str, tuple[str, tuple[float, ...]]]:
    """child frame -> (parent frame, planar pose of child in parent) from /tf_static."""
    out: dict[str, tuple[str, tuple[float, ...]]] = {}
    if not conns:  # an empty selection means "all connections" to rosbags
        return out
    for conn, _, raw in reader.messages(connections=conns):
        msg = reader.deserialize(raw, conn.msgtype)
        for tf in msg.transforms:
            t, q = tf.transform.translation, tf.transform.rotation
            out[tf.child_frame_id.lstrip("/")] = (
                tf.header.frame_id.lstrip("/"),
                (float(t.x), float(t.y), yaw_from_quaternion(q.x, q.y, q.z, q.w)))
    return out


def _mount_from_tf(frame: str, base: str, tfs: dict[str, tuple[str, tuple[float, ...]]]
                   ) -> tuple[float, float, float] | None:
    pose = (0.0, 0.0, 0.0)
    seen = set()
    frame = frame.lstrip("/")
    while frame != base:
        if frame in seen or frame not in tfs:
            return None
        seen.add(frame)
        parent, p = tfs[frame]
        x, y, yaw = (float(v) for v in se2.compose(p[:3], pose))
        pose = (x, y, yaw)
        frame = parent
    yaw_deg = math.degrees(pose[2])
    return (pose[0], pose[1], yaw_deg + 360.0 if yaw_deg <= -180.0 else yaw_deg)  # (-180, 180]


def _pick_topic(conns: list[Any], types: Sequence[str], wanted: str | None, what: str
                ) -> str | None:
    have = sorted({c.topic for c in conns if c.msgtype in types})
    if wanted is not None:
        if wanted not in have:
            raise RosbagError(f"no {what} topic {wanted!r} in the bag (have: "
                              f"{', '.join(have) or 'none'})")
        return wanted
    if len(have) > 1:
        raise RosbagError(f"several {what} topics ({', '.join(have)}): choose one with "
                          f"--{what}-topic")
    return have[0] if have else None


def import_bag(
    bag: str | Path,
    out: str | Path | IO[str],
    *,
    sensors: Sequence[RangeSource] = (),
    rig: RigRecord | None = None,
    rig_names: Sequence[RangeSource] = (),
    odom_topic: str | None = None,
    truth_topic: str | None = None,
    base_frame: str | None = None,
    speed_of_sound_mps: float | None = None,
    stamp: Literal["header", "bag"] = "header",
    init: InitRecord | None = None,
    reorder_window_s: float = 1.0,
) -> ImportStats:
    """Convert a ROS 1 or ROS 2 bag into a log JSONL (FORMATS.md section 4).

    Parameters
    ----------
    bag : a ``.bag`` file (ROS 1) or a ROS 2 bag directory.
    out : path or text stream for the log.
    sensors : Range sources (topic or frame_id -> sensor id, optional mount pose). When
        empty and ``rig`` names none, every Range source gets an id in natural order of
        its topic (or frame_id when one topic carries several).
    rig : mount poses (and speed of sound) by sensor id, e.g. from :func:`load_rig_json`.
    rig_names : Range sources named in the rig JSON (its ``topic``/``frame_id`` keys).
    odom_topic : ``nav_msgs/msg/Odometry`` topic; None picks the only one (error if several).
    truth_topic : optional ground-truth pose topic (Odometry, PoseStamped or
        PoseWithCovarianceStamped) written as ``truth`` records.
    base_frame : frame of the mount poses; default the odometry's ``child_frame_id``
        or ``base_link``.
    speed_of_sound_mps : the speed the driver used to turn TOF into range (default: the
        rig's, else 343.0).
    stamp : ``"header"`` (message header stamps, default) or ``"bag"`` (receive times).
    init : optional prior written as an ``init`` record.
    reorder_window_s : records are sorted within this window of bag time; later ones are
        dropped and counted in ``late``.
    """
    bag = Path(bag)
    if reorder_window_s < 0 or not math.isfinite(reorder_window_s):
        raise ValueError(f"`reorder_window_s` must be >= 0, got {reorder_window_s!r}")
    if stamp not in ("header", "bag"):
        raise ValueError(f"`stamp` must be 'header' or 'bag', got {stamp!r}")
    c = speed_of_sound_mps if speed_of_sound_mps is not None else (
        rig.speed_of_sound_mps if rig is not None else 343.0)
    c = check_air_speed_of_sound(c, "`speed_of_sound_mps`")   # (the log's rig record)
    stats = ImportStats()
    try:
        with _open_reader(bag) as reader:
            if isinstance(reader, UnindexedBag1Reader):
                stats.unindexed = reader.report
            conns = list(reader.connections)
            range_conns = [x for x in conns if x.msgtype == RANGE_TYPE]
            if not range_conns:
                raise RosbagError(f"no {RANGE_TYPE} topics in {bag} (topics: "
                                  f"{', '.join(sorted({x.topic for x in conns})) or 'none'})")
            odom_topic = _pick_topic(conns, (ODOM_TYPE,), odom_topic, "odom")
            stats.odom_topic = odom_topic
            if truth_topic is not None:
                _pick_topic(conns, POSE_TYPES, truth_topic, "truth")
            odom_conns = [x for x in conns if x.topic == odom_topic]
            truth_conns = [x for x in conns if x.topic == truth_topic]
            tf_conns = [x for x in conns if x.topic == "/tf_static" and x.msgtype == TF_TYPE]

            # pass 1: Range sources, base frame, static transforms
            keys: Counter[tuple[str, str]] = Counter()
            for conn, _, raw in reader.messages(connections=range_conns):
                msg = reader.deserialize(raw, conn.msgtype)
                keys[(conn.topic, msg.header.frame_id.lstrip("/"))] += 1
            if base_frame is None and odom_conns:
                for conn, _, raw in reader.messages(connections=odom_conns):
                    child = reader.deserialize(raw, conn.msgtype).child_frame_id.lstrip("/")
                    base_frame = child or None
                    break
            base_frame = base_frame or "base_link"
            stats.base_frame = base_frame
            tfs = _static_transforms(reader, tf_conns)

            key_to_id = _assign_ids(keys, sensors, rig_names)
            mounts = _resolve_mounts(key_to_id, sensors, rig, base_frame, tfs, stats)
            rig_out = RigRecord(tuple(mounts[i] for i in sorted(mounts)), c, 0.0)

            def records() -> Iterator[tuple[float, float, Record]]:
                """(bag time, stamp, record) in bag order."""
                wanted = range_conns + odom_conns + truth_conns
                for conn, t_ns, raw in reader.messages(connections=wanted):
                    msg = reader.deserialize(raw, conn.msgtype)
                    t_bag = t_ns * 1e-9
                    t = t_bag if stamp == "bag" else _stamp_s(msg)
                    rec = _convert(conn, msg, t, key_to_id, c, stats, odom_topic)
                    if rec is not None:
                        yield t_bag, t, rec

            with LogWriter(out) as writer:
                writer.write(rig_out)
                if init is not None:
                    writer.write(init)
                for rec in _reorder(records(), reorder_window_s, stats):
                    writer.write(rec)
    except RosbagError:
        raise
    except SonarlocError:
        raise
    except Exception as err:
        if type(err).__module__.startswith("rosbags"):
            raise RosbagError(f"bag {bag}: {_first_line(err)}") from err
        raise
    return stats


def _assign_ids(keys: Counter[tuple[str, str]], sensors: Sequence[RangeSource],
                rig_names: Sequence[RangeSource]) -> dict[tuple[str, str], int]:
    """Sensor id of each (topic, frame_id) key; named sources first, else natural order."""
    named = list(sensors) + list(rig_names)
    out: dict[tuple[str, str], int] = {}
    if named:
        for key in keys:
            for src in named:
                if src.name in (key[0], key[1], "/" + key[1]):
                    out[key] = src.sensor
                    break
        return out
    topics = sorted({k[0] for k in keys}, key=_natural_key)
    multi = any(len({k[1] for k in keys if k[0] == t}) > 1 for t in topics)
    ordered = sorted(keys, key=lambda k: (_natural_key(k[0]), _natural_key(k[1])))
    if multi:
        for i, key in enumerate(ordered):
            out[key] = i
    else:
        for i, t in enumerate(topics):
            for key in ordered:
                if key[0] == t:
                    out[key] = i
    return out


def _resolve_mounts(key_to_id: dict[tuple[str, str], int], sensors: Sequence[RangeSource],
                    rig: RigRecord | None, base: str,
                    tfs: dict[str, tuple[str, tuple[float, ...]]], stats: ImportStats
                    ) -> dict[int, SensorMount]:
    by_spec: dict[int, tuple[float, float, float]] = {
        s.sensor: s.mount for s in sensors if s.mount is not None}
    by_rig = {m.id: m for m in rig.sensors} if rig is not None else {}
    mounts: dict[int, SensorMount] = {}
    for (topic, frame), sid in sorted(key_to_id.items(), key=lambda kv: kv[1]):
        label = f"topic {topic}, frame {frame or '(empty)'}"
        stats.sensors.setdefault(sid, label)
        if sid in mounts:
            continue
        if sid in by_spec:
            mounts[sid] = SensorMount(sid, *by_spec[sid])
            stats.mount_from[sid] = "command line"
        elif sid in by_rig:
            mounts[sid] = by_rig[sid]
            stats.mount_from[sid] = "rig"
        elif frame and (tf_pose := _mount_from_tf(frame, base, tfs)) is not None:
            mounts[sid] = SensorMount(sid, *tf_pose)
            stats.mount_from[sid] = "/tf_static"
        else:
            raise RosbagError(
                f"no mount pose for sensor {sid} ({label}): give --sensor "
                f"{topic}={sid}@X,Y,YAW_DEG, a rig JSON, or a /tf_static chain from "
                f"{frame or 'its frame'} to {base}")
    if not mounts:
        raise RosbagError("no Range source matched the given --sensor names")
    return mounts


def _convert(conn: Any, msg: Any, t: float, key_to_id: dict[tuple[str, str], int], c: float,
             stats: ImportStats, odom_topic: str | None) -> Record | None:
    if conn.msgtype == RANGE_TYPE:
        key = (conn.topic, msg.header.frame_id.lstrip("/"))
        sid = key_to_id.get(key)
        if sid is None:
            stats.unmapped[f"{key[0]}:{key[1]}"] += 1
            return None
        r = float(msg.range)
        lo, hi = float(msg.min_range), float(msg.max_range)
        limits = hi > 0 and hi > lo
        if math.isnan(r) or (r == -math.inf):
            if r == -math.inf:
                stats.skipped_too_close += 1
            else:
                stats.skipped_invalid += 1
            return None
        if r == math.inf or (limits and r >= hi):
            stats.tof += 1
            stats.no_echo += 1
            return TofRecord(t, sid, None)
        if limits and r < lo:
            stats.skipped_too_close += 1
            return None
        if r <= 0:
            stats.skipped_invalid += 1
            return None
        stats.tof += 1
        return TofRecord(t, sid, 2.0 * r / c * 1e6)
    pose = msg.pose.pose if hasattr(msg.pose, "pose") else msg.pose
    p, q = pose.position, pose.orientation
    yaw_deg = math.degrees(yaw_from_quaternion(q.x, q.y, q.z, q.w))
    if conn.topic == odom_topic:
        stats.odom += 1
        return OdomRecord(t, float(p.x), float(p.y), yaw_deg)
    stats.truth += 1
    return TruthRecord(t, float(p.x), float(p.y), yaw_deg)


def _reorder(items: Iterable[tuple[float, float, Record]], window_s: float, stats: ImportStats
             ) -> Iterator[Record]:
    """Sort records by stamp within a window of bag time (bounded memory)."""
    heap: list[tuple[float, int, Record]] = []
    counter = itertools.count()
    last = -math.inf
    for t_bag, t, rec in items:
        if t < last:
            stats.late += 1
            if isinstance(rec, TofRecord):
                stats.tof -= 1
                stats.no_echo -= rec.tof_us is None
            elif isinstance(rec, OdomRecord):
                stats.odom -= 1
            else:
                stats.truth -= 1
            continue
        heapq.heappush(heap, (t, next(counter), rec))
        while heap and heap[0][0] < t_bag - window_s:
            last, _, out = heapq.heappop(heap)
            yield out
    while heap:
        last, _, out = heapq.heappop(heap)
        yield out


# --------------------------------------------------------------------------- export

@dataclass
class ExportStats:
    poses: int = 0
    transforms: int = 0
    no_odom: int = 0
    ros_version: int = 2

    def summary(self) -> str:
        text = (f"{self.poses} poses, {self.transforms} map->odom transforms "
                f"(ROS {self.ros_version})")
        if self.no_odom:
            text += f"; {self.no_odom} poses outside the odometry's time span had no transform"
        return text


def odometry_from_log(log: str | Path) -> NDArray[np.float64]:
    """(n, 4) array (t_s, x_m, y_m, yaw_rad) of the ``odom`` records of a log."""
    rows = [(r.t_s, r.x_m, r.y_m, math.radians(r.yaw_deg))
            for r in iter_log(log) if isinstance(r, OdomRecord)]
    return np.array(rows, dtype=float).reshape(-1, 4)


def interpolate_poses(track: NDArray[np.float64], t_s: NDArray[np.float64],
                      tolerance_s: float = 1e-3) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Poses of ``track`` ((n, 4): t_s, x_m, y_m, yaw_rad) at times ``t_s`` (m,).

    Linear in x, y and the unwrapped yaw. Returns ((m, 3) poses, (m,) mask of times
    inside the track's span, widened by ``tolerance_s``).
    """
    t = np.asarray(t_s, dtype=float)
    if len(track) == 0:
        return np.full((len(t), 3), np.nan), np.zeros(len(t), bool)
    yaw = np.unwrap(track[:, 3])
    out = np.stack([np.interp(t, track[:, 0], track[:, 1]),
                    np.interp(t, track[:, 0], track[:, 2]),
                    np.interp(t, track[:, 0], yaw)], axis=-1)
    inside = (t >= track[0, 0] - tolerance_s) & (t <= track[-1, 0] + tolerance_s)
    return out, inside


def _quat(ts: Any, yaw: float) -> Any:
    return ts.types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=math.sin(yaw / 2),
                                                   w=math.cos(yaw / 2))


def _header(ts: Any, t_s: float, frame: str, seq: int) -> Any:
    ns = int(round(t_s * 1e9))
    stamp = ts.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000,
                                                    nanosec=ns % 1_000_000_000)
    kwargs: dict[str, Any] = {"stamp": stamp, "frame_id": frame}
    if any(name == "seq" for name, _ in ts.fielddefs["std_msgs/msg/Header"][1]):
        kwargs["seq"] = seq
    return ts.types["std_msgs/msg/Header"](**kwargs)


def pose_covariance_6x6(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """ROS row-major 6x6 covariance (x, y, z, roll, pitch, yaw) of planar (x, y, yaw) ones.

    ``cov``: (..., 3, 3) → (..., 36). z, roll and pitch are left at zero (planar robot).
    """
    c = np.asarray(cov, dtype=float)
    out = np.zeros((*c.shape[:-2], 6, 6))
    idx = [0, 1, 5]
    for i, a in enumerate(idx):
        for j, b in enumerate(idx):
            out[..., a, b] = c[..., i, j]
    return out.reshape(*c.shape[:-2], 36)


def export_poses(
    poses: PoseTrack,
    out: str | Path,
    *,
    odometry: NDArray[np.float64] | None = None,
    ros_version: Literal[1, 2] | None = None,
    pose_topic: str = "/sonarloc/pose",
    tf_topic: str = "/tf",
    map_frame: str = "map",
    odom_frame: str = "odom",
    storage: Literal["sqlite3", "mcap"] = "sqlite3",
) -> ExportStats:
    """Write poses (and the ``map -> odom`` transform) into a new bag.

    Parameters
    ----------
    poses : estimates of ``base_link`` in ``map`` (e.g. from ``read_poses_csv``).
    out : new ``.bag`` file (ROS 1) or ROS 2 bag directory; must not exist.
    odometry : (n, 4) (t_s, x_m, y_m, yaw_rad) odometry of ``base_link`` in ``odom``
        (e.g. :func:`odometry_from_log`); with it, each pose also gets a TFMessage with
        ``map -> odom`` = pose ⊕ odometry⁻¹ at the pose's time.
    ros_version : 1 or 2; default from the suffix of ``out`` (``.bag`` → 1).
    """
    rb = _rosbags()
    out = Path(out)
    if out.exists():
        raise RosbagError(f"{out} exists already; not overwriting")
    version = ros_version if ros_version is not None else (1 if out.suffix == ".bag" else 2)
    if version not in (1, 2):
        raise ValueError(f"`ros_version` must be 1 or 2, got {ros_version!r}")
    if storage not in ("sqlite3", "mcap"):
        raise ValueError(f"`storage` must be 'sqlite3' or 'mcap', got {storage!r}")
    ts = typestore(version)
    stats = ExportStats(ros_version=version)
    tf_poses, inside = (interpolate_poses(odometry, poses.t_s) if odometry is not None
                        else (None, np.zeros(len(poses), bool)))
    tf_all = (map_to_odom(np.stack([poses.x_m, poses.y_m, poses.yaw_rad], -1), tf_poses)
              if tf_poses is not None else None)
    cov36 = pose_covariance_6x6(np.nan_to_num(poses.cov, nan=0.0))
    T = ts.types
    if version == 1:
        writer: Any = rb.rosbag1.Writer(out)
    else:
        plugin = (rb.rosbag2.StoragePlugin.MCAP if storage == "mcap"
                  else rb.rosbag2.StoragePlugin.SQLITE3)
        writer = rb.rosbag2.Writer(out, version=9, storage_plugin=plugin)
    serialize = ts.serialize_ros1 if version == 1 else ts.serialize_cdr
    with writer:
        pose_conn = writer.add_connection(pose_topic, "geometry_msgs/msg/PoseWithCovarianceStamped",
                                          typestore=ts)
        tf_conn = (writer.add_connection(tf_topic, TF_TYPE, typestore=ts)
                   if tf_all is not None else None)
        for i in range(len(poses)):
            t = float(poses.t_s[i])
            ns = int(round(t * 1e9))
            pose = T["geometry_msgs/msg/Pose"](
                position=T["geometry_msgs/msg/Point"](x=float(poses.x_m[i]),
                                                      y=float(poses.y_m[i]), z=0.0),
                orientation=_quat(ts, float(poses.yaw_rad[i])))
            msg = T["geometry_msgs/msg/PoseWithCovarianceStamped"](
                header=_header(ts, t, map_frame, i),
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=cov36[i]))
            writer.write(pose_conn, ns, serialize(msg, msg.__msgtype__))
            stats.poses += 1
            if tf_all is None or tf_conn is None:
                continue
            if not inside[i]:
                stats.no_odom += 1
                continue
            tx, ty, th = (float(v) for v in tf_all[i])
            tf = T["geometry_msgs/msg/TransformStamped"](
                header=_header(ts, t, map_frame, i), child_frame_id=odom_frame,
                transform=T["geometry_msgs/msg/Transform"](
                    translation=T["geometry_msgs/msg/Vector3"](x=tx, y=ty, z=0.0),
                    rotation=_quat(ts, th)))
            tfmsg = T[TF_TYPE](transforms=[tf])
            writer.write(tf_conn, ns, serialize(tfmsg, TF_TYPE))
            stats.transforms += 1
    return stats


def read_messages(bag: str | Path, topics: Sequence[str] | None = None
                  ) -> Iterator[tuple[str, int, Any]]:
    """(topic, bag time in ns, deserialized message) of a bag, in time order."""
    with _open_reader(Path(bag)) as reader:
        conns = [c for c in reader.connections if topics is None or c.topic in topics]
        if not conns:
            return
        for conn, t_ns, raw in reader.messages(connections=conns):
            yield conn.topic, t_ns, reader.deserialize(raw, conn.msgtype)

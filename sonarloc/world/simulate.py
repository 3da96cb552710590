"""Simulated logs: a robot with a sonar rig in a mapped world, as a stream of records.

:func:`simulate_records` yields the records of the log format (FORMATS.md section 4)
in non-decreasing time: ``rig`` first, ``init`` (a prior of ``base_link`` in ``map``,
drawn around the true start pose), then interleaved ``odom`` + ``truth`` (at
``odom_hz``) and ``tof`` records (as the rig fires; with ``pan_deg`` for a pan rig).
It streams: nothing is precomputed, so it can drive a simulated device for as long
as needed. Everything random comes from ``seed`` through independent streams (sonar,
odometry, prior), so e.g. changing the odometry model does not change the echoes.

Per ping, the callback ``on_ping`` receives a :class:`PingTruth` with what the log
does not say: the transducer's true pose in ``map`` and in ``odom``, which reflector
won and which model tier produced its echo. :func:`simulate_scan` collects these
into a scan (FORMATS.md section 1) with transducer poses in the map frame.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from shapely.geometry import LineString

from sonarloc.io.logfile import (
    InitRecord,
    OdomRecord,
    Record,
    RigRecord,
    TofRecord,
    TruthRecord,
)
from sonarloc.io.scancsv import ScanReadings
from sonarloc.maps.geojson import Map
from sonarloc.physics.tiers import Tier
from sonarloc.physics.tof import ModuleParams
from sonarloc.world.rig import PanRig, Rig, slot_range_m
from sonarloc.world.robot import DriveParams, OdometryModel, Pose2, Robot, Route
from sonarloc.world.scene import Scene


@dataclass(frozen=True)
class PingTruth:
    """Simulator-side detail of one ping (never written to the log).

    Poses are of the transducer (mount and pan applied): ``x_m, y_m, yaw_rad`` true, in
    ``map``; ``odom_*`` as odometry believes, in ``odom``. ``tof_us`` NaN = no echo;
    ``tier`` the :class:`~sonarloc.physics.tiers.Tier` code of the winning echo and
    ``reflector`` its index in ``Map.reflectors`` (-1 both when no echo).
    """

    t_s: float
    sensor: int
    pan_deg: float | None
    x_m: float
    y_m: float
    yaw_rad: float
    odom_x_m: float
    odom_y_m: float
    odom_yaw_rad: float
    tof_us: float
    tier: int
    reflector: int


def module_for_rig(rig: Rig, params: ModuleParams = ModuleParams()) -> ModuleParams:
    """The module with the rig's range gate (a ring slot limits the range it can wait for)."""
    if rig.range_gate_m is not None:
        gate = rig.range_gate_m
    elif isinstance(rig, PanRig):
        gate = slot_range_m(rig.ping_period_s, params.c_mps)
    else:
        gate = slot_range_m(rig.slot_s, params.c_mps)
    return replace(params, max_range_m=min(params.max_range_m, gate))


def default_duration_s(rig: Rig, driving: bool, route: Route | None = None,
                       drive: DriveParams = DriveParams()) -> float:
    """One pan sweep (pan rig standing still), 10 s (ring standing still), one route lap."""
    if driving and route is not None:
        return route.length / drive.speed_mps
    if isinstance(rig, PanRig):
        return rig.sweep_s
    return 10.0


def _check_pose(at: tuple[float, float, float]) -> Pose2:
    if len(at) != 3 or not all(math.isfinite(float(v)) for v in at):
        raise ValueError(f"`at` must be three finite numbers X, Y, YAW_DEG, got {at!r}")
    return Pose2(float(at[0]), float(at[1]), math.radians(float(at[2])))


def simulate_records(
    world_map: Map,
    rig: Rig,
    *,
    duration_s: float | None = None,
    at: tuple[float, float, float] | None = None,
    route: LineString | None = None,
    tier: Tier | str = Tier.AUTO,
    seed: int = 0,
    params: ModuleParams = ModuleParams(),
    odom_hz: float = 20.0,
    drive: DriveParams = DriveParams(),
    odometry: OdometryModel = OdometryModel(),
    init_sd_xy_m: float = 0.05,
    init_sd_yaw_deg: float = 2.0,
    on_ping: Callable[[PingTruth], None] | None = None,
) -> Iterator[Record]:
    """Yield a simulated log, record by record, in non-decreasing ``t_s``.

    Parameters
    ----------
    world_map : the world.
    rig : the sonar rig (:mod:`sonarloc.world.rig`).
    duration_s : simulated time; default :func:`default_duration_s`.
    at : (x_m, y_m, yaw_deg) to keep the robot still there; otherwise it drives
        ``route`` (default: the map's default route) from its first point.
    tier : physics tier (``gauss``, ``piston``, ``waveform``, ``auto``).
    seed : seeds every random stream.
    params : ranging module (the rig's range gate is applied on top).
    odom_hz : rate of ``odom`` and ``truth`` records.
    drive, odometry : robot motion and odometry error models.
    init_sd_xy_m, init_sd_yaw_deg : SD of the ``init`` prior around the true start.
    on_ping : called with a :class:`PingTruth` per ping, just before its record.

    Raises
    ------
    ValueError
        naming the argument, e.g. no ``at`` and no route.
    """
    tier = Tier.parse(tier)
    if not (math.isfinite(odom_hz) and odom_hz > 0):
        raise ValueError(f"`odom_hz` must be positive, got {odom_hz!r}")
    for name, v in (("init_sd_xy_m", init_sd_xy_m), ("init_sd_yaw_deg", init_sd_yaw_deg)):
        if not (math.isfinite(v) and v >= 0):
            raise ValueError(f"`{name}` must be non-negative, got {v!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"`seed` must be a non-negative integer, got {seed!r}")
    sonar_ss, odom_ss, init_ss = np.random.SeedSequence(int(seed)).spawn(3)
    sonar_rng = np.random.default_rng(sonar_ss)

    path: Route | None = None
    if at is not None:
        robot = Robot(_check_pose(at), None, drive, odometry, np.random.default_rng(odom_ss))
    else:
        line = route if route is not None else world_map.route
        if line is None:
            raise ValueError("the map has no default route (a LineString with kind "
                             "\"route\"); give `at` X,Y,YAW_DEG to keep the robot still")
        path = Route(line)
        robot = Robot.at_route_start(path, drive=drive, odometry=odometry,
                                     rng=np.random.default_rng(odom_ss))
    if duration_s is None:
        duration_s = default_duration_s(rig, at is None, path, drive)
    if not (math.isfinite(duration_s) and duration_s >= 0):
        raise ValueError(f"`duration_s` must be a non-negative number, got {duration_s!r}")

    module = module_for_rig(rig, params)
    scene = Scene(world_map, module)
    mounts = {m.id: m for m in rig.sensors}
    yield RigRecord(tuple(rig.sensors), module.c_mps, 0.0)

    init_rng = np.random.default_rng(init_ss)
    t0 = robot.truth
    ex, ey = init_rng.normal(0.0, init_sd_xy_m, 2) if init_sd_xy_m > 0 else (0.0, 0.0)
    eyaw = float(init_rng.normal(0.0, init_sd_yaw_deg)) if init_sd_yaw_deg > 0 else 0.0
    prior = Pose2(t0.x + float(ex), t0.y + float(ey), t0.yaw + math.radians(eyaw))
    yield InitRecord(0.0, _r(prior.x), _r(prior.y), _r(prior.yaw_deg), init_sd_xy_m,
                     init_sd_yaw_deg)

    firings = rig.firings()
    next_fire = next(firings)
    k_odom = 0
    while True:
        t_odom = round(k_odom / odom_hz, 9)
        t_fire = next_fire[0]
        odom_due = t_odom <= duration_s + 1e-9
        fire_due = t_fire < duration_s - 1e-9
        if not odom_due and not fire_due:
            return
        if odom_due and (not fire_due or t_odom <= t_fire):
            robot.advance_to(t_odom)
            o, tr = robot.odom, robot.truth
            yield OdomRecord(t_odom, _r(o.x), _r(o.y), _r(o.yaw_deg))
            yield TruthRecord(t_odom, _r(tr.x), _r(tr.y), _r(tr.yaw_deg))
            k_odom += 1
            continue
        robot.advance_to(t_fire)
        shots = next_fire[1]
        poses, odom_poses = [], []
        for sid, pan in shots:
            m = mounts[sid]
            rel = math.radians(m.yaw_deg + (pan or 0.0))
            poses.append(robot.truth.compose(m.x_m, m.y_m, rel))
            odom_poses.append(robot.odom.compose(m.x_m, m.y_m, rel))
        res = scene.ping(np.array([p.x for p in poses]), np.array([p.y for p in poses]),
                         np.array([p.yaw for p in poses]), sonar_rng, tier)
        for j, (sid, pan) in enumerate(shots):
            tof = float(res.tof_us[j])
            if on_ping is not None:
                p, q = poses[j], odom_poses[j]
                on_ping(PingTruth(t_fire, sid, pan, p.x, p.y, p.yaw, q.x, q.y, q.yaw, tof,
                                  int(res.tier[j]), int(res.reflector[j])))
            yield TofRecord(t_fire, sid, None if math.isnan(tof) else tof, pan)
        next_fire = next(firings)


def _r(v: float) -> float:
    """Round a logged number to 1e-6 (micrometres, microdegrees)."""
    return round(float(v), 6)


@dataclass(frozen=True)
class SimulatedScan:
    """A simulated scan and what produced each reading.

    ``readings`` holds the transducer poses in ``map`` (or ``odom``, see
    :func:`simulate_scan`); ``tier``/``reflector`` (n,) are the winning echo's tier code
    and reflector index (-1 = no echo).
    """

    readings: ScanReadings
    tier: NDArray[np.int8]
    reflector: NDArray[np.int64]


def scan_from_pings(pings: list[PingTruth], frame: str = "map") -> SimulatedScan:
    """Collect :class:`PingTruth` items into a scan with poses in ``map`` or ``odom``."""
    if frame not in ("map", "odom"):
        raise ValueError(f"`frame` must be 'map' or 'odom', got {frame!r}")
    n = len(pings)
    t = np.fromiter((p.t_s for p in pings), float, n)
    if frame == "map":
        x = np.fromiter((p.x_m for p in pings), float, n)
        y = np.fromiter((p.y_m for p in pings), float, n)
        yaw = np.fromiter((p.yaw_rad for p in pings), float, n)
    else:
        x = np.fromiter((p.odom_x_m for p in pings), float, n)
        y = np.fromiter((p.odom_y_m for p in pings), float, n)
        yaw = np.fromiter((p.odom_yaw_rad for p in pings), float, n)
    yaw = np.arctan2(np.sin(yaw), np.cos(yaw))
    tof = np.fromiter((p.tof_us for p in pings), float, n)
    sensor = np.fromiter((p.sensor for p in pings), np.int64, n)
    tier = np.fromiter((p.tier for p in pings), np.int8, n)
    refl = np.fromiter((p.reflector for p in pings), np.int64, n)
    return SimulatedScan(ScanReadings(t, x, y, yaw, tof, sensor), tier, refl)


def simulate_scan(world_map: Map, rig: Rig, *, frame: str = "map",
                  **kwargs: object) -> SimulatedScan:
    """Run :func:`simulate_records` to the end and return its pings as a scan.

    Keyword arguments are those of :func:`simulate_records` (except ``on_ping``).
    ``frame`` chooses the transducer poses: ``map`` (truth) or ``odom`` (odometry).
    """
    if frame not in ("map", "odom"):
        raise ValueError(f"`frame` must be 'map' or 'odom', got {frame!r}")
    pings: list[PingTruth] = []
    for _ in simulate_records(world_map, rig, on_ping=pings.append, **kwargs):  # type: ignore[arg-type]
        pass
    return scan_from_pings(pings, frame)

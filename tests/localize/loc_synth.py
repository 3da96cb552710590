"""A synthetic drive for Localizer tests: odometry and fitted-landmark-like observations
generated from a known truth, independent of the simulator and the fitter."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from hypothesis import strategies as st

from sonarloc import se2
from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import (
    InitRecord,
    OdomRecord,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
)
from sonarloc.localize.ekf import OdomNoise
from sonarloc.localize.features import FeatureMap

ROOM = np.array([[[0, 0], [8, 0]], [[8, 0], [8, 5]], [[8, 5], [0, 5]], [[0, 5], [0, 0]]], float)
POLES = np.array([[2.5, 2.0], [5.6, 2.3], [4.5, 0.9], [6.5, 4.0]])
MOUNT = SensorMount(0, 0.2, 0.0, 0.0)


def room_map() -> FeatureMap:
    return FeatureMap.build(POLES, ROOM, point_kind=("pole",) * len(POLES))


@dataclass
class Drive:
    records: list  # rig, init, then odom/truth in time order
    truth: np.ndarray  # (n, 3) at odom times
    times: np.ndarray
    odom: np.ndarray
    landmarks: list  # (arrival index: deliver after odom record i, Landmark)


def make_drive(seed: int = 1, n: int = 400, dt: float = 0.05, delay_steps: int = 4,
               noise: OdomNoise | None = None, every: int = 2, pos_sd: float = 0.004,
               ang_sd_deg: float = 0.5, start=(2.0, 1.0, 0.3)) -> Drive:
    rng = np.random.default_rng(seed)
    noise = noise or OdomNoise(along_var_per_m=0.01**2, cross_var_per_m=0.005**2,
                               yaw_var_per_m=math.radians(1.5) ** 2,
                               yaw_var_per_rad=math.radians(1.5) ** 2)
    truth = [np.array(start, float)]
    odom = [np.zeros(3)]
    for _ in range(n - 1):
        u = np.array([0.3 * dt, 0.0, 0.25 * dt])  # circle, radius 1.2 m
        truth.append(se2.compose(truth[-1], u))
        q = noise.cov(u)
        v = rng.multivariate_normal(np.zeros(3), q)
        odom.append(se2.compose(odom[-1], u + v))
    truth_a = np.array(truth)
    odom_a = np.array(odom)
    times = np.arange(n) * dt
    init = InitRecord(0.0, start[0] + rng.normal(0, 0.03), start[1] + rng.normal(0, 0.03),
                      math.degrees(start[2] + rng.normal(0, math.radians(1))), 0.03, 1.0)
    recs: list = [RigRecord((MOUNT,), 343.0), init]
    for k in range(n):
        recs.append(OdomRecord(float(times[k]), *odom_a[k, :2], math.degrees(odom_a[k, 2])))
        recs.append(TruthRecord(float(times[k]), *truth_a[k, :2], math.degrees(truth_a[k, 2])))
    lms = []
    mount = np.array([MOUNT.x_m, MOUNT.y_m, 0.0])
    fm = room_map()
    for k in range(1, n - 1, every):
        frac = 0.5  # reference reading between odom k and k+1
        t_ref = float(times[k] + frac * dt)
        tr = se2.interpolate(truth_a[k], truth_a[k + 1], frac)
        od = se2.interpolate(odom_a[k], odom_a[k + 1], frac)
        sensor_map = se2.compose(tr, mount)
        which = (k // every) % 3
        if which < 2:
            d = np.hypot(*(POLES - sensor_map[:2]).T)
            j = int(np.argmin(d))
            p_map = POLES[j]
            p_b = se2.inverse_transform_points(tr, p_map) + rng.normal(0, pos_sd, 2)
            p_o = se2.transform_points(od, p_b)
            cov = np.diag([pos_sd**2, pos_sd**2, 0.01])
            params = np.array([p_o[0], p_o[1], 0.67 * math.exp(rng.normal(0, 0.1))])
            kind = "point"
        else:
            facing = np.flatnonzero(fm.walls_facing(sensor_map[:2]))
            dist = [abs(se2.inverse_transform_line(sensor_map, fm.wall_line[w])[0])
                    for w in facing]
            w = int(facing[int(np.argmin(dist))])
            line_b = se2.inverse_transform_line(tr, fm.wall_line[w])
            e = rng.normal(0, [pos_sd, math.radians(ang_sd_deg)])
            line_b = line_b + e
            line_o = se2.transform_line(od, line_b)
            # covariance in odom: d rho_o / d alpha_b = -x sin(a_o) + y cos(a_o)
            a_o = line_o[1]
            jr = -od[0] * math.sin(a_o) + od[1] * math.cos(a_o)
            flip = 1.0 if abs(se2.wrap_angle(line_o[1] - line_b[1] - od[2])) < 1 else -1.0
            jmat = np.array([[flip, jr], [0, 1]])
            c2 = jmat @ np.diag([pos_sd**2, math.radians(ang_sd_deg) ** 2]) @ jmat.T
            cov = np.zeros((3, 3))
            cov[:2, :2] = c2
            cov[2, 2] = 0.001
            params = np.array([line_o[0], line_o[1], 0.15])
            kind = "line"
        ref_pose = se2.compose(od, mount)
        lm = Landmark(kind, params, cov, 1.0, 0.0, 20, t_ref, tuple(ref_pose.tolist()))
        lms.append((k + 1 + delay_steps, lm))
    return Drive(recs, truth_a, times, odom_a, lms)


def feed(loc, drive: Drive, deliver=None):
    """Feed a drive; landmarks delivered after odom index (default: their arrival index)."""
    by_index: dict[int, list] = {}
    for idx, lm in drive.landmarks:
        i = idx if deliver is None else deliver(idx, lm)
        by_index.setdefault(i, []).append(lm)
    out = []
    k = -1
    for rec in drive.records:
        loc.handle(rec)
        if isinstance(rec, OdomRecord):
            k += 1
            for lm in by_index.get(k, []):
                loc.add_landmark(lm)
            out.append(loc.estimate)
    for i in sorted(i for i in by_index if i > k):  # arriving after the last odom record
        for lm in by_index[i]:
            if i < 10**9:
                loc.add_landmark(lm)
    return out


_t = st.floats(-5, 60, allow_nan=False)
_xy = st.floats(-20, 20, allow_nan=False)
_deg = st.floats(-720, 720, allow_nan=False)
log_records = st.lists(st.one_of(
    st.builds(OdomRecord, _t, _xy, _xy, _deg),
    st.builds(TofRecord, _t, st.integers(-1, 3),
              st.one_of(st.none(), st.floats(1.0, 40000.0)),
              st.one_of(st.none(), st.floats(-90, 90))),
    st.builds(InitRecord, _t, _xy, _xy, _deg, st.floats(0.001, 1.0), st.floats(0.01, 30.0)),
    st.just(RigRecord((SensorMount(0, 0.2, 0.0, 0.0), SensorMount(1, 0.0, 0.2, 90.0)))),
), max_size=60)
"""Any sequence of log records: time going backwards, unknown sensors, jumps, re-inits."""

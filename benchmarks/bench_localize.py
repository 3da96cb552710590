"""Localization: Kuc-fitted landmarks against odometry and conventional sonar EKFs.

Simulated drives (``sonarloc.world``) through the example room with a ring of 16
transducers and with a panning transducer, and through a field of poles and rods;
several seeds each. Every drive is localized in the same run by four methods fed the
same log: dead reckoning (``odometry``), the textbook sonar EKF (``conventional``: each
reading a range along the beam axis, 10 deg bearing SD, walls ray-cast along the
axis), the same reading with walls seen at normal incidence (``specular``: a stronger
baseline) and ours (``kuc``: fitted landmarks with range, bearing and strength), both
in the batch replay of ``sonarloc localize`` and fed record by record (``kuc live``).
Reported: position and yaw RMSE (whole drive and after a 5 s warm-up), average NEES
against its 95 % chi-square band, replay speed; the EKF core's peer check and step time
against FilterPy; the model-exact Monte-Carlo NEES of the core; the fit-batching
latency trade-off; the batch replay's speed against the live one; memory over long
looped replays (live and batch, 1 h by default); and map building errors.

Run: ``python benchmarks/bench_localize.py [--quick] [--soak-hours H]
[--batch-soak-hours H]``; writes
benchmarks/results/localize.md and localize.png.
"""

from __future__ import annotations

import argparse
import io
import math
import resource
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from scipy.stats import chi2  # noqa: E402

from benchmarks._machine import SHARED, machine_line  # noqa: E402
from sonarloc import se2  # noqa: E402
from sonarloc.io.logfile import (  # noqa: E402
    LogWriter,
    OdomRecord,
    Record,
    SensorMount,
    TruthRecord,
)
from sonarloc.io.posescsv import PoseTrack  # noqa: E402
from sonarloc.localize import ekf  # noqa: E402
from sonarloc.localize.ekf import Feature, Gaussian, Observation, OdomNoise  # noqa: E402
from sonarloc.localize.features import FeatureMap  # noqa: E402
from sonarloc.localize.localizer import Localizer, LocalizerConfig, SegmentFitSource  # noqa: E402
from sonarloc.localize.offline import OfflinePipeline  # noqa: E402
from sonarloc.localize.replay import Mode, replay_log  # noqa: E402
from sonarloc.maps import compare as maps_compare  # noqa: E402
from sonarloc.maps.build import build_from_log  # noqa: E402
from sonarloc.maps.geojson import Map, load_map, map_from_geojson  # noqa: E402
from sonarloc.world.rig import PanRig, Rig, ring16  # noqa: E402
from sonarloc.world.simulate import simulate_records  # noqa: E402

METHODS = ("odometry", "conventional", "specular", "kuc fit", "kuc", "kuc live")
WARMUP_S = 5.0


def pole_field() -> Map:
    """Ten poles and rods on a 9 m x 6 m field, no walls, with a loop route."""
    pts = [("pole", 1.0, 0.0), ("pole", 3.5, 0.2), ("rod", 6.0, -0.1), ("pole", 7.8, 1.5),
           ("rod", 8.2, 4.0), ("pole", 6.2, 5.8), ("rod", 3.8, 6.1), ("pole", 1.2, 5.7),
           ("rod", -0.2, 3.0), ("pole", 4.0, 3.0)]
    feats: list[dict[str, Any]] = [
        {"type": "Feature",
         "properties": {"kind": k, "id": f"{k}-{i}", "radius_m": 0.0445 if k == "pole" else 0.004},
         "geometry": {"type": "Point", "coordinates": [x, y]}} for i, (k, x, y) in enumerate(pts)]
    feats.append({"type": "Feature", "properties": {"kind": "route", "id": "loop"},
                  "geometry": {"type": "LineString", "coordinates": [
                      [1.5, 1.2], [6.5, 1.2], [6.8, 4.5], [2.0, 4.8], [1.2, 3.0], [1.5, 1.2]]}})
    return map_from_geojson({"type": "FeatureCollection", "features": feats})


def pan_rig() -> PanRig:
    """A transducer 10 cm ahead of base_link panning -90..90 deg in 1.5 deg steps, 30 ms
    per ping (5 m range gate): a full sweep every 3.6 s."""
    return PanRig(SensorMount(0, 0.1, 0.0, 0.0), (-90.0, 90.0, 1.5), 1, 0.03)


@dataclass
class Scenario:
    name: str
    world: Map
    rig: Rig


def scenarios() -> list[Scenario]:
    room = load_map(ROOT / "maps" / "room.geojson")
    return [Scenario("room, ring16", room, ring16()),
            Scenario("room, panning transducer", room, pan_rig()),
            Scenario("pole field, ring16", pole_field(), ring16())]


def simulate_text(sc: Scenario, seed: int, duration_s: float | None) -> str:
    buf = io.StringIO()
    with LogWriter(buf) as w:
        w.write_all(simulate_records(sc.world, sc.rig, duration_s=duration_s, seed=seed))
    return buf.getvalue()


@dataclass
class Run:
    t: np.ndarray
    err: np.ndarray    # (n, 3) estimate - truth (yaw wrapped)
    nees: np.ndarray   # (n,)
    wall_s: float
    log_s: float
    fused: int = 0
    observations: int = 0
    landmarks: int = 0
    readings: int = 0
    segments: int = 0
    cpu_s: float = math.nan  # CPU time of the replay (the speed measure)


def method_config(method: str) -> tuple[LocalizerConfig, Mode]:
    """``kuc live``: the kuc method fed record by record (``--online``); ``kuc fit``: kuc
    fusing the fitted landmarks instead of their readings; the others as ``sonarloc
    localize`` runs them (kuc and odometry in batches)."""
    if method == "kuc live":
        return LocalizerConfig(method="kuc"), "online"
    if method == "kuc fit":  # the fitted landmarks fused, not their readings (ablation)
        return LocalizerConfig(method="kuc", kuc_fusion="fit"), "auto"
    return LocalizerConfig(method=method), "auto"  # type: ignore[arg-type]


def localize_run(text: str, fmap: FeatureMap, truth: dict[float, np.ndarray],
                 config: LocalizerConfig, localizer: Localizer | None = None,
                 mode: Mode = "auto") -> Run:
    rows: list[tuple[float, np.ndarray, np.ndarray]] = []

    def keep(rec: OdomRecord, est: Any) -> None:
        rows.append((rec.t_s, est.state.mean, est.state.cov))

    res = replay_log(io.StringIO(text), fmap, config=config, on_estimate=keep,
                     localizer=localizer, mode=mode)
    t = np.array([r[0] for r in rows])
    mean = np.array([r[1] for r in rows])
    cov = np.array([r[2] for r in rows])
    tru = np.array([truth[x] for x in t])
    err = mean - tru
    err[:, 2] = se2.wrap_angle(err[:, 2])
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    st = res.localizer.stats
    return Run(t, err, nees, res.wall_time_s, res.log_duration_s, st.accepted,
               st.observations, st.landmarks, st.echoes_fused, st.segments, res.cpu_time_s)


@dataclass
class Summary:
    rmse_mm: float
    steady_mm: float
    yaw_deg: float
    steady_yaw_deg: float
    max_mm: float
    nees: float
    nees_inside: float
    speed: float
    fused: int
    observations: int
    landmarks: int
    readings: int = 0
    segments: int = 0


def summarize(runs: list[Run]) -> Summary:
    e = np.concatenate([r.err for r in runs])
    t = np.concatenate([r.t for r in runs])
    pos = np.hypot(e[:, 0], e[:, 1])
    steady = t > WARMUP_S
    # NEES: per time step averaged over the runs, against the 95 % band for N runs
    n_min = min(len(r.nees) for r in runs)
    n_runs = len(runs)
    avg = np.mean([r.nees[:n_min] for r in runs], axis=0)
    lo, hi = chi2.ppf(0.025, 3 * n_runs) / n_runs, chi2.ppf(0.975, 3 * n_runs) / n_runs
    inside = float(np.mean((avg >= lo) & (avg <= hi)))
    return Summary(
        1000 * math.sqrt(float(np.mean(pos**2))),
        1000 * math.sqrt(float(np.mean(pos[steady] ** 2))),
        math.degrees(math.sqrt(float(np.mean(e[:, 2] ** 2)))),
        math.degrees(math.sqrt(float(np.mean(e[steady, 2] ** 2)))),
        1000 * float(pos.max()), float(np.mean(avg)), inside,
        float(np.median([r.log_s / r.cpu_s for r in runs])),
        sum(r.fused for r in runs), sum(r.observations for r in runs),
        sum(r.landmarks for r in runs), sum(r.readings for r in runs),
        sum(r.segments for r in runs))


def truth_of(text: str) -> dict[float, np.ndarray]:
    from sonarloc.io.logfile import iter_log

    return {r.t_s: np.array([r.x_m, r.y_m, math.radians(r.yaw_deg)])
            for r in iter_log(io.StringIO(text)) if isinstance(r, TruthRecord)}


# --------------------------------------------------------------------------- EKF core


def filterpy_check(n_steps: int, repeats: int) -> dict[str, float]:
    """Largest difference to FilterPy over a predict/update sequence, and step times."""
    from filterpy.kalman import ExtendedKalmanFilter

    class PoseEKF(ExtendedKalmanFilter):  # type: ignore[misc]
        def predict_x(self, u: Any = 0) -> None:
            self.x = se2.compose(self.x[:, 0], u)[:, None]

    rng = np.random.default_rng(7)
    noise = OdomNoise()
    g0 = Gaussian.from_pose(1.0, 0.5, 0.3, 0.05, math.radians(3))
    feat = Feature("point", [3.0, 1.0], 0.04)
    sensor = np.array([0.2, 0.0, 0.3])
    steps = []
    truth = g0.mean.copy()
    for _ in range(n_steps):
        u = np.array([0.02, 0.0, 0.01]) + rng.normal(0, [0.002, 0.001, 0.005])
        truth = se2.compose(truth, u)
        cov = np.array([[1e-4, 2e-5], [2e-5, 3e-4]])
        z = ekf.point_in_base(truth, feat.params, 0.04, sensor)[0] + \
            rng.multivariate_normal([0, 0], cov)
        steps.append((u, Observation("point", z, cov, sensor)))

    def ours() -> Gaussian:
        s = g0
        for u, obs in steps:
            s = ekf.predict(s, u, noise)
            s, _ = ekf.update(s, obs, feat, gate_probability=None)
        return s

    def theirs() -> PoseEKF:
        f = PoseEKF(dim_x=3, dim_z=2)
        f.x = g0.mean.copy()[:, None]
        f.P = g0.cov.copy()
        for u, obs in steps:
            fj, gj = se2.compose_jacobians(f.x[:, 0], u)
            f.F, f.Q = fj, gj @ noise.cov(u) @ gj.T
            f.predict(u=u)
            f.update(obs.z[:, None],
                     lambda x, o=obs: ekf.measure(x[:, 0], o, feat)[1],
                     lambda x, o=obs: ekf.measure(x[:, 0], o, feat)[0][:, None], R=obs.cov)
        return f

    a, b = ours(), theirs()
    diff_x = float(np.max(np.abs(a.mean - b.x[:, 0])))
    diff_p = float(np.max(np.abs(a.cov - b.P)))
    t_ours = min(_timed(ours) for _ in range(repeats)) / n_steps
    t_theirs = min(_timed(theirs) for _ in range(repeats)) / n_steps
    # the same steps for a batch of 1000 filters at once, per filter-step
    batch = 1000
    gb = Gaussian(np.tile(g0.mean, (batch, 1)), np.tile(g0.cov, (batch, 1, 1)))
    ub = [(np.tile(u, (batch, 1)), Observation("point", np.tile(o.z, (batch, 1)), o.cov, sensor))
          for u, o in steps[:100]]

    def batched() -> None:
        s = gb
        for u, obs in ub:
            s = ekf.predict(s, u, noise)
            s, _ = ekf.update(s, obs, feat, gate_probability=None)

    t_batch = min(_timed(batched) for _ in range(repeats)) / (100 * batch)
    return {"diff_x": diff_x, "diff_p": diff_p, "ours_us": 1e6 * t_ours,
            "filterpy_us": 1e6 * t_theirs, "batched_us": 1e6 * t_batch}


def _timed(fn: Any) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def core_nees(n_runs: int, n_steps: int) -> tuple[float, float, tuple[float, float]]:
    """Model-exact Monte-Carlo of the core (circle drive, point and wall observations)."""
    rng = np.random.default_rng(11)
    noise = OdomNoise(along_var_per_m=0.02**2, cross_var_per_m=0.01**2,
                      yaw_var_per_m=math.radians(2) ** 2, yaw_var_per_rad=math.radians(2) ** 2)
    points = np.array([[3.0, 0.0], [0.0, 3.0], [-3.0, 0.0], [0.0, -3.0], [2.0, 2.0]])
    walls = np.array([[4.0, 0.0], [4.0, math.pi / 2], [4.0, math.pi], [4.0, -math.pi / 2]])
    truth = np.tile([1.0, 0.0, math.pi / 2], (n_runs, 1))
    g = Gaussian.from_pose(truth[:, 0], truth[:, 1], truth[:, 2], 0.05, math.radians(2))
    truth = truth + rng.normal(0, 1, truth.shape) * [0.05, 0.05, math.radians(2)]
    out = np.zeros((n_steps, n_runs))
    u_true = np.array([0.05, 0.0, 0.05])
    for k in range(n_steps):
        q = noise.cov(np.broadcast_to(u_true, (n_runs, 3)))
        v = np.einsum("nij,nj->ni", np.linalg.cholesky(q), rng.normal(0, 1, (n_runs, 3)))
        truth = se2.compose(truth, u_true)
        g = ekf.predict(g, u_true + v, increment_cov=q)
        if k % 2:
            feat = Feature("point", points[k % 5])
            cov = np.diag([0.02**2, 0.01**2])
            z = ekf.point_in_base(truth, feat.params)[0]
            kind = "point"
        else:
            feat = Feature("wall", walls[k % 4])
            cov = np.diag([0.01**2, math.radians(3) ** 2])
            z = ekf.wall_in_base(truth, feat.params)[0]
            kind = "line"
        z = z + rng.multivariate_normal([0, 0], cov, n_runs)
        g, _ = ekf.update(g, Observation(kind, z, cov), feat, gate_probability=None)  # type: ignore[arg-type]
        out[k] = ekf.nees(g, truth)
    avg = out.mean(axis=1)
    lo, hi = chi2.ppf(0.025, 3 * n_runs) / n_runs, chi2.ppf(0.975, 3 * n_runs) / n_runs
    return float(avg.mean()), float(np.mean((avg >= lo) & (avg <= hi))), (lo, hi)


# --------------------------------------------------------------------------- soak


def lap_geometry(records: list[Record]) -> tuple[float, np.ndarray]:
    """Lap duration and the odometry pose of the next lap's start in the lap's odom frame.

    The lap ends where the robot happens to be, not exactly at its start; the looped
    stream makes the robot jump back (the readings repeat the first lap's), and the
    odometry says so: it continues by the true relative pose of that jump.
    """
    odoms = [r for r in records if isinstance(r, OdomRecord)]
    truths = [r for r in records if isinstance(r, TruthRecord)]
    lap_s = odoms[-1].t_s + (odoms[-1].t_s - odoms[-2].t_s)

    def pose(r: OdomRecord | TruthRecord) -> np.ndarray:
        return np.array([r.x_m, r.y_m, math.radians(r.yaw_deg)])

    jump = se2.between(pose(truths[-1]), pose(truths[0]))
    return lap_s, se2.compose(se2.between(pose(odoms[0]), pose(odoms[-1])), jump)


def looped(records: list[Record], hours: float) -> Iterator[Record]:
    """The lap's records over and over for ``hours`` of log time (truth left out),
    odometry continuing across the jump back to the lap's start."""
    odoms = [r for r in records if isinstance(r, OdomRecord)]
    lap_s, lap_inc = lap_geometry(records)
    first = np.array([odoms[0].x_m, odoms[0].y_m, math.radians(odoms[0].yaw_deg)])
    base = np.zeros(3)
    lap = 0
    while lap * lap_s < hours * 3600:
        for r in records:
            if lap and r.type in ("rig", "init"):
                continue
            if isinstance(r, TruthRecord):
                continue
            if isinstance(r, OdomRecord):
                p = se2.compose(base, se2.between(first, [r.x_m, r.y_m,
                                                          math.radians(r.yaw_deg)]))
                yield OdomRecord(r.t_s + lap * lap_s, float(p[0]), float(p[1]),
                                 math.degrees(float(p[2])))
            else:
                yield type(r)(**{**r.__dict__, "t_s": r.t_s + lap * lap_s})  # type: ignore[arg-type]
        base = se2.compose(base, lap_inc)
        lap += 1


def rss_mb() -> float:
    """Current resident set size [MB] (Linux /proc)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
        return pages * resource.getpagesize() / 1e6
    except OSError:  # pragma: no cover - not Linux
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3


def soak(text: str, fmap: FeatureMap, hours: float, every_s: float
         ) -> tuple[list[tuple[float, float, int]], float, float, str]:
    """Replay a looped drive; (log hours, RSS MB, history entries) samples, wall, log time,
    final status."""
    from sonarloc.io.logfile import iter_log

    records = list(iter_log(io.StringIO(text)))
    loc = Localizer(fmap, LocalizerConfig())
    samples: list[tuple[float, float, int]] = []
    next_t = 0.0
    t0 = time.perf_counter()
    last_t = 0.0
    for rec in looped(records, hours):
        loc.handle(rec)
        last_t = rec.t_s
        if rec.t_s >= next_t and isinstance(rec, OdomRecord):
            samples.append((rec.t_s / 3600, rss_mb(), loc.history_len))
            next_t += every_s
    loc.finish()
    samples.append((last_t / 3600, rss_mb(), loc.history_len))
    status = loc.estimate.status if loc.estimate is not None else "none"
    return samples, time.perf_counter() - t0, last_t, status


def batch_soak(text: str, fmap: FeatureMap, hours: float, every_s: float
               ) -> tuple[list[tuple[float, float, int, int]], float, float, float, str]:
    """The whole kuc pipeline in batch mode (segmenter, batched reading-level fusion on time,
    history) on a looped drive for ``hours`` of log time, records handed straight to the
    :class:`OfflinePipeline` (no log text). Returns (log hours, RSS MB, history entries,
    records buffered by the pipeline) samples, wall time, log time, the position RMSE
    of the last lap [mm] and the final status."""
    from sonarloc.io.logfile import InitRecord, RigRecord, TofRecord, iter_log

    records = list(iter_log(io.StringIO(text)))
    lap_s, _ = lap_geometry(records)
    truth = {r.t_s: (r.x_m, r.y_m) for r in records if isinstance(r, TruthRecord)}
    total_laps = math.ceil(hours * 3600 / lap_s)
    last_lap_t = (total_laps - 1) * lap_s
    errs: list[float] = []

    def keep(rec: OdomRecord, est: Any) -> None:
        if rec.t_s >= last_lap_t:
            tx, ty = truth[round(rec.t_s - last_lap_t, 9)]
            errs.append(math.hypot(est.x_m - tx, est.y_m - ty))

    loc = Localizer(fmap, LocalizerConfig())
    pipe = OfflinePipeline(loc, keep)

    def buffered() -> int:
        seg = pipe._source.segmenter.open_segments if pipe._source is not None else 0
        return (len(pipe._odom) + len(pipe._rows) + len(pipe._tof_t) + len(pipe._waiting)
                + len(pipe._landmarks) + len(pipe._segs) + len(pipe._track_t) + seg)

    samples: list[tuple[float, float, int, int]] = []
    next_t = 0.0
    last_t = 0.0
    t0 = time.perf_counter()
    for rec in looped(records, hours):
        last_t = rec.t_s
        if isinstance(rec, OdomRecord):
            pipe.odom(rec)
            if rec.t_s >= next_t:
                samples.append((rec.t_s / 3600, rss_mb(), loc.history_len, buffered()))
                next_t += every_s
        elif isinstance(rec, TofRecord):
            pipe.tof(rec)
        elif isinstance(rec, (RigRecord, InitRecord)):
            pipe.finish()
            loc.handle(rec)
    pipe.finish()
    samples.append((last_t / 3600, rss_mb(), loc.history_len, buffered()))
    rmse = 1000 * math.sqrt(float(np.mean(np.square(errs)))) if errs else math.nan
    status = pipe.last.status if pipe.last is not None else "none"
    return samples, time.perf_counter() - t0, last_t, rmse, status


# --------------------------------------------------------------------------- map building


@dataclass
class MapErrors:
    poses: str
    found: str
    pole_mm: float
    rod_mm: float
    corner_mm: float
    wall_mm: float
    extra: int
    kinds: str = ""
    details: list[float] = field(default_factory=list)


def observable_points(true: FeatureMap, poses: np.ndarray, max_range_m: float = 5.0
                      ) -> np.ndarray:
    """(P,) true points that can echo towards some pose (N, 3) of the drive: a corner
    only from inside its walls' angle, an edge only from outside and near (the reflex
    vertex of the L-shaped room has no corner a robot inside could see)."""
    seen = np.zeros(true.n_points, dtype=bool)
    for xy in poses[::10, :2]:
        seen |= true.points_visible_from(xy, max_range_m)
    return seen


def map_errors(built: Map, true: Map, label: str, poses: np.ndarray) -> MapErrors:
    b = FeatureMap.from_map(built)
    t = FeatureMap.from_map(true)
    seen = observable_points(t, poses)
    errs: dict[str, list[float]] = {"pole": [], "rod": [], "corner": []}
    found = 0
    for i, k in enumerate(t.point_kind):
        if k not in errs or b.n_points == 0 or not seen[i]:
            continue
        d = float(np.min(np.hypot(*(b.point_xy - t.point_xy[i]).T)))
        if d < 0.1:
            errs[k].append(d)
            found += 1
    # kind labels: a built point is labelled right if a true point of that kind is
    # within 2 cm (a vertex carries both a corner and an edge: either side may be seen)
    right = sum(any(np.hypot(*(t.point_xy[j] - p)) < 0.02 and t.point_kind[j] == k
                    for j in range(t.n_points)) for p, k in zip(b.point_xy, b.point_kind,
                                                                 strict=True))
    wall_err = []
    for ends in b.wall_ends:
        best = math.inf
        for a, c in t.wall_ends:
            dvec = c - a
            nrm = np.array([-dvec[1], dvec[0]]) / np.hypot(*dvec)
            best = min(best, max(abs(float((p - a) @ nrm)) for p in ends))
        wall_err.append(best)
    good_walls = sum(e < 0.02 for e in wall_err)
    extra = sum(e >= 0.02 for e in wall_err) + sum(
        float(np.min(np.hypot(*(t.point_xy - p).T))) >= 0.02 for p in b.point_xy)
    n_true = sum(k in errs and bool(s) for k, s in zip(t.point_kind, seen, strict=True))

    def worst(v: list[float]) -> float:
        return 1000 * max(v) if v else math.nan

    return MapErrors(label, f"{found}/{n_true} points, {good_walls} walls", worst(errs["pole"]),
                     worst(errs["rod"]), worst(errs["corner"]),
                     1000 * max((e for e in wall_err if e < 0.02), default=math.nan), extra,
                     f"{right}/{b.n_points}")


def map_building(seed: int, duration_s: float) -> list[MapErrors]:
    room = load_map(ROOT / "maps" / "room.geojson")
    sc = Scenario("room", room, ring16())
    text = simulate_text(sc, seed, duration_s)
    truth = truth_of(text)
    t = np.array(sorted(truth))
    tr = np.array([truth[x] for x in t])
    out = []
    track = PoseTrack(t, tr[:, 0], tr[:, 1], tr[:, 2], np.zeros((len(t), 3, 3)))
    out.append(map_errors(map_from_geojson(build_from_log(io.StringIO(text), track).geojson()),
                          room, "truth", tr))
    # poses from our localizer against the true map (localize, then map)
    rows: list[tuple[float, np.ndarray, np.ndarray]] = []
    replay_log(io.StringIO(text), FeatureMap.from_map(room),
               on_estimate=lambda r, e: rows.append((r.t_s, e.state.mean, e.state.cov)))
    lt = PoseTrack(np.array([r[0] for r in rows]), np.array([r[1][0] for r in rows]),
                   np.array([r[1][1] for r in rows]), np.array([r[1][2] for r in rows]),
                   np.array([r[2] for r in rows]))
    out.append(map_errors(map_from_geojson(build_from_log(io.StringIO(text), lt).geojson()),
                          room, "sonarloc localize (kuc)", tr))
    out.append(map_errors(map_from_geojson(build_from_log(io.StringIO(text),
                                                          method="odometry").geojson()),
                          room, "odometry only", tr))
    slam = build_from_log(io.StringIO(text), method="slam")
    out.append(map_errors(map_from_geojson(slam.geojson()), room, "odometry + SLAM (no poses)",
                          tr))
    # its frame is the init pose's (5 cm, 2 deg SD): the same map moved onto the truth
    feats = slam.builder.features()
    mv = maps_compare.moved(feats, maps_compare.rigid_alignment(feats, room, 1.5))
    aligned = {"type": "FeatureCollection",
               "features": [f.geojson(f"{f.kind}-{i}") for i, f in enumerate(mv)]}
    out.append(map_errors(map_from_geojson(aligned), room,
                          "odometry + SLAM, rigidly aligned to the truth", tr))
    return out


# --------------------------------------------------------------------------- relocalization


def symmetric_room() -> Map:
    """A 6 m x 4 m room with two poles placed point-symmetrically about its centre (a
    half turn maps it onto itself) and a symmetric route."""
    feats: list[dict[str, Any]] = [
        {"type": "Feature", "properties": {"kind": "wall", "id": "room"},
         "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [6, 0], [6, 4], [0, 4],
                                                          [0, 0]]]}},
        {"type": "Feature", "properties": {"kind": "pole", "id": "p1", "radius_m": 0.0445},
         "geometry": {"type": "Point", "coordinates": [1.5, 1.2]}},
        {"type": "Feature", "properties": {"kind": "pole", "id": "p2", "radius_m": 0.0445},
         "geometry": {"type": "Point", "coordinates": [4.5, 2.8]}},
        {"type": "Feature", "properties": {"kind": "route", "id": "loop"},
         "geometry": {"type": "LineString", "coordinates": [[1, 2], [3, 0.8], [5, 2], [3, 3.2],
                                                            [1, 2]]}}]
    return map_from_geojson({"type": "FeatureCollection", "features": feats})


def _records(text: str) -> list[Record]:
    from sonarloc.io.logfile import iter_log
    return list(iter_log(io.StringIO(text)))


def kidnap_records(records: list[Record], t_k: float, jump: np.ndarray) -> list[Record]:
    """The robot carried off at ``t_k``: from then on the odometry is off by ``jump``
    (composed at the kidnap pose) against the truth."""
    out: list[Record] = []
    ref = None
    for r in records:
        if isinstance(r, OdomRecord) and r.t_s >= t_k:
            p = np.array([r.x_m, r.y_m, math.radians(r.yaw_deg)])
            if ref is None:
                ref = p
            q = se2.compose(se2.compose(ref, jump), se2.between(ref, p))
            r = OdomRecord(r.t_s, float(q[0]), float(q[1]), math.degrees(float(q[2])))
        out.append(r)
    return out


@dataclass
class RelocTrial:
    kind: str
    fixes: int = 0
    wrong: int = 0            # fixes more than 10 cm from the truth
    ambiguous: int = 0
    attempts: int = 0
    t_first_fix: float = math.nan   # after the kidnap / the start
    t_recovered: float = math.nan   # from then on within 2 cm
    err_fix_mm: float = math.nan
    final_mm: float = math.nan
    solve_s: list[float] = field(default_factory=list)


def reloc_trial(records: list[Record], fmap: FeatureMap, t0: float, kind: str) -> RelocTrial:
    from sonarloc.io.logfile import InitRecord
    from sonarloc.localize import relocalize as rl

    # the kidnap is an odometry jump against the truth (kidnap_records), which jump
    # detection would step over as an odometry reset: off, explicitly, to test the
    # relocalization
    loc = Localizer(fmap, LocalizerConfig(relocalize=True, odom_max_speed_mps=math.inf,
                                          odom_max_yaw_rate_rad_s=math.inf))
    truth = {r.t_s: r for r in records if isinstance(r, TruthRecord)}
    tr = RelocTrial(kind)
    assert loc._reloc is not None
    reloc = loc._reloc
    orig = reloc.solve

    def timed(t_s: float) -> rl.Relocalization:
        a = time.perf_counter()
        out = orig(t_s)
        tr.solve_s.append(time.perf_counter() - a)
        return out

    reloc.solve = timed  # type: ignore[method-assign]
    errs: list[tuple[float, float]] = []
    fixes_seen = 0
    for r in records:
        if kind == "no prior" and isinstance(r, InitRecord):
            continue
        est = loc.handle(r)
        if est is None or not isinstance(r, OdomRecord):
            continue
        t = truth[r.t_s]
        e = math.hypot(est.x_m - t.x_m, est.y_m - t.y_m)
        errs.append((r.t_s, e))
        found = loc.stats.relocalization["found"]
        if found > fixes_seen and r.t_s >= t0:
            fixes_seen = found
            tr.fixes += 1
            tr.wrong += e > 0.1
            if math.isnan(tr.t_first_fix):
                tr.t_first_fix = r.t_s - t0
                tr.err_fix_mm = 1000 * e
    loc.finish()
    tr.ambiguous = loc.stats.relocalization["ambiguous"]
    tr.attempts = sum(loc.stats.relocalization.values())
    after = [(t, e) for t, e in errs if t >= t0]
    if after:
        tr.final_mm = 1000 * after[-1][1]
        bad = [t for t, e in after if e >= 0.02]
        if after[-1][1] < 0.02:
            tr.t_recovered = (max(bad) if bad else after[0][0]) - t0
    return tr


def relocalization(n_seeds: int, duration_s: float) -> dict[str, list[RelocTrial]]:
    room = load_map(ROOT / "maps" / "room.geojson")
    fmap = FeatureMap.from_map(room)
    jumps = [(0.0, 0.0, 60.0), (1.0, -0.5, 0.0), (-0.8, 0.6, -90.0), (0.5, 0.5, 180.0),
             (0.0, 1.2, 30.0)]
    out: dict[str, list[RelocTrial]] = {"kidnapped (room)": [], "no prior (room)": [],
                                        "no prior (symmetric room)": []}
    sym = symmetric_room()
    sym_fmap = FeatureMap.from_map(sym)
    for k in range(n_seeds):
        recs = _records(simulate_text(Scenario("room", room, ring16()), 300 + k, duration_s))
        j = jumps[k % len(jumps)]
        t_k = 20.0
        out["kidnapped (room)"].append(reloc_trial(
            kidnap_records(recs, t_k, np.array([j[0], j[1], math.radians(j[2])])), fmap, t_k,
            "kidnapped"))
        out["no prior (room)"].append(reloc_trial(recs, fmap, 0.0, "no prior"))
        srecs = _records(simulate_text(Scenario("sym", sym, ring16()), 400 + k, duration_s))
        out["no prior (symmetric room)"].append(reloc_trial(srecs, sym_fmap, 0.0, "no prior"))
        print(f"relocalization seed {k}: " + ", ".join(
            f"{name}: fixes {v[-1].fixes} wrong {v[-1].wrong} amb {v[-1].ambiguous} "
            f"t_fix {v[-1].t_first_fix:.1f} s final {v[-1].final_mm:.1f} mm"
            for name, v in out.items()), file=sys.stderr)
    return out


def reloc_lines(reloc: dict[str, list[RelocTrial]], n_seeds: int, duration_s: float
                ) -> list[str]:
    lines = [f"## Global relocalization ({n_seeds} drives per case, ring16, {duration_s:g} s)",
             "", "`LocalizerConfig(relocalize=True)` (`sonarloc localize --relocalize`). "
             "*kidnapped*: at 20 s the odometry jumps against the truth (60 deg turn; 1.1 m; "
             "1 m and -90 deg; 0.7 m and 180 deg; 1.2 m and 30 deg, one per drive), as if the "
             "robot were carried off; *no prior*: the log's `init` record removed. *fix*: the "
             "filter restarted at a relocalization; *wrong*: a fix more than 10 cm from the "
             "truth; *recovered*: from then on within 2 cm of the truth to the end of the "
             "drive (time after the kidnap / start); *ambiguous*: attempts that found several "
             "poses about as likely and refused to pick one. The symmetric room (6 m x 4 m, "
             "two poles point-symmetric about the centre) is ambiguous by construction: the "
             "right answer there is no fix.", "",
             "| case | recovered | fixes (wrong) | first fix after (s, median) | error at "
             "first fix (mm, median) | recovered after (s, median / max) | final error (mm, "
             "max) | attempts: ambiguous / all | solve time (ms, median) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, trials in reloc.items():
        rec = [t for t in trials if math.isfinite(t.t_recovered)]
        fixes = sum(t.fixes for t in trials)
        wrong = sum(t.wrong for t in trials)

        def med(v: list[float]) -> str:
            v = [x for x in v if math.isfinite(x)]
            return f"{float(np.median(v)):.1f}" if v else "-"

        rec_t = [t.t_recovered for t in rec]
        finals = [t.final_mm for t in trials if math.isfinite(t.final_mm)]
        solve = [x for t in trials for x in t.solve_s]
        lines.append(
            f"| {name} | {len(rec)}/{len(trials)} | {fixes} ({wrong}) | "
            f"{med([t.t_first_fix for t in trials])} | {med([t.err_fix_mm for t in trials])} | "
            f"{med(rec_t)} / {(f'{max(rec_t):.1f}' if rec_t else '-')} | "
            f"{_fmt(max(finals, default=math.nan))} | "
            f"{sum(t.ambiguous for t in trials)} / {sum(t.attempts for t in trials)} | "
            f"{1000 * float(np.median(solve)) if solve else math.nan:.0f} |")
    return lines


def _fmt(v: float) -> str:
    return f"{v:.1f}" if math.isfinite(v) else "-"


def mapping_lines(mapping: list[MapErrors]) -> list[str]:
    lines = ["## Map building (room, ring16, 3 laps, seed 200)", "",
             "`sonarloc map build` on the simulated log, with poses from the truth, from "
             "`sonarloc localize` (kuc, against the true map), from odometry alone "
             "(`--method odometry`) and from the odometry corrected by SLAM (the default "
             "without poses; its map frame is the init record's, 5 cm / 2 deg off the "
             "true one: also shown moved by its best rigid alignment onto the truth). "
             "*found*: built points within 10 cm of the true poles/rods/corners that the "
             "drive can see (a corner only from inside its walls' angle: the L's reflex "
             "vertex has none), and built walls lying on a true wall (both ends < 2 cm "
             "from its line). Worst centre error of the points found, worst end-to-line "
             "distance of those walls; *extra*: built features more than 2 cm from any "
             "true one (ghosts); *kinds right*: built points with a true point of the same "
             "kind within 2 cm.", "",
             "| poses | found | worst pole (mm) | worst rod (mm) | worst corner (mm) | "
             "worst wall (mm) | extra | kinds right |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    for me in mapping:
        lines.append(f"| {me.poses} | {me.found} | {me.pole_mm:.1f} | {me.rod_mm:.1f} | "
                     f"{me.corner_mm:.1f} | {me.wall_mm:.1f} | {me.extra} | {me.kinds} |")
    return lines


def run_sections(args: argparse.Namespace) -> int:
    """``--sections``: run only map building and relocalization, and replace those
    sections of the existing results file (the rest stays from its full run)."""
    quick = args.quick
    n_seeds = args.seeds or (1 if quick else 5)
    lines = mapping_lines(map_building(200, 40.0 if quick else 174.0)) + [""]
    dur = 30.0 if quick else 60.0
    lines += reloc_lines(relocalization(n_seeds, dur), n_seeds, dur)
    lines += ["", machine_line("`--sections` run", f"{n_seeds} seed(s)", SHARED,
                               "solve times are indicative", quick=quick,
                               label="Map building and relocalization sections")]
    out = Path(args.out)
    old = out.read_text(encoding="utf-8") if out.exists() else ""
    cut = old.find("## Map building")
    if cut < 0:
        head, tail = old, ""
    else:
        head = old[:cut]
        machine = old.find("\nMachine:", cut)
        tail = old[machine:] if machine >= 0 else ""
        reloc_note = tail.find("\nMap building and relocalization sections:")
        if reloc_note >= 0:
            tail = tail[:reloc_note] + "\n"
    text = head + "\n".join(lines) + "\n" + tail
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    print("\n".join(lines))
    return 0


# --------------------------------------------------------------------------- report


def plot(example: dict[str, Run], summaries: dict[str, dict[str, Summary]],
         kuc_nees: tuple[np.ndarray, float, float], soak_samples: list[tuple[float, float, int]],
         path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5), dpi=110)
    ax = axes[0, 0]
    for m, r in example.items():
        ax.semilogy(r.t, np.maximum(1000 * np.hypot(r.err[:, 0], r.err[:, 1]), 1e-2), lw=0.8,
                    label=m)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("position error [mm]")
    ax.set_title("room, ring16, one drive")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[0, 1]
    names = list(summaries)
    width = 0.13
    for j, m in enumerate(METHODS):
        vals = [summaries[s][m].steady_mm for s in names]
        ax.bar(np.arange(len(names)) + (j - 0.5 * (len(METHODS) - 1)) * width, vals, width,
               label=m)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(names)))
    ax.set_xticklabels([n.replace(", ", "\n") for n in names], fontsize=8)
    ax.set_ylabel(f"position RMSE after {WARMUP_S:g} s [mm]")
    ax.axhline(20, color="k", ls=":", lw=0.8)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    ax = axes[1, 0]
    avg, lo, hi = kuc_nees
    ax.plot(np.arange(len(avg)) * 0.05, avg, lw=0.8, label="kuc: NEES averaged over seeds")
    ax.axhspan(lo, hi, color="g", alpha=0.15, label="95 % band")
    ax.axhline(3, color="k", lw=0.6)
    ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("NEES (3 dof)")
    ax.set_title("room, ring16: consistency")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax = axes[1, 1]
    if soak_samples:
        h = [s[0] for s in soak_samples]
        ax.plot(h, [s[1] for s in soak_samples], "o-", ms=3, label="RSS [MB]")
        ax2 = ax.twinx()
        ax2.plot(h, [s[2] for s in soak_samples], "s--", ms=3, color="C1",
                 label="history entries")
        ax2.set_ylabel("history entries")
        ax.set_ylim(0, max(s[1] for s in soak_samples) * 1.3)
        ax2.set_ylim(0, max(s[2] for s in soak_samples) * 1.3 + 1)
    ax.set_xlabel("log time [h]")
    ax.set_ylabel("resident memory [MB]")
    ax.set_title("long looped replay (kuc)")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="short drives, one seed (smoke run)")
    ap.add_argument("--seeds", type=int, default=None, help="drives per scenario (default 5)")
    ap.add_argument("--soak-hours", type=float, default=None,
                    help="log hours of the looped memory replay (default 1, quick 0.02)")
    ap.add_argument("--batch-soak-hours", type=float, default=None,
                    help="log hours of the batch-mode full-pipeline replay (default 1, "
                         "quick 0.05; 24 for the day-long memory check)")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "localize.md"))
    ap.add_argument("--sections", action="store_true",
                    help="run only map building and relocalization and replace those "
                         "sections of the existing results file")
    args = ap.parse_args(argv)
    if args.sections:
        return run_sections(args)
    quick = args.quick
    n_seeds = args.seeds or (1 if quick else 5)
    duration = 20.0 if quick else None  # None: one lap of the route
    soak_hours = args.soak_hours if args.soak_hours is not None else (0.02 if quick else 1.0)
    batch_hours = args.batch_soak_hours if args.batch_soak_hours is not None else \
        (0.05 if quick else 1.0)
    ekf.chi2_gate(2)  # import scipy.stats outside the timings

    summaries: dict[str, dict[str, Summary]] = {}
    speedup: dict[str, float] = {}
    example: dict[str, Run] = {}
    kuc_nees = (np.zeros(1), 0.0, 0.0)
    for sc in scenarios():
        fmap = FeatureMap.from_map(sc.world)
        runs: dict[str, list[Run]] = {m: [] for m in METHODS}
        for seed in range(n_seeds):
            text = simulate_text(sc, 100 + seed, duration)
            truth = truth_of(text)
            if seed == 0:  # untimed: the physics and delay tables built (speeds are warm)
                replay_log(io.StringIO(text), fmap, config=LocalizerConfig(method="kuc"))
            for m in METHODS:
                cfg, mode = method_config(m)
                runs[m].append(localize_run(text, fmap, truth, cfg, mode=mode))
            print(f"{sc.name} seed {seed}: " + ", ".join(
                f"{m} {1000 * math.sqrt(np.mean(np.sum(runs[m][-1].err[:, :2] ** 2, 1))):.1f} mm"
                for m in METHODS), file=sys.stderr)
        summaries[sc.name] = {m: summarize(runs[m]) for m in METHODS}
        speedup[sc.name] = float(np.median([a.cpu_s / b.cpu_s for a, b in
                                            zip(runs["kuc live"], runs["kuc"], strict=True)]))
        if sc.name == "room, ring16":
            example = {m: runs[m][0] for m in METHODS}
            n_min = min(len(r.nees) for r in runs["kuc"])
            avg = np.mean([r.nees[:n_min] for r in runs["kuc"]], axis=0)
            kuc_nees = (avg, chi2.ppf(0.025, 3 * n_seeds) / n_seeds,
                        chi2.ppf(0.975, 3 * n_seeds) / n_seeds)

    # fit batching: latency against speed (room, ring16, first seed)
    room_sc = scenarios()[0]
    room_text = simulate_text(room_sc, 100, duration)
    room_truth = truth_of(room_text)
    room_fmap = FeatureMap.from_map(room_sc.world)
    batching = []
    for batch, wait in ((1, 0.0), (4, 0.25), (16, 1.0), (64, 4.0)):
        loc = Localizer(room_fmap, LocalizerConfig(),
                        landmark_source=lambda c, b=batch, w=wait: SegmentFitSource(c, b, w, 8))
        r = localize_run(room_text, room_fmap, room_truth, LocalizerConfig(), loc)
        batching.append((batch, wait, summarize([r])))

    peer = filterpy_check(200 if quick else 1000, 3 if quick else 7)
    core = core_nees(50 if quick else 500, 200 if quick else 1000)
    samples, soak_wall, soak_log, soak_status = soak(room_text, room_fmap, soak_hours,
                                                     60.0 if quick else 300.0)
    b_every = 120.0 if quick else min(3600.0, max(300.0, batch_hours * 300.0))
    bsamples, b_wall, b_log, b_rmse, b_status = batch_soak(room_text, room_fmap, batch_hours,
                                                           b_every)
    mapping = map_building(200, 40.0 if quick else 174.0)
    reloc_s = 30.0 if quick else 60.0
    reloc = relocalization(n_seeds, reloc_s)

    lines = ["# Localization: Kuc landmarks vs odometry and conventional sonar EKFs", ""]
    lines += [
        f"{n_seeds} simulated drive(s) per scenario ({'20 s' if quick else 'one lap of the route'}"
        ", seeds 100..), each localized by every method from the same log in the same run. "
        "*odometry*: dead reckoning from the init prior; *conventional*: each reading a range "
        "along the beam axis with a 10 deg bearing SD, walls ray-cast along the axis; "
        "*specular*: that reading with walls predicted at normal incidence (a stronger, "
        "geometry-aware baseline); *kuc*: segments associated with the map and each "
        "segment's readings fused through Kuc's forward model (time of flight = "
        "range + the module's threshold delay off axis, odometry error inside the segment in "
        "the covariance; `kuc_fusion=\"echoes\"`), at the segment's reference time (*kuc*: "
        "the batch replay of `sonarloc localize`: segments associated by their readings, "
        "not fitted, linearised many at a time at the beliefs the odometry predicts "
        "(`sonarloc.localize.batchfuse`); *kuc live*: the same Localizer fed record by "
        "record, each segment fitted (`sonarloc.fit`), associated by its fit, else by its "
        "readings, and fused when its fit completes; *kuc fit*: the batch replay fitting "
        "the segments and fusing the fitted landmarks themselves, with 2 mm / 0.2 deg "
        "floors, as before reading-level fusion). RMSE over all odom steps of all "
        f"drives; *steady* after a {WARMUP_S:g} s warm-up (the prior is off by ~5 cm / 2 deg). "
        "NEES: per time step averaged over the drives; *in band* = fraction of steps inside "
        "the 95 % chi-square band for that many drives. Speed: log time / CPU time of the "
        "replay (the process's own time: other jobs on a shared machine do not count), "
        "median over drives (same process, same machine; warm: the physics tables and "
        "the delay table of the forward model built before, by an untimed kuc replay of "
        "the scenario's first drive).", "",
        "| scenario | method | RMSE (mm) | steady RMSE (mm) | yaw RMSE (deg) | steady yaw "
        "(deg) | max (mm) | avg NEES | NEES in band | fused / observations | replay speed |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, by in summaries.items():
        for m in METHODS:
            s = by[m]
            obs = f"{s.fused} / {s.observations}" if m != "odometry" else "-"
            if m.startswith("kuc"):
                what = f"{s.landmarks} fits" if s.landmarks else f"{s.segments} segments"
                obs += f" ({what}" + (f", {s.readings} readings)" if s.readings else ")")
            lines.append(f"| {name} | {m} | {s.rmse_mm:.1f} | {s.steady_mm:.1f} | "
                         f"{s.yaw_deg:.2f} | {s.steady_yaw_deg:.2f} | {s.max_mm:.0f} | "
                         f"{s.nees:.2f} | {100 * s.nees_inside:.0f} % | {obs} | "
                         f"{s.speed:.0f}x |")
    lines += ["", "Error of the other methods relative to *kuc* (steady position RMSE; > 1 "
              "means kuc is better):", "",
              "| scenario | odometry / kuc | conventional / kuc | specular / kuc | kuc fit / "
              "kuc | yaw: conventional / kuc |",
              "|---|---:|---:|---:|---:|---:|"]
    for name, by in summaries.items():
        k = by["kuc"].steady_mm
        lines.append(f"| {name} | {by['odometry'].steady_mm / k:.1f} | "
                     f"{by['conventional'].steady_mm / k:.2f} | "
                     f"{by['specular'].steady_mm / k:.2f} | "
                     f"{by['kuc fit'].steady_mm / k:.2f} | "
                     f"{by['conventional'].steady_yaw_deg / by['kuc'].steady_yaw_deg:.2f} |")
    lines += ["", "## Replay speed: batch against live (same logs, same run)", "",
              "*kuc* is `sonarloc localize` (batch replay: readings segmented in a lean "
              "loop, closed segments not fitted but associated by their readings: up to "
              "128 linearised at a time, up to 2 s of them decided at a time, at the beliefs the "
              "odometry predicts, the reduced updates applied in time order at the reference "
              "readings, odometry "
              "between updates predicted in closed form); *kuc live* feeds the same "
              "Localizer record by record (`--online`, fits of 4 segments fused when they "
              "complete, associated by the fit where it can). Both fuse the same segments' "
              "readings. Speed-up: median over the drives of live CPU time / batch CPU "
              "time.", "",
              "| scenario | kuc live | kuc (batch) | speed-up | steady RMSE live / batch "
              "(mm) | steady yaw live / batch (deg) |", "|---|---:|---:|---:|---:|---:|"]
    for name, by in summaries.items():
        lv, bt = by["kuc live"], by["kuc"]
        lines.append(f"| {name} | {lv.speed:.0f}x | {bt.speed:.0f}x | {speedup[name]:.1f}x | "
                     f"{lv.steady_mm:.1f} / {bt.steady_mm:.1f} | {lv.steady_yaw_deg:.2f} / "
                     f"{bt.steady_yaw_deg:.2f} |")
    lines += ["", "## Fit batching: latency against replay speed (room, ring16, seed 100)", "",
              "The fitter runs on batches of closed segments; a fit fused later than it could "
              "be leaves the *current* pose to dead reckoning meanwhile.", "",
              "| batch | max wait (s) | RMSE (mm) | steady RMSE (mm) | replay speed |",
              "|---:|---:|---:|---:|---:|"]
    for batch, wait, s in batching:
        lines.append(f"| {batch} | {wait:g} | {s.rmse_mm:.1f} | {s.steady_mm:.1f} | "
                     f"{s.speed:.1f}x |")
    lines += ["", "## EKF core", "",
              f"* Peer check against FilterPy's `ExtendedKalmanFilter` (same motion model "
              f"x ⊕ u, same Jacobians, Joseph form), {200 if quick else 1000} predict+update "
              f"steps: largest difference {peer['diff_x']:.1e} in the mean, "
              f"{peer['diff_p']:.1e} in the covariance.",
              f"* Time per predict+update step (best of repeats): sonarloc "
              f"{peer['ours_us']:.0f} us, FilterPy {peer['filterpy_us']:.0f} us "
              f"({peer['filterpy_us'] / peer['ours_us']:.2f}x ours); sonarloc batched over "
              f"1000 filters: {peer['batched_us']:.2f} us per filter-step.",
              f"* Model-exact Monte-Carlo ({500 if not quick else 50} runs x "
              f"{1000 if not quick else 200} steps, point and wall updates): average NEES "
              f"{core[0]:.3f}, {100 * core[1]:.0f} % of steps inside the 95 % band "
              f"[{core[2][0]:.3f}, {core[2][1]:.3f}].", ""]
    first = samples[1] if len(samples) > 2 else samples[0]
    mid = samples[len(samples) // 2]
    last = samples[-1]
    growth = (last[1] - first[1]) / max(last[0] - first[0], 1e-9)
    lines += ["## Memory over a long replay", "",
              f"The room/ring16 drive looped (odometry continued) for {soak_log / 3600:.2f} h "
              f"of log time through the kuc Localizer (segmenter, fitter, history, association "
              f"all running): {soak_wall:.0f} s wall time ({soak_log / soak_wall:.1f}x real "
              f"time). Resident memory {first[1]:.1f} MB at {60 * first[0]:.0f} min, "
              f"{mid[1]:.1f} MB at {60 * mid[0]:.0f} min, {last[1]:.1f} MB at "
              f"{60 * last[0]:.0f} min ({growth:+.2f} MB per log hour); history entries "
              f"{first[2]} / {mid[2]} / {last[2]} (bounded by `history_s`); status at the "
              f"end: {soak_status}.", ""]
    bf, bm, bl = (bsamples[1] if len(bsamples) > 2 else bsamples[0],
                  bsamples[len(bsamples) // 2], bsamples[-1])
    lines += [f"The whole pipeline in batch mode (what `sonarloc localize` runs: segmenter, "
              "reading-level fusion many segments at a time, on time, history) over "
              f"{b_log / 3600:.1f} h of the "
              "looped drive, the records handed to the `OfflinePipeline` directly (no log "
              f"text to parse): {b_wall:.0f} s wall time ({b_log / b_wall:.0f}x real time). "
              f"Resident memory {bf[1]:.1f} MB at {bf[0]:.2f} h, {bm[1]:.1f} MB at "
              f"{bm[0]:.2f} h, {bl[1]:.1f} MB at {bl[0]:.2f} h "
              f"({(bl[1] - bf[1]) / max(bl[0] - bf[0], 1e-9):+.3f} MB per hour); history "
              f"entries {bf[2]} / {bm[2]} / {bl[2]}; records held by the pipeline (odometry "
              "waiting for the batch fitter, open and waiting segments) at most "
              f"{max(x[3] for x in bsamples)}; position RMSE over the last lap "
              f"{b_rmse:.1f} mm; status at the end: {b_status}.", ""]
    lines += mapping_lines(mapping) + [""]
    lines += reloc_lines(reloc, n_seeds, reloc_s)
    lines += ["", machine_line(f"{n_seeds} seed(s)", f"soak {soak_hours:g} h",
                               f"batch soak {batch_hours:g} h", SHARED, "absolute speeds "
                               "vary from run to run; the ratios come from the same run",
                               quick=quick)]
    text = "\n".join(lines) + "\n"
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    plot(example, summaries, kuc_nees, [x[:3] for x in bsamples], out.with_suffix(".png"))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

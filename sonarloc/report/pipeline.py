"""The end-to-end drive: simulator → device protocol → driver → fit → EKF → report.

This is ``sonarloc drive`` as a library call (:func:`run_drive`). The simulated world
(:func:`sonarloc.world.simulate.simulate_records`) drives a robot along the map's route;
a simulated sonar module (:class:`sonarloc.io.drivers.sim.SimModule`) streams its
readings and odometry over a python-can virtual bus or a pseudo-terminal; the host
reads them with the same driver a robot uses (:func:`sonarloc.io.drivers.open_driver`)
and feeds a :class:`sonarloc.localize.localizer.Localizer`, whose online fitter turns
readings into landmarks and whose EKF fuses them with the odometry.

What never crosses the wire: the ``truth`` records (kept aside for the report) and the
``init`` prior (given to the Localizer directly, as an operator or a higher-level
localizer would). Everything the Localizer sees came through the device protocol.
"""

from __future__ import annotations

import itertools
import math
import os
import sysconfig
import threading
import time
from array import array
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from sonarloc.errors import DeviceTimeoutError, MapError
from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import InitRecord, OdomRecord, Record, TofRecord, TruthRecord
from sonarloc.report.drive import WARMUP_S, DriveReport, SegmentView
from sonarloc.report.metrics import track_error

Device = Literal["can", "serial"]
_channels = itertools.count()

#: Pan schedule of a panning transducer on a driving robot (start, stop, step in degrees):
#: a full turn in 3 degree steps (12 s per sweep at 0.1 s per ping). The paper's fine
#: -40..40 deg / 0.3 deg scan takes 27 s, too slow to see landmarks while driving.
DRIVE_PAN = (-180.0, 180.0, 3.0)


SHARED_MAPS = Path("share", "sonarloc", "maps")
"""Where an install that is not a checkout puts the shipped maps, under its data prefix
(pyproject.toml's ``data-files``)."""


def map_dirs() -> list[Path]:
    """Folders :func:`find_map` searches, in order: ``maps/`` next to the package (a
    checkout or an editable install), the installed maps (:data:`SHARED_MAPS` under the
    environment's and the user's data prefix: ``pip install .`` or a wheel), then
    ``maps/`` in the working directory and its parents."""
    import sonarloc

    dirs = [Path(sonarloc.__file__).resolve().parent.parent / "maps"]
    schemes = [sysconfig.get_default_scheme(), sysconfig.get_preferred_scheme("user")]
    dirs += [Path(sysconfig.get_path("data", scheme)) / SHARED_MAPS for scheme in schemes]
    cwd = Path.cwd().resolve()
    return dirs + [d / "maps" for d in (cwd, *cwd.parents)]


def find_map(name: str | Path) -> Path:
    """A map file: a path, or the name of a shipped map (``room``, ``room.geojson``) or
    of one in a ``maps/`` folder (:func:`map_dirs`)."""
    p = Path(name)
    if p.is_file():
        return p
    names = [p.name] if p.suffix else [p.name + ".geojson", p.name]
    for root in map_dirs():
        for n in names:
            if (root / n).is_file():
                return root / n
    raise MapError(f"map {str(name)!r} not found (not a file, not a shipped map, and not in a "
                   "maps/ folder above the working directory)")


@dataclass(frozen=True)
class DriveConfig:
    """Settings of :func:`run_drive` (the options of ``sonarloc drive``)."""

    map: str | Path = "room"
    rig: str = "ring16"
    device: Device = "can"
    seed: int = 0
    duration_s: float | None = None  # default: one lap of the map's route
    tier: str = "auto"
    pan_deg: tuple[float, float, float] | None = None  # pan rig schedule; default DRIVE_PAN
    method: Literal["kuc", "conventional", "odometry"] = "kuc"
    rate: float | None = None  # pacing of the simulated module; None = as fast as possible
    read_timeout_s: float = 20.0
    fit_workers: int = 0  # LocalizerConfig.fit_workers: fits off the caller's thread
    fit_executor: Literal["thread", "process"] = "thread"

    def __post_init__(self) -> None:
        if self.device not in ("can", "serial"):
            raise ValueError(f"`device` must be 'can' or 'serial', got {self.device!r}")
        if self.duration_s is not None and not (math.isfinite(self.duration_s)
                                                and self.duration_s > 0):
            raise ValueError(f"`duration_s` must be positive, got {self.duration_s!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ValueError(f"`seed` must be a non-negative integer, got {self.seed!r}")


@dataclass
class DriveResult:
    """Everything a drive produced: the report, and the data behind the figure.

    Tracks are (n, 4) arrays (t_s, x_m, y_m, yaw_rad) in ``map``; ``landmarks`` are in
    ``map`` (moved from ``odom`` with the estimate when they were fused), each paired
    with whether the Localizer matched it to the map; ``segments`` are a few fitted
    segments with their readings (``odom`` frame) for the TOF panel.
    """

    report: DriveReport
    map_path: Path
    truth: NDArray[np.float64]
    odometry: NDArray[np.float64]
    estimate: NDArray[np.float64]
    covariance: NDArray[np.float64]
    landmarks: list[tuple[Landmark, bool]] = field(default_factory=list)
    segments: list[SegmentView] = field(default_factory=list)


class _Tee:
    """Wraps the simulator's record stream: keeps ``truth`` and ``init`` aside."""

    def __init__(self, records: Iterator[Record]):
        self._records = records
        self.truth: list[tuple[float, float, float, float]] = []
        self.init: InitRecord | None = None
        self.have_init = threading.Event()
        self.error: BaseException | None = None

    def __iter__(self) -> Iterator[Record]:
        try:
            for rec in self._records:
                if isinstance(rec, TruthRecord):
                    self.truth.append((rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg)))
                elif isinstance(rec, InitRecord):
                    self.init = rec
                    self.have_init.set()
                yield rec
        except BaseException as err:  # surfaced by run_drive, not lost on the sim thread
            self.error = err
            raise
        finally:
            self.have_init.set()


class _SegmentKeeper:
    """Keeps a few fitted segments with their readings, the best of each kind (bounded)."""

    def __init__(self, per_kind: int = 6):
        self.per_kind = per_kind
        self.best: dict[str, list[tuple[float, int, SegmentView]]] = {}
        self._n = itertools.count()

    def offer(self, lm: Landmark, readings: Any) -> None:
        """Consider one fitted segment; kept if it is among the best of its kind.

        Best: trusted fits whose echoes span a wide arc of the beam (the U shows), with
        many echoes and residuals that agree with the jitter model (``rms_us`` near 1).
        """
        if not lm.ok:
            return
        from sonarloc.report.plots import landmark_model_us

        echo = np.isfinite(readings.tof_us)
        n_echo = int(echo.sum())
        if n_echo < 5:
            return
        _, theta = landmark_model_us(lm, readings.x_m[echo], readings.y_m[echo],
                                     readings.yaw_rad[echo])
        span_deg = float(np.degrees(np.ptp(theta)))
        rms = lm.rms_us if math.isfinite(lm.rms_us) else 99.0
        score = min(span_deg, 25.0) * math.sqrt(n_echo) / max(rms, 1.0) ** 2
        if lm.kind == "line":
            label = "wall"
        elif lm.kappa_us < 0.3:
            label = "strong point (corner, edge)"
        elif lm.kappa_us < 1.5:
            label = "point (pole)"
        else:
            label = "weak point (rod)"
        pool = self.best.setdefault(label, [])
        view = SegmentView(lm, np.array(readings.x_m), np.array(readings.y_m),
                           np.array(readings.yaw_rad), np.array(readings.tof_us), label)
        pool.append((-score, next(self._n), view))
        pool.sort(key=lambda e: (e[0], e[1]))
        del pool[self.per_kind:]

    ORDER = ("wall", "point (pole)", "strong point (corner, edge)", "weak point (rod)")

    def views(self) -> list[SegmentView]:
        """The kept segments, the best of each kind first, kinds in :attr:`ORDER`."""
        labels = sorted(self.best, key=lambda k: self.ORDER.index(k) if k in self.ORDER
                        else len(self.ORDER))
        return [v for k in labels for _, _, v in self.best[k]]


def _recording_source(keeper: _SegmentKeeper, max_readings: int | None) -> Callable[[float], Any]:
    """The Localizer's own landmark source, also handing each fitted segment to ``keeper``."""
    from sonarloc.localize.localizer import SegmentFitSource

    def factory(c_mps: float) -> Any:
        return SegmentFitSource(c_mps, max_readings=max_readings,
                                on_fit=lambda seg, lm: keeper.offer(lm, seg.readings))

    return factory


def run_drive(config: DriveConfig = DriveConfig(),
              progress: Callable[[float, float], None] | None = None) -> DriveResult:
    """Drive the map's route with a simulated module behind a real driver; localize.

    Parameters
    ----------
    config : what to drive (map, rig, device, seed, duration, ...).
    progress : called as ``progress(t_s, duration_s)`` while records arrive.

    Returns
    -------
    The report (errors against truth for the estimate and for odometry only,
    landmarks, compute per reading, real-time factor, device counters) and the tracks,
    landmarks and segments behind the figure. ``report.plot`` is not set here.
    """
    from sonarloc.api import LocalizerNode
    from sonarloc.io.drivers import open_driver
    from sonarloc.io.drivers.sim import SimModule
    from sonarloc.localize.features import FeatureMap
    from sonarloc.localize.localizer import NO_MOTION_REASON, LocalizerConfig
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import rig_by_name
    from sonarloc.world.robot import Route
    from sonarloc.world.simulate import default_duration_s, simulate_records

    t_start = time.perf_counter()
    map_path = find_map(config.map)
    world_map = load_map(map_path)
    from sonarloc.world.rig import PanRig

    rig = rig_by_name(config.rig)
    if isinstance(rig, PanRig) and (config.pan_deg is not None or config.rig == "pan"):
        rig = rig_by_name(config.rig, config.pan_deg or DRIVE_PAN)
    if world_map.route is None:
        raise MapError(f"map {map_path} has no route (a LineString with kind \"route\") to "
                       "drive")
    duration = config.duration_s if config.duration_s is not None else \
        default_duration_s(rig, True, Route(world_map.route))
    tee = _Tee(simulate_records(world_map, rig, duration_s=duration, seed=config.seed,
                                tier=config.tier))
    keeper = _SegmentKeeper()
    loc_config = LocalizerConfig(method=config.method, fit_workers=config.fit_workers,
                                 fit_executor=config.fit_executor)
    node = LocalizerNode(FeatureMap.from_map(world_map), config=loc_config,
                         keep_landmarks=20_000,
                         landmark_source=_recording_source(keeper,
                                                           loc_config.segment_max_readings))
    if config.device == "can":
        channel = f"sonarloc-drive-{os.getpid()}-{next(_channels)}"
        module = SimModule.on_can(tee, interface="virtual", channel=channel, rate=config.rate)
    else:
        module = SimModule.on_pty(tee, rate=config.rate)

    est_rows: list[tuple[float, float, float, float]] = []
    covs: list[NDArray[np.float64]] = []
    odom_rows: list[tuple[float, float, float, float]] = []
    n_tof = n_echo = 0
    compute = 0.0
    call_cpu = array("d")  # the calling thread's CPU seconds of each node call
    last_status = ""
    node.warm_up()  # as a robot's node would while it starts up: not in a timed call
    t_stream = time.perf_counter()
    with module, node:
        if not tee.have_init.wait(config.read_timeout_s) or tee.init is None:
            raise tee.error or DeviceTimeoutError("the simulator produced no init record")
        node.feed(tee.init)  # the prior: an operator's input, not device data
        # (no wake-up Start: this module never restarts, and once it has sent the whole
        # drive, faster than the Localizer reads it, its silence is the end, not a reset)
        with open_driver(module.url, wake_s=None) as drv:
            while True:
                try:
                    rec = drv.read(timeout=0.25)
                except DeviceTimeoutError:
                    if module.finished.is_set():
                        break  # the module is done and the wire has gone quiet
                    if time.perf_counter() - t_stream > config.read_timeout_s and \
                            not est_rows:
                        raise
                    continue
                if rec is None:
                    break
                t0, c0 = time.perf_counter(), time.thread_time()
                est = node.feed(rec)
                compute += time.perf_counter() - t0
                call_cpu.append(time.thread_time() - c0)
                if isinstance(rec, TofRecord):
                    n_tof += 1
                    n_echo += rec.tof_us is not None
                elif isinstance(rec, OdomRecord):
                    odom_rows.append((rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg)))
                    if progress is not None:
                        progress(rec.t_s, duration)
                if est is not None:
                    est_rows.append((est.t_s, est.x_m, est.y_m, est.yaw_rad))
                    covs.append(np.asarray(est.state.cov, dtype=float))
                    last_status = f"{est.status} ({est.reason})"
            t0, c0 = time.perf_counter(), time.thread_time()
            node.finish()
            compute += time.perf_counter() - t0
            call_cpu.append(time.thread_time() - c0)
            device_stats = drv.counters()
    if tee.error is not None:
        raise tee.error
    stream_s = time.perf_counter() - t_stream
    truth = np.array(tee.truth, dtype=float).reshape(-1, 4)
    est_track = np.array(est_rows, dtype=float).reshape(-1, 4)
    if len(est_track):
        est_track[:, 3] = np.unwrap(est_track[:, 3])
    odo = _odometry_in_map(np.array(odom_rows, dtype=float).reshape(-1, 4), tee.init)
    e_est, e_odo = track_error(est_track, truth), track_error(odo, truth)
    t0 = float(truth[0, 0]) if len(truth) else 0.0
    e_steady = track_error(est_track, truth, t_from_s=t0 + WARMUP_S)

    reports = node.landmarks()
    # matched but not fused again from the same place: drawn as matched
    in_map = [(r.in_map, r.fused or r.outcome == NO_MOTION_REASON) for r in reports
              if r.in_map is not None]
    st = node.stats
    skipped = st.skipped["no_motion_since_fused"]
    report = DriveReport(
        map=map_path.stem, rig=config.rig, device=config.device, seed=config.seed,
        duration_s=float(duration), readings=n_tof, echoes=n_echo, odom_records=len(odom_rows),
        pose_rmse_m=e_est.rmse_m, yaw_rmse_deg=e_est.yaw_rmse_deg, pose_max_m=e_est.max_m,
        pose_final_m=e_est.final_m, steady_pose_rmse_m=e_steady.rmse_m,
        steady_yaw_rmse_deg=e_steady.yaw_rmse_deg, odom_pose_rmse_m=e_odo.rmse_m,
        odom_yaw_rmse_deg=e_odo.yaw_rmse_deg, landmarks_fitted=st.landmarks,
        landmarks_ok=sum(1 for r in reports if r.landmark.ok),
        landmarks_matched=st.accepted,
        landmarks_rejected=st.observations - st.accepted - skipped,
        landmarks_skipped=skipped,
        readings_fused=st.echoes_fused,
        status=last_status, compute_s=compute,
        compute_per_reading_us=compute / n_tof * 1e6 if n_tof else math.nan,
        call_p99_ms=float(np.percentile(call_cpu, 99)) * 1e3 if call_cpu else math.nan,
        call_max_ms=max(call_cpu) * 1e3 if call_cpu else math.nan,
        fit_workers=config.fit_workers, fit_executor=config.fit_executor,
        fit_waits=st.fit_waits,
        wall_time_s=time.perf_counter() - t_start,
        realtime_factor=float(duration) / stream_s if stream_s > 0 else math.nan,
        device_stats={k: v for k, v in device_stats.items()
                      if v or k in ("frames", "crc_errors", "seq_gaps", "dropped")})
    if module.stats.lost:
        report.notes.append(f"{module.stats.lost} messages lost by the simulated module's "
                            "transport")
    if n_tof == 0:
        report.notes.append("no readings arrived through the device")
    return DriveResult(report, map_path, truth, odo, est_track,
                       np.array(covs).reshape(-1, 3, 3), in_map, keeper.views())


def _odometry_in_map(odom: NDArray[np.float64], init: InitRecord | None) -> NDArray[np.float64]:
    """Odometry dead-reckoned from the same prior the Localizer got (the baseline)."""
    if len(odom) == 0 or init is None:
        return odom
    from sonarloc.report.logdata import compose, inverse

    start = np.array([init.x_m, init.y_m, math.radians(init.yaw_deg)])
    T = compose(start, inverse(odom[0, 1:]))
    out = odom.copy()
    out[:, 1:] = compose(np.broadcast_to(T, (len(out), 3)), odom[:, 1:])
    out[:, 3] = np.unwrap(out[:, 3])
    return out


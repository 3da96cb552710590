"""The Localizer: a thin shell that holds the current belief and routes messages.

It takes the records of a log (or the same messages live: rig, init, odom, tof) and
reports the pose of ``base_link`` in ``map`` with its covariance, the ``map → odom``
transform (REP-105) and a status. It never reads ``truth`` records.

Two observation methods:

* ``"kuc"`` (default): every reading goes, with its transducer pose in ``odom``, to the
  fitting stage's online segmenter and fitter; each fitted landmark (point or wall, in
  ``odom``, with covariance and strength) is associated with the map and fused.
* ``"conventional"``: each reading is a range along the beam axis with a beam-wide
  bearing uncertainty (the classic sonar EKF), kept as the baseline to beat.

Delayed observations: a fit completes some time after its reference reading. The
Localizer keeps a short history of its beliefs (one entry per odom record and per fused
observation, ``history_s`` long). An observation referring to time ``t_ref`` is fused
into the belief at ``t_ref`` (rewound, the odometry interpolated to ``t_ref``), and the
later odometry increments and observations are replayed on top: the same result as if
the observation had arrived on time, whatever else was fused meanwhile.

Readings are buffered until an odom record at or after their time has arrived, so the
transducer pose is interpolated, never extrapolated.

Embedding (e.g. a ROS node)::

    loc = Localizer(FeatureMap.from_map(load_map("room.geojson")))
    loc.set_rig(mounts, speed_of_sound_mps=343.0)        # or loc.handle(rig_record)
    loc.set_prior(t, x, y, yaw_rad, sd_xy_m, sd_yaw_rad)   # or loc.handle(init_record)
    est = loc.on_odom(t, x, y, yaw_rad)                    # wheel odometry, odom frame
    loc.on_tof(t, sensor_id, tof_us_or_None, pan_rad=None)
    est.state.mean, est.state.cov, est.map_to_odom, est.status, est.reason
"""

from __future__ import annotations

import bisect
import math
import operator
import weakref
from collections import Counter, deque
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import BrokenExecutor, Future
from dataclasses import dataclass, field, replace
from typing import Any, Literal, Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc import se2
from sonarloc.errors import FitWorkerError
from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import (
    InitRecord,
    OdomRecord,
    Record,
    RigRecord,
    SensorMount,
    TofRecord,
    TruthRecord,
)
from sonarloc.localize import echoes, ekf
from sonarloc.localize.associate import Association, AssociationConfig, associate
from sonarloc.localize.confirmed import POSE, ConfirmedFeatures, missing_dof
from sonarloc.localize.echoes import EchoObservation
from sonarloc.localize.ekf import Feature, Gaussian, Observation, OdomNoise
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.fitpool import FitExecutor, FitPool, fit_job
from sonarloc.localize.fitpool import warm_up as fitpool_warm_up
from sonarloc.localize.odomframe import (
    Frame,
    OdomJoiner,
    Restart,
    check_odom_reset_settings,
    raw_pose,
)
from sonarloc.localize.relocalize import Relocalization, RelocalizeConfig, Relocalizer
from sonarloc.physics.sound import check_air_speed_of_sound

Array = NDArray[np.float64]
Method = Literal["kuc", "conventional", "specular", "odometry"]

#: Fit statuses whose segments are still associated and fused by their readings when
#: ``kuc_fusion == "echoes"`` (the fit failed, the readings did not).
ECHO_ONLY_STATUSES = ("ok", "flat", "too_few_points", "unresolved", "partial")
#: A segment associated by its readings needs this many readings kept, and this share.
ECHO_MIN_READINGS = 1
ECHO_MIN_FRACTION = 0.75
KucFusion = Literal["echoes", "fit"]
#: :class:`FusionOutcome` reason of an observation skipped by ``update_min_d`` /
#: ``update_min_a`` (:meth:`Localizer.may_fuse_again`).
NO_MOTION_REASON = "no motion since this map feature was fused"
#: Transducer poses remembered per map feature for :meth:`Localizer.may_fuse_again` (a
#: panning transducer standing still sees a feature from a few dozen angles, 1.5 deg
#: apart, each sweep).
FUSED_POSES_KEPT = 64
Status = Literal["initializing", "tracking", "dead_reckoning", "lost"]


#: Odometry that moved less than this across a gap still places the readings inside it
#: (a robot standing still: some drivers publish only on change; the pose is known).
GAP_STILL_M = 1e-3
GAP_STILL_RAD = math.radians(0.1)


def odom_moved(a: ArrayLike, b: ArrayLike) -> NDArray[np.bool_]:
    """Whether odometry poses ``b`` differ from ``a`` ((..., 3) m, m, rad each) by more
    than :data:`GAP_STILL_M` in position or :data:`GAP_STILL_RAD` in yaw."""
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    return np.asarray((np.hypot(d[..., 0], d[..., 1]) > GAP_STILL_M)
                      | (np.abs(se2.wrap_angle(d[..., 2])) > GAP_STILL_RAD))


def in_odom_gap(t_s: float, t_a: float, pose_a: ArrayLike, t_b: float, pose_b: ArrayLike,
                gap_s: float) -> bool:
    """Whether a reading at ``t_s``, between odometry poses ``pose_a`` at ``t_a`` and
    ``pose_b`` at ``t_b``, lies strictly inside a gap: the two further apart than
    ``gap_s`` and the robot moved across it (:func:`odom_moved`), so that a pose
    interpolated there is a guess (``LocalizerConfig.odom_gap_s``)."""
    return t_b - t_a > gap_s and t_a < t_s < t_b and bool(odom_moved(pose_a, pose_b))


def moved_enough(a: Sequence[float], b: Sequence[float], min_d_m: float, min_a_rad: float
                 ) -> bool:
    """Whether odometry pose ``b`` is at least ``min_d_m`` [m] from ``a`` or turned at
    least ``min_a_rad`` [rad] from it (poses (x_m, y_m, yaw_rad) in ``odom``): the robot
    moved enough for a map feature fused at ``a`` to be fused again at ``b``
    (``LocalizerConfig.update_min_d`` / ``update_min_a``). Both 0: always."""
    ax, ay, ath = a
    bx, by, bth = b
    dyaw = abs((bth - ath + math.pi) % (2.0 * math.pi) - math.pi)
    return math.hypot(bx - ax, by - ay) >= min_d_m or dyaw >= min_a_rad


class LandmarkSource(Protocol):
    """What the Localizer needs from the fitting stage: readings in, landmarks out.

    ``push`` takes one reading with its transducer pose in ``odom`` (``tof_us`` NaN = no
    echo) and returns the landmarks it completed (often none); ``flush`` ends the stream.
    """

    def push(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, tof_us: float,
             sensor: int) -> list[Landmark]: ...

    def flush(self) -> list[Landmark]: ...


DEFAULT_ODOM_NOISE = OdomNoise(
    along_var_per_m=0.005**2, cross_var_per_m=0.003**2, xy_var_per_rad=0.002**2,
    yaw_var_per_m=math.radians(1.0) ** 2, yaw_var_per_rad=math.radians(1.0) ** 2)
"""Odometry increment noise of :class:`LocalizerConfig` and of the map builder
(:class:`~sonarloc.maps.build.BuildConfig`): 5 mm along and 3 mm across per sqrt(m),
1 deg per sqrt(m) and per sqrt(rad) of yaw."""


@dataclass(frozen=True)
class LocalizerConfig:
    """Settings of the :class:`Localizer`.

    Attributes
    ----------
    method : ``"kuc"`` (fitted landmarks); ``"conventional"`` (each reading a range along
        the beam axis with a beam-wide bearing SD: walls ray-cast along the axis);
        ``"specular"`` (the conventional reading, but a wall predicted at its
        normal-incidence point: a stronger baseline); ``"odometry"`` (readings ignored:
        dead reckoning from the prior, for comparison).
    odom_noise : odometry increment noise model of :func:`~sonarloc.localize.ekf.predict`.
    association : gate and ambiguity settings.
    history_s : how far back delayed observations can be fused.
    fit_sd_floor_m, fit_sd_floor_deg : added in quadrature to fitted landmarks'
        position/rho and bearing/alpha SDs (odometry error inside a segment, model error).
    fit_cov_scale : multiplies the fit covariance before the floor is added.
    kuc_fusion : what the ``kuc`` method fuses once a fit is associated with a map
        feature: ``"echoes"`` (default) the segment's readings themselves, each a time of
        flight predicted by the forward model from the map feature and the pose
        (:mod:`sonarloc.localize.echoes`; odometry error inside the segment enters their
        covariance); ``"fit"`` the fitted landmark (point or line with the fit's
        covariance and the floors below).
    echo_gate_probability : chi-square gate (dof = readings kept) of the stacked update.
    echo_screen_probability : per-reading chi-square(1) gate screening out readings of
        another reflector before the stacked update.
    fit_statuses : fit statuses fused (``flat``: a wall seen near normal incidence over a
        short arc; its range is precise, its bearing SD large, as its covariance says).
    segment_max_readings : the segmenter closes (and the fitter fits) a segment after this
        many readings, so a wall seen for a long time by a fixed transducer still gives
        regular updates. None (default): 8, except 400 (the segmenter's own limit) for
        a panning transducer with ``kuc_fusion="fit"``: a pan sweeps past its landmarks,
        and a pass cut short leaves a partial U whose fit is poor. Reading-level fusion
        needs no whole U (the pass was associated, and is fused, reading by reading), and
        a pass fused in chunks of 8 reaches the pose while it is fresh: on the panning
        room drives of ``benchmarks/bench_localize.py`` 1.7 mm against 2.1 mm steady RMSE
        with whole passes.
    segment_sweep_away_deg : a panning transducer's segment is closed once its axis has
        swept this far past the segment's last echo (the segmenter's ``sweep_away_deg``),
        so the next pass over the same landmark, a sweep later, is a segment of its own
        (fused when it is seen, with the odometry of one pass inside it). None (default):
        twice the segmenter's beam half-width (50 deg) when the readings come with a pan
        angle, never for fixed transducers; ``math.inf``: never.
    segment_min_echoes : segments with fewer echoes are dropped as spikes by the
        segmenter. None (default): 1 with ``kuc_fusion="echoes"`` (a lone echo of a
        feature is still a forward-model measurement), the segmenter's 3 otherwise.
    conventional_range_sd_m, conventional_bearing_sd_deg : the conventional model.
    max_range_m : readings (conventional) and candidates farther than this are ignored.
    lost_after_rejections : this many observations in a row rejected (no candidate,
        outside the gate, ambiguous) make the status ``lost``.
    lost_sd_m : a position SD above this makes the status ``lost``.
    dead_reckoning_after_s : the window [s] of the status: ``tracking`` needs the map
        features confirmed within it (:meth:`Localizer.confirm`) to pin x, y and yaw
        (:func:`~sonarloc.localize.confirmed.missing_dof`); otherwise, or with nothing
        confirmed for this long, ``dead_reckoning``.
    odom_gap_s : consecutive odometry messages further apart than this are a gap
        (counted in ``stats.odom_gaps``). Readings taken inside a gap during which the
        odometry moved (:func:`odom_moved`) are skipped and counted
        (``skipped["tof_in_odom_gap"]``): a pose interpolated over seconds of driving is
        a guess (a turn inside a 5 s gap put the conventional EKF 0.44 m off while it
        reported millimetres). The odometry increment across the gap is still used,
        with its noise (:class:`OdomNoise`: per metre and radian the odometry measured).
        ``math.inf``: no gaps. The default, 1 s, is ten periods of a 10 Hz odometry (a
        Pioneer's SIPs; ROS bases publish at 10-50 Hz): set it to a few periods of a
        slower one, whose every reading would otherwise fall in a gap.
    odom_max_speed_mps, odom_max_yaw_rate_rad_s : an increment between consecutive
        odometry records implying a faster motion [m/s] or turn [rad/s] (over their
        time apart, at least 0.02 s) is a *jump*, taken as a reset (below) and counted
        in ``stats.odom_jumps``. ``math.inf``: no jump detection (a log that teleports
        the robot's odometry on purpose, e.g. a kidnap test).
    odom_reset_sd_m, odom_reset_sd_deg : across an odometry reset (an odom record
        flagged ``reset``: the base controller restarted its odometry; counted in
        ``stats.odom_resets``) or jump, the increment is not applied: the belief of
        ``base_link`` in ``map`` is kept, its position and yaw SDs grown by these in
        quadrature (the robot's motion between the two records is unknown), and
        ``map_to_odom`` then follows from the new odometry pose
        (:mod:`~sonarloc.localize.odomframe`). Readings taken between the two records
        have no pose: skipped and counted (``skipped["tof_across_odom_reset"]``).
        Segments the fitter holds open are closed at a reset.
    map_sd_m : SD [m] of a map feature's position: an error shared by the readings of
        one update (added to every element of their covariance; to the range, rho or
        position variance of a conventional reading or fitted landmark). The larger of
        this and the feature's own SD (its ``sd_rel_m``, relative to the map frame, else
        its ``sd_m``: map properties ``map build`` writes; :attr:`FeatureMap.point_sd_m`)
        is used. Default 0: the map taken as exact,
        unless it says otherwise (the simulated maps are: 3 mm costs the moving drives
        of ``benchmarks/bench_localize.py`` 10-18 % of their steady accuracy).
    map_error_memory_s : a feature's map error is one constant that all its readings
        share, not an error drawn anew by each update: with this > 0 [s], the map
        variance of an update (above) is multiplied by one plus the feature's recent
        fusions, each counted ``exp(-age / map_error_memory_s)``
        (:meth:`Localizer.map_uses`), so that a feature fused ``n`` times within the
        pose's memory gives it about ``1 / var`` of information from its map error,
        not ``n / var``. Default 0: off (each update takes the map variance as it is).
        Changes nothing on a map without a map error. On SLAM-built maps with honest
        ``sd_rel_m`` (x0.22; benchmarks/results/map_sd.md), 10 s brings
        the pose NEES from 9-13 to 3-3.6 and the steady error from 3.8-4.4 to 3.5-4.0 mm;
        on maps whose SDs are already conservative it makes the pose underconfident
        and costs accuracy (docs/LOCALIZATION.md, "Standing still").
    update_min_d, update_min_a : a map feature is fused again only once the transducer
        it is seen from has moved at least ``update_min_d`` [m] or turned at least
        ``update_min_a`` [rad] (odometry, ``odom`` frame) from each pose that feature was
        fused from lately (:data:`FUSED_POSES_KEPT`), as AMCL's parameters of these
        names. Readings of a feature from the same place share its map error and the
        model's error there; fused again and again by a robot standing still, they
        would average down an error that does not average down (odometry adds no noise
        while still): the covariance collapses to micrometres and a map a few
        millimetres off is then rejected. An observation that would be fused
        (associated, inside the gate) but comes too soon is skipped and counted
        (``skipped["no_motion_since_fused"]``); it still confirms the pose for the
        status (not ``dead_reckoning``). Transducer poses, not base poses: a panning
        transducer sees a feature from new angles within one pass. Applies to every
        method and to the batch replay alike. 0 and 0: every observation fused (the
        behaviour before these settings). Defaults 2 cm and 1 deg: the moving drives of
        ``benchmarks/bench_localize.py`` fuse as before (a ring's transducers move
        further between two segments; a pan turns 1.5 deg a ping), while 5 cm / 5 deg
        cost the panning drives 15-20 % of their steady accuracy.
    relocalize : (method ``kuc``) when ``lost`` (or started without a prior), try a global
        relocalization (:mod:`~sonarloc.localize.relocalize`) every
        ``relocalization.every_s`` from the fits since the trouble began, and restart
        the filter at an unambiguous winner. Without a prior, no estimate is reported
        until then.
    relocalization : its settings.
    max_tof_us : a module that reports a timeout as a reading (its largest TOF) rather
        than as no echo: readings at or above this [us] are taken as no echo and counted
        (``stats.timeouts``), as ``sonarloc fit --max-tof``. None (default): every
        reading is an echo.
    fit_workers : (method ``kuc``) fit closed segments in this many background workers
        (:mod:`~sonarloc.localize.fitpool`) instead of in the caller's call, so a call
        that closes a batch of segments does not stall the caller. 0 (default): fit
        and fuse in the call, as before. The landmarks are fused in the order their
        segments closed, each at its own reference time (rewind and replay): the
        belief once every fit is fused is the synchronous one; the estimates reported
        meanwhile lack the fits still in flight. Only with the built-in fitter
        (:class:`SegmentFitSource`); another ``landmark_source`` is called in the call.
        Call :meth:`Localizer.close` (or use ``with``) to stop the workers.
    fit_executor : ``"thread"`` (default) or ``"process"`` workers (forkserver, else
        spawn; segments and landmarks pickled across).
    fit_max_lag_s : back-pressure [s of log time]: when the oldest fit in flight was
        submitted longer ago than this (the workers fall behind), the call waits for it
        (counted in ``stats.fit_waits``); finished landmarks that old are fused whatever
        ``fuse_per_call`` says. Must be below ``history_s``.
    fuse_per_call : at most this many finished landmarks fused per call (the rest wait
        for the next calls), so the fusion work is spread over calls too.
    """

    method: Method = "kuc"
    odom_noise: OdomNoise = field(default_factory=lambda: DEFAULT_ODOM_NOISE)
    association: AssociationConfig = field(default_factory=AssociationConfig)
    history_s: float = 10.0
    fit_sd_floor_m: float = 0.002
    fit_sd_floor_deg: float = 0.2
    fit_cov_scale: float = 1.0
    fit_statuses: tuple[str, ...] = ("ok", "flat")
    kuc_fusion: KucFusion = "echoes"
    echo_gate_probability: float = 0.99
    echo_screen_probability: float = 0.999
    segment_max_readings: int | None = None
    segment_min_echoes: int | None = None
    segment_sweep_away_deg: float | None = None
    conventional_range_sd_m: float = 0.01
    conventional_bearing_sd_deg: float = 10.0
    max_range_m: float = 6.0
    lost_after_rejections: int = 15
    lost_sd_m: float = 0.5
    dead_reckoning_after_s: float = 5.0
    odom_gap_s: float = 1.0
    odom_max_speed_mps: float = 5.0
    odom_max_yaw_rate_rad_s: float = 10.0
    odom_reset_sd_m: float = 0.1
    odom_reset_sd_deg: float = 5.0
    map_sd_m: float = 0.0
    map_error_memory_s: float = 0.0
    update_min_d: float = 0.02
    update_min_a: float = math.radians(1.0)
    relocalize: bool = False
    relocalization: RelocalizeConfig = field(default_factory=RelocalizeConfig)
    max_tof_us: float | None = None
    fit_workers: int = 0
    fit_executor: FitExecutor = "thread"
    fit_max_lag_s: float = 2.0
    fuse_per_call: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.fit_workers, bool) or not isinstance(self.fit_workers, int) or \
                self.fit_workers < 0:
            raise ValueError(f"`fit_workers` must be a non-negative integer, got "
                             f"{self.fit_workers!r}")
        if self.fit_executor not in ("thread", "process"):
            raise ValueError(f"`fit_executor` must be 'thread' or 'process', got "
                             f"{self.fit_executor!r}")
        if isinstance(self.fuse_per_call, bool) or not isinstance(self.fuse_per_call, int) \
                or self.fuse_per_call < 1:
            raise ValueError(f"`fuse_per_call` must be a positive integer, got "
                             f"{self.fuse_per_call!r}")
        if not self.fit_max_lag_s > 0:
            raise ValueError(f"`fit_max_lag_s` must be positive, got {self.fit_max_lag_s!r}")
        if self.fit_workers and not self.fit_max_lag_s < self.history_s:
            raise ValueError(f"`fit_max_lag_s` must be below `history_s` ({self.history_s!r}) "
                             f"with `fit_workers`, got {self.fit_max_lag_s!r}")
        if self.max_tof_us is not None and not (math.isfinite(self.max_tof_us)
                                                and self.max_tof_us > 0):
            raise ValueError(f"`max_tof_us` must be a positive number of microseconds or "
                             f"None, got {self.max_tof_us!r}")
        if self.kuc_fusion not in ("echoes", "fit"):
            raise ValueError(f"`kuc_fusion` must be 'echoes' or 'fit', got {self.kuc_fusion!r}")
        for name in ("echo_gate_probability", "echo_screen_probability"):
            v = getattr(self, name)
            if not 0.0 < v < 1.0:
                raise ValueError(f"`{name}` must be in (0, 1), got {v!r}")
        if self.method not in ("kuc", "conventional", "specular", "odometry"):
            raise ValueError(f"`method` must be 'kuc', 'conventional', 'specular' or "
                             f"'odometry', got {self.method!r}")
        for name in ("history_s", "conventional_range_sd_m", "conventional_bearing_sd_deg",
                     "max_range_m", "lost_sd_m", "dead_reckoning_after_s", "fit_cov_scale"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        if not self.odom_gap_s > 0:  # math.inf allowed: no gaps
            raise ValueError(f"`odom_gap_s` must be positive, got {self.odom_gap_s!r}")
        check_odom_reset_settings(self.odom_max_speed_mps, self.odom_max_yaw_rate_rad_s,
                                  self.odom_reset_sd_m, self.odom_reset_sd_deg)
        for name in ("fit_sd_floor_m", "fit_sd_floor_deg", "update_min_d", "update_min_a",
                     "map_sd_m", "map_error_memory_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"`{name}` must be non-negative, got {v!r}")
        if self.relocalize and self.method != "kuc":
            raise ValueError(f"`relocalize` needs fitted landmarks: method 'kuc', got "
                             f"{self.method!r}")
        if not (isinstance(self.lost_after_rejections, int) and self.lost_after_rejections >= 1):
            raise ValueError(f"`lost_after_rejections` must be a positive integer, got "
                             f"{self.lost_after_rejections!r}")


@dataclass(frozen=True)
class PoseEstimate:
    """The Localizer's report after an odom record.

    ``state``: belief of ``base_link`` in ``map`` (mean (3,) m, m, rad; cov (3, 3)).
    ``odom_pose``: the odometry pose of ``base_link`` in ``odom`` at ``t_s``.
    ``map_to_odom``: pose of ``odom`` in ``map`` (x, y, yaw), so that ``map→base_link =
    map_to_odom ⊕ odom_pose`` (the transform a ROS node broadcasts).
    ``status``/``reason``: tracking, dead_reckoning or lost, and why.
    """

    t_s: float
    state: Gaussian
    odom_pose: Array
    map_to_odom: Array
    status: Status
    reason: str

    @classmethod
    def _of(cls, t_s: float, state: Gaussian, odom_pose: Array, map_to_odom: Array,
            status: Status, reason: str) -> PoseEstimate:
        """The same as the constructor, without the frozen dataclass's per-field
        ``object.__setattr__`` (the batch replay makes one per odom record)."""
        est = object.__new__(cls)
        est.__dict__.update(t_s=t_s, state=state, odom_pose=odom_pose,
                            map_to_odom=map_to_odom, status=status, reason=reason)
        return est

    @property
    def x_m(self) -> float:
        return float(self.state.mean[0])

    @property
    def y_m(self) -> float:
        return float(self.state.mean[1])

    @property
    def yaw_rad(self) -> float:
        return float(self.state.mean[2])


@dataclass
class LocalizerStats:
    """Counters: what came in and what became of it (bounded memory)."""

    odom: int = 0
    tof: int = 0
    landmarks: int = 0
    segments: int = 0
    observations: int = 0
    accepted: int = 0
    echoes_fused: int = 0
    outcomes: Counter[str] = field(default_factory=Counter)
    skipped: Counter[str] = field(default_factory=Counter)
    replayed_steps: int = 0
    relocalization: Counter[str] = field(default_factory=Counter)
    #: consecutive odometry messages more than ``LocalizerConfig.odom_gap_s`` apart
    odom_gaps: int = 0
    #: odom records flagged ``reset`` (a restarted odometry), and increments taken as
    #: jumps (``LocalizerConfig.odom_max_speed_mps`` / ``odom_max_yaw_rate_rad_s``)
    odom_resets: int = 0
    odom_jumps: int = 0
    #: readings at or above ``LocalizerConfig.max_tof_us``, taken as no echo
    timeouts: int = 0
    #: batches of segments sent to background workers (``LocalizerConfig.fit_workers``),
    #: and calls that waited for one (``fit_max_lag_s``: the workers fell behind)
    fit_jobs: int = 0
    fit_waits: int = 0
    #: worker pools replaced after they broke (a process worker killed)
    fit_pool_restarts: int = 0

    def summary(self) -> str:
        parts = [f"{self.odom} odom", f"{self.tof} tof", f"{self.observations} observations",
                 f"{self.accepted} fused"]
        if self.landmarks:
            parts.insert(2, f"{self.landmarks} landmarks fitted")
        if self.segments:
            parts.insert(2, f"{self.segments} segments")
        if self.echoes_fused:
            parts.append(f"{self.echoes_fused} readings fused")
        if self.outcomes.get("echo_matched"):
            parts.append(f"{self.outcomes['echo_matched']} associated by their readings")
        rej = {k: v for k, v in self.outcomes.items() if k not in ("matched", "echo_matched")}
        if rej:
            parts.append("rejected: " + ", ".join(f"{k} {v}" for k, v in sorted(rej.items())))
        if self.odom_gaps:
            parts.append(f"{self.odom_gaps} odometry gaps")
        if self.odom_resets:
            parts.append(f"{self.odom_resets} odometry resets")
        if self.odom_jumps:
            parts.append(f"{self.odom_jumps} odometry jumps")
        if self.timeouts:
            parts.append(f"{self.timeouts} timeouts taken as no echo")
        if self.fit_jobs:
            parts.append(f"{self.fit_jobs} fit batches in workers ({self.fit_waits} waited "
                         f"for)")
        if self.fit_pool_restarts:
            parts.append(f"{self.fit_pool_restarts} fit worker pools restarted")
        if self.skipped:
            parts.append("skipped: " + ", ".join(f"{k} {v}" for k, v in
                                                 sorted(self.skipped.items())))
        if self.relocalization:
            parts.append("relocalization attempts: " + ", ".join(
                f"{k} {v}" for k, v in sorted(self.relocalization.items())))
        return "; ".join(parts)


class _FusedPoses:
    """The last :data:`FUSED_POSES_KEPT` transducer poses (x, y, yaw in ``odom``) a map
    feature was fused from, in a ring buffer (one vectorised test for all of them)."""

    __slots__ = ("_poses", "_n", "_next")

    def __init__(self) -> None:
        self._poses = np.zeros((FUSED_POSES_KEPT, 3))
        self._n = 0
        self._next = 0

    def add(self, pose: Sequence[float]) -> None:
        self._poses[self._next] = pose
        self._next = (self._next + 1) % FUSED_POSES_KEPT
        self._n = min(self._n + 1, FUSED_POSES_KEPT)

    def near(self, pose: Sequence[float], min_d_m: float, min_a_rad: float) -> bool:
        """Whether ``pose`` has not :func:`moved_enough` from one of the poses kept."""
        p = self._poses[:self._n]
        x, y, yaw = pose
        close = np.hypot(p[:, 0] - x, p[:, 1] - y) < min_d_m
        if not close.any():
            return False
        turn = np.abs((p[close, 2] - yaw + math.pi) % (2.0 * math.pi) - math.pi)
        return bool(np.any(turn < min_a_rad))


@dataclass
class _Entry:
    """One step of the history: the belief right after it. ``odom``: the odometry pose
    in the joined frame (:mod:`~sonarloc.localize.odomframe`); ``frame``: the raw
    odometry frame's pose in it (None: the same); ``reset``: the odometry restarted
    here (no increment from the entry before; the reset noise added)."""

    t: float
    odom: Array
    state: Gaussian
    obs: Observation | EchoObservation | None = None
    feature: Feature | None = None
    reset: bool = False
    frame: Frame | None = None


@dataclass(frozen=True)
class FusionOutcome:
    """What became of one observation: its association and whether it was fused."""

    t_ref: float
    association: Association | None
    fused: bool
    reason: str


@dataclass
class _FitJob:
    """A batch of closed segments fitting in a background worker: the log time of the
    reading that closed the batch, the source that closed them (its ``on_fit``), the
    segments and the future of their landmarks."""

    t_s: float
    source: SegmentFitSource
    segments: list[Any]
    future: Future[list[Landmark]]


class SegmentFitSource:
    """The fitting stage's online segmenter and batch fitter as a :class:`LandmarkSource`.

    Closed segments are fitted together (vectorised) once ``batch`` of them are waiting
    or the oldest has waited ``max_wait_s`` of stream time; the Localizer fuses the
    delayed fits at their reference times anyway. Each landmark gets
    ``extra["view_xy"]``: the mean transducer position of its echoes (in the frame of
    the poses), the direction a cylinder's fitted surface point faces; and
    ``extra["echoes"]``: the segment's echoes as arrays ``(t_s, x_m, y_m, yaw_rad,
    tof_us)`` (transducer poses in that frame) for the Localizer's reading-level fusion.

    ``max_readings``: segment length limit; None lets the :class:`Localizer` choose at
    the first reading (:meth:`Localizer.segment_max_readings`), or 400 when used on its
    own. ``sweep_away_deg``: the segmenter's setting of that name (None: never
    close a segment because the beam turned away; see
    :meth:`Localizer.segment_sweep_away_deg`). ``min_echoes``: shorter segments are
    dropped by the segmenter as spikes;
    None lets the Localizer choose (1 with reading-level fusion, whose forward model
    can use a lone echo, else the segmenter's default).

    ``on_fit(segment, landmark)``: optional callback for every fitted segment (e.g. to
    keep the readings behind a figure), called in stream order.
    """

    def __init__(self, speed_of_sound_mps: float = 343.0, batch: int = 4,
                 max_wait_s: float = 0.25, max_readings: int | None = None,
                 on_fit: Callable[[Any, Landmark], None] | None = None,
                 min_echoes: int | None = None, sweep_away_deg: float | None = None
                 ) -> None:
        from sonarloc.fit.lsq import FitConfig
        from sonarloc.physics.tof import ModuleParams

        self.fit_config = FitConfig(module=ModuleParams(c_mps=speed_of_sound_mps))
        self.max_readings = max_readings
        self.min_echoes = min_echoes
        self.sweep_away_deg = sweep_away_deg
        self._segmenter: Any = None
        self.batch = batch
        self.max_wait_s = max_wait_s
        self._waiting: list[tuple[float, Any]] = []
        self.on_fit = on_fit

    @property
    def segmenter(self) -> Any:
        """The fitting stage's :class:`~sonarloc.fit.segment.Segmenter` (made at first use)."""
        if self._segmenter is None:
            from sonarloc.fit.segment import Segmenter, SegmenterConfig

            cfg = SegmenterConfig()
            if self.max_readings is not None:
                cfg = replace(cfg, max_readings=self.max_readings)
            if self.min_echoes is not None:
                cfg = replace(cfg, min_echoes=self.min_echoes)
            if self.sweep_away_deg is not None and math.isfinite(self.sweep_away_deg):
                cfg = replace(cfg, sweep_away_deg=self.sweep_away_deg)
            self._segmenter = Segmenter(cfg, self.fit_config.module)
        return self._segmenter

    def push(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, tof_us: float,
             sensor: int) -> list[Landmark]:
        return self.fit(self.take(t_s, x_m, y_m, yaw_rad, tof_us, sensor))

    def flush(self) -> list[Landmark]:
        return self.fit(self.take_rest())

    def take(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, tof_us: float,
             sensor: int) -> list[Any]:
        """:meth:`push` without the fit: the closed segments whose batch is due (often
        none), for :meth:`fit` here or :func:`~sonarloc.localize.fitpool.fit_job` in a
        worker (then :meth:`fitted`)."""
        for s in self.segmenter.push(t_s, x_m, y_m, yaw_rad, tof_us, sensor):
            self._waiting.append((t_s, s))
        if self._waiting and (len(self._waiting) >= self.batch
                              or t_s - self._waiting[0][0] >= self.max_wait_s):
            return self._take_waiting()
        return []

    def take_rest(self) -> list[Any]:
        """:meth:`flush` without the fit: every segment still open or waiting."""
        for s in self.segmenter.flush():
            self._waiting.append((math.inf, s))
        return self._take_waiting()

    def _take_waiting(self) -> list[Any]:
        segs = [s for _, s in self._waiting]
        self._waiting.clear()
        return segs

    def fit(self, segs: Sequence[Any]) -> list[Landmark]:
        """Fit closed segments (one vectorised batch,
        :func:`~sonarloc.localize.fitpool.fit_job`); one landmark per segment, in order."""
        return self.fitted(segs, fit_job(segs, self.fit_config))

    def fitted(self, segs: Sequence[Any], landmarks: list[Landmark]) -> list[Landmark]:
        """The landmarks :func:`~sonarloc.localize.fitpool.fit_job` fitted to ``segs``,
        after :attr:`on_fit` has seen each pair (in the caller's thread)."""
        if self.on_fit is not None:
            for s, lm in zip(segs, landmarks, strict=True):
                self.on_fit(s, lm)
        return landmarks


def _fitted_kappa(lm: Landmark) -> float:
    """The fitted strength of ``lm`` [us] (NaN when it has none)."""
    p = np.asarray(lm.params, dtype=float)
    return float(p[2]) if p.shape == (3,) else math.nan


def _kappa_fallback(fitted_kappa_us: float) -> float:
    """Strength used for a map feature without one: the fit's, kept within 0.05..10 us,
    else 1 us."""
    if math.isfinite(fitted_kappa_us):
        return min(max(fitted_kappa_us, 0.05), 10.0)
    return 1.0


def _echo_arrays(lm: Landmark) -> tuple[Array, ...] | None:
    """``lm.extra["echoes"]`` as five equal-length float arrays (t, x, y, yaw, tof), or
    None when absent or malformed."""
    raw = lm.extra.get("echoes")
    if not isinstance(raw, tuple) or len(raw) != 5:
        return None
    arrays = tuple(np.asarray(a, dtype=float).reshape(-1) for a in raw)
    if len({a.size for a in arrays}) != 1 or arrays[0].size == 0:
        return None
    return arrays


class Localizer:
    """EKF localization against a landmark map (see the module docstring).

    Parameters
    ----------
    fmap : the map's features.
    config : settings.
    landmark_source : factory ``(speed_of_sound_mps) -> LandmarkSource`` for the
        ``kuc`` method (default: a :class:`SegmentFitSource` with
        ``config.segment_max_readings``).
    """

    def __init__(self, fmap: FeatureMap, config: LocalizerConfig | None = None,
                 landmark_source: Callable[[float], LandmarkSource] | None = None) -> None:
        self.fmap = fmap
        self.config = config or LocalizerConfig()
        self.stats = LocalizerStats()
        self._source_factory = landmark_source
        self._source: LandmarkSource | None = None
        self._mounts: dict[int, Array] = {}
        self._c_mps = 343.0
        self._prior: Gaussian | None = None
        self._entries: list[_Entry] = []
        self._times: list[float] = []
        # readings waiting for odometry at or after their time, in arrival order (a deque:
        # dropping the oldest when no odometry arrives is O(1))
        self._pending: deque[TofRecord] = deque()
        self._last_odom_t = -math.inf
        # time of the first odometry since the prior (NaN before it): a reading older
        # than it has no pose at all (`tof_before_odom`), one older than the trimmed
        # history had one (`tof_older_than_history`)
        self._odom_start_t = math.nan
        self._last_pushed_t = -math.inf  # the latest reading given to the segmenter
        self._consecutive_rejected = 0
        # map features that confirmed the pose lately (confirm(); the status)
        self._confirmed = ConfirmedFeatures()
        self._dof_memo: tuple[list[tuple[str, int]] | None, str] = (None, "")
        self._start_t = math.nan
        self._estimate: PoseEstimate | None = None
        self._reloc = Relocalizer(fmap, self.config.relocalization) \
            if self.config.relocalize else None
        self._unknown = False  # started without a prior: no pose until relocalized
        self._reject_start_t = math.nan
        # transducer poses (x, y, yaw in odom) of the latest fusions of each map feature
        # ("point"/"wall", index): LocalizerConfig.update_min_d / update_min_a
        self._fused_at: dict[tuple[str, int], _FusedPoses] = {}
        # each map feature's (points, then walls) recent fusions, decayed, and the time
        # of the latest: LocalizerConfig.map_error_memory_s
        self._map_base_var = self.map_var_all()
        self._map_n = np.zeros(len(self._map_base_var))
        self._map_t = np.zeros(len(self._map_base_var))
        c = self.config
        self._conv_cov = np.diag([c.conventional_range_sd_m**2,
                                  math.radians(c.conventional_bearing_sd_deg) ** 2])
        # odometry joined across resets and jumps (LocalizerConfig.odom_max_speed_mps)
        self.odom_joiner = OdomJoiner(c.odom_max_speed_mps, c.odom_max_yaw_rate_rad_s)
        self._reset_cov = np.diag([c.odom_reset_sd_m**2, c.odom_reset_sd_m**2,
                                   math.radians(c.odom_reset_sd_deg) ** 2])
        # background fits (LocalizerConfig.fit_workers): the jobs in the order their
        # segments closed, and the landmarks of finished ones waiting to be fused (with
        # their job's time), fused in that order
        self._pool: FitPool | None = None
        self._jobs: deque[_FitJob] = deque()
        self._ready: deque[tuple[float, Landmark]] = deque()
        self._fit_now = -math.inf   # the latest log time seen (back-pressure)
        if c.fit_workers and c.method == "kuc":
            self._start_pool()

    # -- background fits -------------------------------------------------------------

    def close(self) -> None:
        """Stop the background fit workers (``LocalizerConfig.fit_workers``; nothing to
        do without). Fits still in flight are dropped and counted
        (``stats.skipped["fit_dropped_at_close"]``, in segments): call :meth:`finish`
        first to fuse them. Later calls fit in the call, as with ``fit_workers=0``."""
        pool, self._pool = self._pool, None
        if pool is None:
            return
        dropped = sum(len(j.segments) for j in self._jobs) + len(self._ready)
        if dropped:
            self.stats.skipped["fit_dropped_at_close"] += dropped
        self._jobs.clear()
        self._ready.clear()
        self._pool_finalizer.detach()
        pool.close()

    def warm_up(self) -> None:
        """Build the landmark fitter's tables and the fusion's delay table for the map's
        features now (cached per process and speed of sound: the rig's, 343 m/s before
        one is set), so that the first calls that fit and fuse do not pay for them
        (:func:`~sonarloc.localize.fitpool.warm_up`,
        :func:`~sonarloc.localize.echoes.warm_up`; ~0.12 s; the first fitting call of a
        room drive 70.7 -> 35.2 ms of CPU, benchmarks/results/warmup.md). For a node about to
        drive; nothing to do for the methods without fits. With ``fit_workers`` the pool
        warms its workers itself."""
        if self.config.method == "kuc":
            fitpool_warm_up(self._c_mps)
            fm = self.fmap
            echoes.warm_up(fm.point_kappa_us, fm.point_kind, fm.point_radius_m,
                           fm.wall_kappa_us, self._c_mps)

    def _restart_pool(self) -> int:
        """Replace a broken worker pool (a process worker killed, e.g. by the kernel's
        out-of-memory killer) with a new one, so that one lost worker does not stop the
        fits for good. The jobs in flight on the old pool are dropped (they fail with
        it); returns their number of segments. Counted in ``stats.fit_pool_restarts``."""
        old = self._pool
        assert old is not None
        lost = sum(len(j.segments) for j in self._jobs)
        self._jobs.clear()
        self._pool_finalizer.detach()
        old.close(wait=False)
        self._start_pool()
        self.stats.fit_pool_restarts += 1
        return lost

    def _start_pool(self) -> None:
        """The background fit workers (``LocalizerConfig.fit_workers``), warmed up for
        the current speed of sound."""
        c = self.config
        self._pool = FitPool(c.fit_workers, c.fit_executor, self._c_mps)
        # a Localizer dropped without close() does not leave its workers behind
        self._pool_finalizer = weakref.finalize(self, self._pool.close, False)

    def __enter__(self) -> Localizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def pending_fits(self) -> int:
        """Segments fitting in background workers plus fitted landmarks not yet fused."""
        return sum(len(j.segments) for j in self._jobs) + len(self._ready)

    def _submit(self, source: SegmentFitSource, segs: list[Any], t_s: float) -> None:
        """Send a batch of closed segments to a worker (to a new pool if the pool broke:
        see :meth:`_restart_pool`)."""
        if not segs:
            return
        assert self._pool is not None
        lost, broke = 0, None
        try:
            try:
                future = self._pool.submit(segs, source.fit_config)
            except BrokenExecutor as err:   # a process worker died: a new pool takes them
                broke, lost = err, self._restart_pool()
                self.stats.skipped["fit_worker_error"] += lost
                future = self._pool.submit(segs, source.fit_config)
        except Exception as err:   # a pool shut down, or the new one broken too
            self.stats.skipped["fit_worker_error"] += len(segs)
            raise FitWorkerError(f"could not send {len(segs)} segments to a fit worker: "
                                 f"{err!r}") from err
        self._jobs.append(_FitJob(t_s, source, segs, future))
        self.stats.fit_jobs += 1
        if lost:
            raise FitWorkerError(f"the fit worker pool broke ({broke!r}): {lost} segments "
                                 "in flight lost; a new pool fits the next ones") from broke

    def _collect(self, job: _FitJob) -> None:
        """A finished (or waited for) job's landmarks, queued to be fused."""
        try:
            landmarks = job.future.result()
        except Exception as err:
            lost = len(job.segments)
            then = ""
            if isinstance(err, BrokenExecutor):   # its other jobs failed with it
                lost += self._restart_pool()
                then = "; the pool broke and a new one fits the next segments"
            self.stats.skipped["fit_worker_error"] += lost
            raise FitWorkerError(f"a background fit of {len(job.segments)} segments "
                                 f"(closed at t={job.t_s:.3f} s) failed: {err!r}{then}"
                                 ) from err
        for lm in job.source.fitted(job.segments, landmarks):
            self._ready.append((job.t_s, lm))

    def _service_fits(self, t_s: float) -> None:
        """Once per call with background fits: collect finished jobs in order (waiting
        for the oldest if older than ``fit_max_lag_s``), and fuse up to
        ``fuse_per_call`` of their landmarks (all those that old)."""
        pool = self._pool
        if pool is None:
            return
        if t_s > self._fit_now:
            self._fit_now = t_s
        for err in pool.warm_up_errors():
            raise FitWorkerError(f"warming up a fit worker failed: {err!r}") from err
        horizon = self._fit_now - self.config.fit_max_lag_s
        jobs = self._jobs
        while jobs and (jobs[0].future.done() or jobs[0].t_s < horizon):
            if not jobs[0].future.done():
                self.stats.fit_waits += 1
            self._collect(jobs.popleft())
        ready = self._ready
        n = 0
        while ready and (n < self.config.fuse_per_call or ready[0][0] < horizon):
            self.add_landmark(ready.popleft()[1])
            n += 1

    def _drain_fits(self) -> list[FusionOutcome]:
        """Wait for every background fit and fuse its landmarks, in order."""
        while self._jobs:
            self._collect(self._jobs.popleft())
        out = []
        while self._ready:
            out.append(self.add_landmark(self._ready.popleft()[1]))
        return out

    def _flush_source(self) -> list[FusionOutcome]:
        """Close the fitter's open segments, fit them and fuse them (with background
        workers: sent to one, fused later)."""
        src = self._source
        if src is None:
            return []
        if self._pool is not None and isinstance(src, SegmentFitSource):
            self._submit(src, src.take_rest(), self._fit_now)
            return []
        return [self.add_landmark(lm) for lm in src.flush()]

    # -- configuration messages -----------------------------------------------------

    def set_rig(self, sensors: Sequence[SensorMount], speed_of_sound_mps: float = 343.0) -> None:
        """Transducer mount poses in ``base_link`` and the speed of sound."""
        check_air_speed_of_sound(speed_of_sound_mps, "`speed_of_sound_mps`")
        if self._pool is not None:
            self._drain_fits()   # fused as they would have been before the new rig
            self._pool.warm(float(speed_of_sound_mps))
        self._mounts = {m.id: np.array([m.x_m, m.y_m, math.radians(m.yaw_deg)])
                        for m in sensors}
        self._c_mps = float(speed_of_sound_mps)
        self._source = None
        self._last_pushed_t = -math.inf

    def set_prior(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, sd_xy_m: float,
                  sd_yaw_rad: float) -> None:
        """Prior of ``base_link`` in ``map``; (re)starts the filter at the next odom record
        (whose time may be earlier than the last one's: a restarted clock or log). The
        fitter's open segments are fitted and fused first (as at the end of a stream), and
        the fitter starts afresh: its readings must come in time order. Readings still
        waiting for odometry are dropped and counted (``skipped["tof_after_last_odom"]``,
        as at the end of a stream): the next odometry may run on a restarted clock, which
        would place them at the wrong pose."""
        if self._pending:
            self.stats.skipped[self._no_odom_after()] += len(self._pending)
        if self._source is not None:
            self._flush_source()
            self._source = None
            self._last_pushed_t = -math.inf
        self._drain_fits()
        self._odom_start_t = math.nan
        self.odom_joiner.forget()
        self._prior = Gaussian.from_pose(x_m, y_m, yaw_rad, sd_xy_m, sd_yaw_rad)
        self._unknown = False
        self._entries.clear()
        self._times.clear()
        self._fused_at.clear()
        self._forget_uses()
        self._pending.clear()
        self._last_odom_t = -math.inf
        self._consecutive_rejected = 0
        self._confirmed.clear()
        self._start_t = t_s

    # -- message routing ------------------------------------------------------------

    def handle(self, rec: Record) -> PoseEstimate | None:
        """Route one log record; returns the new estimate after an ``odom`` record."""
        if isinstance(rec, OdomRecord):
            return self.on_odom(rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg),
                                rec.reset)
        if isinstance(rec, TofRecord):
            self.on_tof(rec.t_s, rec.sensor, rec.tof_us,
                        None if rec.pan_deg is None else math.radians(rec.pan_deg))
        elif isinstance(rec, RigRecord):
            self.set_rig(rec.sensors, rec.speed_of_sound_mps)
        elif isinstance(rec, InitRecord):
            self.set_prior(rec.t_s, rec.x_m, rec.y_m, math.radians(rec.yaw_deg),
                           *rec.prior_sds())
        elif isinstance(rec, TruthRecord):
            pass  # never read: localization must not see the truth
        return None

    def run(self, records: Iterable[Record]) -> Iterable[PoseEstimate]:
        """Feed records; yield an estimate per odom record (then flush the fitter)."""
        for rec in records:
            est = self.handle(rec)
            if est is not None:
                yield est
        self.finish()

    def on_odom(self, t_s: float, x_m: float, y_m: float, yaw_rad: float,
                reset: bool = False) -> PoseEstimate | None:
        """An odometry pose of ``base_link`` in ``odom``; returns the new estimate
        (None before any prior). ``reset``: the odometry restarted (a new odometry
        frame begins with this pose; see ``LocalizerConfig.odom_reset_sd_m``).

        A pose with a non-finite value, or so far from the last one that the predicted
        belief would not be finite (``skipped["bad_odom"]``: a corrupted message), or
        older than the last one (``skipped["odom_time_backwards"]``: a stale message,
        delivered late) is skipped and the current estimate returned: an old pose taken
        as the newest would move the belief back and forth and mislocate the readings in
        between.
        """
        self.stats.odom += 1
        odom = np.array([x_m, y_m, yaw_rad], dtype=float)
        if not np.all(np.isfinite(odom)) or not math.isfinite(t_s):
            self.stats.skipped["bad_odom"] += 1
            return self._estimate
        odom[2] = se2.wrap_angle(odom[2])
        if t_s < self._last_odom_t:
            self.stats.skipped["odom_time_backwards"] += 1
            return self._estimate
        if self._prior is None:
            if self._reloc is None:
                self.stats.skipped["odom_before_init"] += 1
                return None
            # no prior: follow the odometry and fit landmarks until relocalized
            self._prior = Gaussian(np.zeros(3), np.eye(3))
            self._unknown = True
        t = t_s
        gap = t - self._last_odom_t > self.config.odom_gap_s and bool(self._entries)
        joiner = self.odom_joiner
        raw = (float(odom[0]), float(odom[1]), float(odom[2]))
        if not self._entries:
            joiner.forget()
            odom = np.array(joiner.join(t, raw))
            self._append(_Entry(t, odom, self._prior, frame=joiner.frame))
            if not math.isfinite(self._start_t):
                self._start_t = t
        else:
            last = self._entries[-1]
            odom = np.array(joiner.peek(raw))
            with np.errstate(over="ignore", invalid="ignore"):
                state = ekf.predict(last.state, se2.between(last.odom, odom),
                                    self.config.odom_noise)
            if not (np.isfinite(state.cov).all() and np.isfinite(state.mean).all()) and \
                    np.isfinite(last.state.cov).all():
                # a corrupted pose (1e200 m): the belief would never be finite again
                self.stats.skipped["bad_odom"] += 1
                return self._estimate
            restart = joiner.restart(t, raw, reset)
            if restart is not None:
                state = self._odom_restart(restart)
            odom = np.array(joiner.join(t, raw, restart))
            self._append(_Entry(t, odom, state, reset=restart is not None,
                                frame=joiner.frame))
        self.stats.odom_gaps += gap
        self._last_odom_t = t
        self._trim()
        if self._reloc is not None:
            self._reloc.on_odom(t, odom)
        self._drain_pending(t)
        self._service_fits(t)
        if self._reloc is not None:
            self._maybe_relocalize(t, odom)
        if self._unknown:
            return None
        self._estimate = self._make_estimate(t_s)
        return self._estimate

    def extend_odometry(self, t_s: ArrayLike, odom: ArrayLike,
                        resets: Sequence[bool] | None = None,
                        frames: Sequence[Frame | None] | None = None) -> None:
        """Many odometry poses at once (offline replay): :meth:`on_odom` without the
        per-record estimate, the predictions chained in closed form
        (:func:`~sonarloc.localize.ekf.predict_chain`).

        ``t_s`` (n,) [s], ``odom`` (n, 3) poses of ``base_link`` in ``odom`` (m, m, rad),
        finite, after a prior. Pending readings are not processed (the caller routes
        readings itself) and the history is not trimmed (call :meth:`trim_history`);
        read estimates with :meth:`estimate_at`.

        Odometry joined across resets (:attr:`odom_joiner`, as the batch replay does):
        ``odom`` the joined poses, ``resets`` (n,) which records restarted the odometry
        (no increment there: :meth:`reset_state`; not counted here), ``frames`` (n,)
        each record's raw odometry frame in the joined one (None: the same), for the
        reported ``odom_pose`` and ``map_to_odom``. None: no resets, no frames.
        """
        if resets is not None or frames is not None:
            self._extend_restarted(t_s, odom, resets, frames)
            return
        if isinstance(t_s, list) and isinstance(odom, list) and 0 < len(t_s) <= 4 and \
                len(odom) == len(t_s) and self._entries:
            self._extend_few(t_s, odom)
            return
        t = np.asarray(t_s, dtype=float).reshape(-1)
        pose = np.asarray(odom, dtype=float).reshape(-1, 3)
        if len(t) != len(pose):
            raise ValueError(f"`t_s` and `odom` must have the same length, got {len(t)} and "
                             f"{len(pose)}")
        if len(t) == 0:
            return
        if self._prior is None:
            raise ValueError("`extend_odometry` needs a prior (set_prior or an init record)")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(pose))):
            raise ValueError("`t_s` and `odom` must be finite")
        self.stats.odom += len(t)
        t = np.maximum.accumulate(np.maximum(t, self._last_odom_t))
        pose = pose.copy()
        pose[:, 2] = se2.wrap_angle(pose[:, 2])
        if not self._entries:
            self._append(_Entry(float(t[0]), pose[0], self._prior))
            if not math.isfinite(self._start_t):
                self._start_t = float(t[0])
            t, pose = t[1:], pose[1:]
        if len(t) > 4:
            last = self._entries[-1]
            prev = np.concatenate([last.odom[None, :], pose[:-1]])
            chain = ekf.predict_chain(last.state, se2.between(prev, pose),
                                      self.config.odom_noise)
            for k, tk in enumerate(t.tolist()):
                self._append(_Entry(tk, pose[k], Gaussian(chain.mean[k], chain.cov[k])))
        else:  # a few steps: one predict each costs less than setting up the chain
            noise = self.config.odom_noise
            for k, tk in enumerate(t.tolist()):
                last = self._entries[-1]
                state = ekf.predict(last.state, se2.between(last.odom, pose[k]), noise)
                self._append(_Entry(tk, pose[k], state))
        self._last_odom_t = float(self._times[-1])

    def _extend_restarted(self, t_s: ArrayLike, odom: ArrayLike,
                          resets: Sequence[bool] | None,
                          frames: Sequence[Frame | None] | None) -> None:
        """:meth:`extend_odometry` with resets and frames: runs between resets as
        without, each reset an entry of its own."""
        t = np.asarray(t_s, dtype=float).reshape(-1)
        pose = np.asarray(odom, dtype=float).reshape(-1, 3)
        n = len(t)
        rs = [False] * n if resets is None else [bool(v) for v in resets]
        fr = [None] * n if frames is None else list(frames)
        if not len(pose) == len(rs) == len(fr) == n:
            raise ValueError(f"`t_s`, `odom`, `resets` and `frames` must have the same "
                             f"length, got {n}, {len(pose)}, {len(rs)} and {len(fr)}")
        start = 0
        for k in [*(k for k in range(n) if rs[k] and (self._entries or k > 0)), n]:
            if k > start:
                first = len(self._entries)
                self.extend_odometry(t[start:k], pose[start:k])
                for e, f in zip(self._entries[first:], fr[start:k], strict=True):
                    e.frame = f
            if k < n:
                if not (np.isfinite(t[k]) and np.all(np.isfinite(pose[k]))):
                    raise ValueError("`t_s` and `odom` must be finite")
                self.stats.odom += 1
                tk = max(float(t[k]), self._last_odom_t)
                p = pose[k].copy()
                p[2] = se2.wrap_angle(p[2])
                self._append(_Entry(tk, p, self.reset_state(self._entries[-1].state),
                                    reset=True, frame=fr[k]))
                self._last_odom_t = tk
            start = k + 1

    def _extend_few(self, t_s: list[float], odom: list[Any]) -> None:
        """:meth:`extend_odometry` of a few records after the first (lists, no arrays)."""
        noise = self.config.odom_noise
        for tk, pk in zip(t_s, odom, strict=True):
            tk = float(tk)
            x, y, yaw = pk
            x, y, yaw = float(x), float(y), float(yaw)
            if not (math.isfinite(tk) and math.isfinite(x) and math.isfinite(y)
                    and math.isfinite(yaw)):
                raise ValueError("`t_s` and `odom` must be finite")
            self.stats.odom += 1
            tk = max(tk, self._last_odom_t)
            yaw = (yaw + math.pi) % (2.0 * math.pi) - math.pi
            last = self._entries[-1]
            # se2.between(last.odom, pose) and ekf.predict, in floats
            u = se2.between_floats(last.odom.tolist(), (x, y, yaw))
            mean, cov = ekf.predict_lists(last.state.mean.tolist(), last.state.cov.tolist(), u,
                                          noise)
            self._append(_Entry(tk, np.array([x, y, yaw]),
                                Gaussian.of_lists(mean, cov)))
            self._last_odom_t = tk

    def trim_history(self) -> None:
        """Drop history older than ``history_s`` (as :meth:`on_odom` does)."""
        if self._entries:
            self._trim()

    def estimate_at(self, t_s: float) -> PoseEstimate | None:
        """The estimate at time ``t_s`` from the history: the belief after the last step
        at or before ``t_s`` (None before the first one); the status as it is now."""
        i = bisect.bisect_right(self._times, t_s) - 1
        if i < 0:
            return None
        e = self._entries[i]
        status, reason = self._status(e.t, e.state)
        # map→odom = mean ⊕ odom⁻¹ (scalar arithmetic: this runs once per odom record)
        mx, my, mth = e.state.mean.tolist()
        ox, oy, oth = e.odom.tolist() if e.frame is None else raw_pose(e.odom.tolist(), e.frame)
        c, s = math.cos(oth), math.sin(oth)
        ix, iy = -c * ox - s * oy, s * ox - c * oy
        cm, sm = math.cos(mth), math.sin(mth)
        yaw = (mth - oth + math.pi) % (2.0 * math.pi) - math.pi
        m2o = np.array([mx + cm * ix - sm * iy, my + sm * ix + cm * iy, yaw])
        odom = e.odom if e.frame is None else np.array([ox, oy, oth])
        return PoseEstimate._of(t_s, e.state, odom, m2o, status, reason)

    def on_tof(self, t_s: float, sensor: int, tof_us: float | None,
               pan_rad: float | None = None) -> None:
        """One reading; processed once odometry has reached its time.

        ``tof_us`` None or NaN: no echo. Skipped and counted in ``stats.skipped``: an
        unknown ``sensor`` (``unknown_sensor``; ``tof_before_rig`` before any mounts),
        a non-finite time or pan angle, a zero, negative or infinite TOF (``bad_tof``).
        A TOF at or above ``LocalizerConfig.max_tof_us`` is no echo (``stats.timeouts``).
        """
        self.stats.tof += 1
        if sensor not in self._mounts:
            self.stats.skipped["unknown_sensor" if self._mounts else "tof_before_rig"] += 1
            return
        tof_us = self._timeout_as_no_echo(tof_us)
        bad_tof = tof_us is not None and (tof_us <= 0.0 or tof_us == math.inf)  # NaN: none
        if bad_tof or not math.isfinite(t_s) or (pan_rad is not None
                                                 and not math.isfinite(pan_rad)):
            self.stats.skipped["bad_tof"] += 1
            return
        pan_deg = None if pan_rad is None else math.degrees(pan_rad)
        self._pending.append(TofRecord(t_s, sensor, tof_us, pan_deg))
        if len(self._pending) > 10_000:  # no odometry arriving: keep memory bounded
            self._pending.popleft()
            self.stats.skipped["tof_without_odom"] += 1
        if self._entries and t_s <= self._last_odom_t:
            self._drain_pending(self._last_odom_t)
        self._service_fits(t_s)

    def _timeout_as_no_echo(self, tof_us: float | None) -> float | None:
        """``tof_us``, or None when at or above ``config.max_tof_us`` (counted)."""
        limit = self.config.max_tof_us
        if limit is not None and tof_us is not None and tof_us >= limit:
            self.stats.timeouts += 1
            return None
        return tof_us

    def add_landmark(self, lm: Landmark) -> FusionOutcome:
        """Fuse a fitted landmark (in ``odom``; refers to the pose at ``lm.ref_t_s``).

        With ``kuc_fusion="echoes"`` and the segment's readings attached, the readings are
        fused instead (:meth:`_add_echoes`); then a segment whose fit is unusable (too few
        points, unresolved, partial) or does not associate is associated by its readings.
        """
        self.stats.landmarks += 1
        reading_level = self.config.kuc_fusion == "echoes" and "echoes" in lm.extra
        usable = lm.status.value in self.config.fit_statuses
        if not self.fuses(lm):
            self.stats.skipped[f"fit_{lm.status.value}"] += 1
            return FusionOutcome(lm.ref_t_s, None, False, f"fit status {lm.status.value}")
        if not self._entries:
            self.stats.skipped["landmark_before_init"] += 1
            return FusionOutcome(lm.ref_t_s, None, False, "no prior yet")
        if self._reloc is not None:
            self._reloc.add(lm)
            if self._unknown:
                return FusionOutcome(lm.ref_t_s, None, False, "relocalizing")
        obs = self._landmark_observation(lm) if usable else None
        if reading_level:
            return self._add_echoes(lm, obs)
        if obs is None:
            self.stats.skipped["landmark_bad"] += 1
            return FusionOutcome(lm.ref_t_s, None, False, "landmark not usable")
        return self.add_observation(obs, lm.ref_t_s)

    def fuses_status(self, status: str) -> bool:
        """Whether a landmark of fit status ``status`` (with its readings attached by
        :class:`SegmentFitSource`) can be fused."""
        return status in self.config.fit_statuses or (
            self.config.kuc_fusion == "echoes" and status in ECHO_ONLY_STATUSES)

    def fuses(self, lm: Landmark) -> bool:
        """Whether :meth:`add_landmark` tries to fuse ``lm`` (by its fit status, and with
        reading-level fusion whether its readings are attached)."""
        if lm.status.value in self.config.fit_statuses:
            return True
        return (self.config.kuc_fusion == "echoes" and "echoes" in lm.extra
                and lm.status.value in ECHO_ONLY_STATUSES)

    @property
    def segment_min_echoes(self) -> int | None:
        """The segmenter's ``min_echoes`` for this Localizer's landmark source (None: the
        segmenter's default): ``config.segment_min_echoes``, else 1 with reading-level
        fusion."""
        c = self.config
        if c.segment_min_echoes is not None:
            return c.segment_min_echoes
        return 1 if c.kuc_fusion == "echoes" else None

    def segment_max_readings(self, panning: bool) -> int:
        """The segmenter's ``max_readings`` for this Localizer's landmark source:
        ``config.segment_max_readings``, else 8, or 400 for a panning transducer whose
        fits are fused (``kuc_fusion="fit"``)."""
        c = self.config
        if c.segment_max_readings is not None:
            return c.segment_max_readings
        return 400 if panning and c.kuc_fusion == "fit" else 8

    def segment_sweep_away_deg(self, panning: bool) -> float | None:
        """The segmenter's ``sweep_away_deg`` for this Localizer's landmark source:
        ``config.segment_sweep_away_deg``, else twice the segmenter's beam half-width for
        a panning transducer and None (never) for fixed ones."""
        c = self.config.segment_sweep_away_deg
        if c is not None:
            return c if math.isfinite(c) else None
        if not panning:
            return None
        from sonarloc.fit.segment import SegmenterConfig

        return 2.0 * SegmenterConfig().beam_half_width_deg

    def _add_echoes(self, lm: Landmark, obs: Observation | None) -> FusionOutcome:
        """Associate a segment (by its fit, else by its readings), then fuse its readings
        through the forward model (:mod:`sonarloc.localize.echoes`)."""
        self.stats.observations += 1
        arrays = _echo_arrays(lm)
        if arrays is None:
            self.stats.outcomes["echo_none"] += 1
            return FusionOutcome(lm.ref_t_s, None, False, "no readings attached")
        t_echo = arrays[0]
        t_ref = float(lm.ref_t_s) if math.isfinite(lm.ref_t_s) else float(np.max(t_echo))
        prior = self._prior_at(t_ref)
        if prior is None:
            return FusionOutcome(t_ref, None, False, "older than the history")
        i, base, odom_ref, state_ref = prior
        chain = self._echo_chain(arrays, t_ref, odom_ref)
        if chain is None:
            self.stats.outcomes["echo_none"] += 1
            return FusionOutcome(t_ref, None, False, "no reading inside the history")
        assoc: Association | None = None
        eo: EchoObservation | None = None
        if obs is not None:
            assoc = associate(state_ref, obs, self.fmap, self.config.association)
            self.stats.outcomes[assoc.status] += 1
            if assoc.matched and assoc.feature is not None:
                eo = self._echo_for(chain, assoc.kind, assoc.index, _fitted_kappa(lm),
                                    state_ref)
                if eo is None:
                    self.stats.outcomes["echo_outliers"] += 1
        if eo is None:
            found = self._associate_echoes(chain, _fitted_kappa(lm), state_ref)
            if found is None:
                self._rejected(t_ref)
                self.stats.outcomes["echo_unmatched"] += 1
                return FusionOutcome(t_ref, assoc, False, "readings match no map feature")
            eo, assoc = found
            self.stats.outcomes["echo_matched"] += 1
        assert assoc is not None
        gate = ekf.chi2_gate(len(eo), self.config.echo_gate_probability)
        new_state, innov = echoes.update(state_ref, eo, gate)
        if not bool(np.all(innov.accepted)):
            self.stats.outcomes["echo_gated"] += 1
            self._rejected(t_ref)
            return FusionOutcome(t_ref, assoc, False, "readings outside the gate")
        sensor_odom = se2.compose_floats(odom_ref.tolist(), chain[2][-1].tolist())  # latest
        if not self.may_fuse_again(assoc.kind, assoc.index, sensor_odom, t_ref):
            return FusionOutcome(t_ref, assoc, False, NO_MOTION_REASON)
        self.stats.echoes_fused += len(eo)
        return self._insert_fused(i, base, t_ref, odom_ref, new_state, eo, eo.feature, assoc,
                                  sensor_odom)

    def _echo_chain(self, arrays: tuple[Array, ...], t_ref: float, odom_ref: Array
                    ) -> tuple[Array, Array, Array, Array, Array] | None:
        """(t, ranges c·Tm/2, rel, p_fac, v_fac) of a segment's echoes inside the history."""
        t, x, y, yaw, tof = arrays
        keep = (t >= self._times[0]) & (t <= t_ref + 1e-9) & np.isfinite(tof)
        if not keep.any():
            return None
        order = np.argsort(t[keep], kind="stable")
        t, x, y, yaw, tof = (a[keep][order] for a in (t, x, y, yaw, tof))
        base_at = np.array([self._odom_at(float(tk), max(bisect.bisect_right(self._times,
                                                                             float(tk)), 1))
                            for tk in t])
        rel, p_fac, v_fac = echoes.relative_sensor_chain(
            odom_ref, base_at, np.stack([x, y, yaw], axis=-1), self.config.odom_noise)
        return t, 0.5e-6 * self._c_mps * tof, rel, p_fac, v_fac

    def _echo_for(self, chain: tuple[Array, Array, Array, Array, Array],
                  kind: str | None, index: int, fitted_kappa_us: float, state: Gaussian
                  ) -> EchoObservation | None:
        """The chain's readings of map feature (kind, index), screened one by one against
        ``state``, without those another map feature explains as well
        (:func:`~sonarloc.localize.echoes.ambiguous`); None when none is left.
        ``fitted_kappa_us`` (NaN: none) stands in for a map feature without a strength."""
        eo = self._feature_echo(chain, kind, index, fitted_kappa_us)
        eo.linearize(state.mean)
        keep = echoes.screen(state, eo, self.config.echo_screen_probability)
        if not keep.any():
            return None
        eo = eo.subset(keep)
        rivals = [r.subset(keep) for r in self._rivals(chain, kind, index, fitted_kappa_us,
                                                       state)]
        if rivals:
            eo = eo.subset(~echoes.ambiguous(state, eo, rivals,
                                             self.config.echo_screen_probability))
        return eo if len(eo) else None

    def _feature_echo(self, chain: tuple[Array, Array, Array, Array, Array],
                      kind: str | None, index: int, fitted_kappa_us: float
                      ) -> EchoObservation:
        """The chain's readings as measurements of map feature (kind, index)."""
        t, z, rel, p_fac, v_fac = chain
        if kind == "point":
            feat = self.fmap.point(index)
            kap = float(self.fmap.point_kappa_us[index])
        else:
            feat = self.fmap.wall(index)
            kap = float(self.fmap.wall_kappa_us[index])
        if not (math.isfinite(kap) and kap > 0):
            kap = _kappa_fallback(fitted_kappa_us)
        kind_name = self.fmap.point_kind[index] if kind == "point" else \
            self.fmap.wall_kind[index]
        return EchoObservation(z, rel, p_fac, v_fac, kap, feat, float(t[-1]), self._c_mps,
                               kind_name, map_var_m2=self.map_var_m2(kind, index,
                                                                     float(t[-1])))

    def _rivals(self, chain: tuple[Array, Array, Array, Array, Array], kind: str | None,
                index: int, fitted_kappa_us: float, state: Gaussian
                ) -> list[EchoObservation]:
        """The chain's readings as measurements of every *other* map feature that can echo
        towards the segment's last transducer position from about the readings' range
        (geometry only; the same line or point under another index is not a rival)."""
        _, z, rel, _, _ = chain
        cfg = self.config.association
        sensor_xy = se2.transform_points(state.mean, rel[-1, :2])
        pts = np.flatnonzero(self.fmap.points_visible_from(sensor_xy, cfg.max_range_m))
        walls = np.flatnonzero(self.fmap.walls_facing(sensor_xy, cfg.wall_margin_m,
                                                      cfg.max_range_m))
        if kind == "point":
            own = self.fmap.point_xy[index]
            pts = pts[np.hypot(*(self.fmap.point_xy[pts] - own).T) > 1e-3]
        else:
            rho, alpha = self.fmap.wall_line[index]
            lines = self.fmap.wall_line[walls]
            same = (np.abs(lines[:, 0] - rho) <= 1e-3) & \
                (np.abs(se2.wrap_angle(lines[:, 1] - alpha)) <= 1e-3)
            walls = walls[~same]
        if pts.size + walls.size == 0:
            return []
        tol = 0.05 + 4 * math.sqrt(max(state.cov[0, 0] + state.cov[1, 1], 0.0))
        rng_p, rng_w = echoes.feature_ranges(state.mean, rel, self.fmap.point_xy[pts],
                                             self.fmap.point_radius_m[pts],
                                             self.fmap.wall_line[walls])
        near_p = np.any(np.abs(rng_p - z) <= tol, axis=1)
        near_w = np.any(np.abs(rng_w - z) <= tol, axis=1)
        return [self._feature_echo(chain, k, int(i), fitted_kappa_us)
                for k, idx in (("point", pts[near_p]), ("wall", walls[near_w])) for i in idx]

    def _associate_echoes(self, chain: tuple[Array, Array, Array, Array, Array],
                          fitted_kappa_us: float, state: Gaussian
                          ) -> tuple[EchoObservation, Association] | None:
        """Which map feature explains a segment's readings (those the fit could not
        associate): each candidate's readings screened, the stacked squared Mahalanobis
        distance gated; a match needs most readings and no close second."""
        _, z, rel, _, _ = chain
        n = len(z)
        need = max(ECHO_MIN_READINGS, math.ceil(ECHO_MIN_FRACTION * n))
        if n < need:
            return None
        sensor_xy = se2.transform_points(state.mean, rel[-1, :2])
        cfg = self.config.association
        pts = np.flatnonzero(self.fmap.points_visible_from(sensor_xy, cfg.max_range_m))
        walls = np.flatnonzero(self.fmap.walls_facing(sensor_xy, cfg.wall_margin_m,
                                                      cfg.max_range_m))
        # geometry-only pre-selection, all candidates at once: the median range of the
        # readings must be near the candidate's (the delay adds at most ~2 mm)
        tol = 0.05 + 4 * math.sqrt(max(state.cov[0, 0] + state.cov[1, 1], 0.0))
        rng_p, rng_w = echoes.feature_ranges(state.mean, rel, self.fmap.point_xy[pts],
                                             self.fmap.point_radius_m[pts],
                                             self.fmap.wall_line[walls])
        zmed = float(np.median(z))
        cands = [("point", int(k)) for k in pts[np.abs(np.median(rng_p, axis=1) - zmed) <= tol]]
        cands += [("wall", int(k)) for k in walls[np.abs(np.median(rng_w, axis=1) - zmed)
                                                  <= tol]]
        scored: list[tuple[int, float, float, EchoObservation, str, int]] = []
        for kind, k in cands:
            eo = self._echo_for(chain, kind, k, fitted_kappa_us, state)
            if eo is None or len(eo) < need:
                continue
            h, hx, r = eo.measure(state.mean)
            nu = eo.z_m - h
            s = hx @ state.cov @ hx.T + r
            try:
                d2 = float(nu @ np.linalg.solve(s, nu))
                logdet = float(np.linalg.slogdet(s)[1])
            except np.linalg.LinAlgError:
                continue
            if not d2 <= ekf.chi2_gate(len(eo), self.config.echo_gate_probability):
                continue
            scored.append((len(eo), d2, logdet, eo, kind, k))
        if not scored:
            return None
        most = max(sc[0] for sc in scored)
        top = [sc for sc in scored if sc[0] == most]
        ll = np.array([-0.5 * sc[1] - 0.5 * sc[2] for sc in top])
        b = int(np.argmax(ll))
        share = float(1.0 / np.sum(np.exp(ll - ll[b])))
        if share < cfg.min_match_probability:
            return None
        _, d2, _, eo, kind, k = top[b]
        feat = eo.feature
        return eo, Association("matched", "point" if kind == "point" else "wall", k, feat, d2,
                               len(eo), math.nan, len(top), share)

    def _prior_at(self, t_ref: float) -> tuple[int, _Entry, Array, Gaussian] | None:
        """Where ``t_ref`` falls in the history (insertion index, the entry before it), the
        odometry pose there and the belief predicted to it; None (counted ``too_old``) when
        ``t_ref`` is older than the history."""
        i = bisect.bisect_right(self._times, t_ref)
        if i == 0 or t_ref < self._times[-1] - self.config.history_s:
            self.stats.outcomes["too_old"] += 1
            return None
        base = self._entries[i - 1]
        odom_ref = self._odom_at(t_ref, i)
        state_ref = ekf.predict(base.state, se2.between(base.odom, odom_ref),
                                self.config.odom_noise)
        return i, base, odom_ref, state_ref

    def add_observation(self, obs: Observation, t_ref: float) -> FusionOutcome:
        """Associate and fuse an observation of the pose at ``t_ref`` (rewinding if needed)."""
        self.stats.observations += 1
        if self._unknown:
            self.stats.outcomes["relocalizing"] += 1
            return FusionOutcome(t_ref, None, False, "relocalizing: no pose yet")
        prior = self._prior_at(t_ref)
        if prior is None:
            return FusionOutcome(t_ref, None, False, "older than the history")
        i, base, odom_ref, state_ref = prior
        assoc = associate(state_ref, obs, self.fmap, self.config.association)
        self.stats.outcomes[assoc.status] += 1
        if not assoc.matched or assoc.feature is None:
            self._rejected(t_ref)
            return FusionOutcome(t_ref, assoc, False, assoc.status)
        var = self.map_var_m2(assoc.kind, assoc.index, t_ref)
        if var > 0:
            cov = obs.cov.copy()
            if obs.kind == "point":
                cov[:2, :2] += var * np.eye(2)
            else:                         # range (conventional, specular) or rho (line)
                cov[0, 0] += var
            obs = replace(obs, cov=cov)
        new_state, innov = ekf.update(state_ref, obs, assoc.feature, gate_probability=None)
        if not bool(np.all(innov.accepted)):
            self.stats.outcomes["singular"] += 1
            self._rejected(t_ref)
            return FusionOutcome(t_ref, assoc, False, "singular")
        sensor_odom = se2.compose_floats(odom_ref.tolist(), obs.sensor.tolist())
        if not self.may_fuse_again(assoc.kind, assoc.index, sensor_odom, t_ref):
            return FusionOutcome(t_ref, assoc, False, NO_MOTION_REASON)
        return self._insert_fused(i, base, t_ref, odom_ref, new_state, obs, assoc.feature,
                                  assoc, sensor_odom)

    def _insert_fused(self, i: int, base: _Entry, t_ref: float, odom_ref: Array,
                      new_state: Gaussian, obs: Observation | EchoObservation,
                      feature: Feature, assoc: Association, sensor_odom: Sequence[float]
                      ) -> FusionOutcome:
        """Insert a fused belief into the history at ``i`` and replay what follows
        (``sensor_odom``: the transducer pose in ``odom`` it was seen from)."""
        entry = _Entry(max(t_ref, base.t), odom_ref, new_state, obs, feature,
                       frame=base.frame)
        self.note_fused(assoc.kind, assoc.index, sensor_odom, t_ref)
        self._entries.insert(i, entry)
        self._times.insert(i, entry.t)
        self._replay(i + 1)
        self.stats.accepted += 1
        self._consecutive_rejected = 0
        self.confirm(t_ref, str(assoc.kind), assoc.index)
        if self._estimate is not None:
            self._estimate = self._make_estimate(self._estimate.t_s)
        return FusionOutcome(t_ref, assoc, True, "fused")

    def finish(self) -> list[FusionOutcome]:
        """End of stream: fuse what the fitter still holds (readings later than the last
        odometry are counted in ``stats.skipped["tof_after_last_odom"]``)."""
        out: list[FusionOutcome] = []
        if self._entries:
            self._drain_pending(self._last_odom_t)
        if self._pending:
            self.stats.skipped[self._no_odom_after()] += len(self._pending)
            self._pending.clear()
        out += self._flush_source()
        out += self._drain_fits()
        return out

    def _no_odom_after(self) -> str:
        """Counter of readings no odometry came after: past the last odometry, or, with
        none since the prior, before any (one name online and in batch)."""
        return "tof_after_last_odom" if math.isfinite(self._odom_start_t) else "tof_before_odom"

    def _too_old(self, t_s: float) -> str:
        """Counter of a reading older than the history's first entry: before the first
        odometry since the prior (no pose at all), or trimmed from the history."""
        return "tof_older_than_history" if t_s >= self._odom_start_t else "tof_before_odom"

    # -- queries --------------------------------------------------------------------

    @property
    def estimate(self) -> PoseEstimate | None:
        """The latest estimate (after the last odom record), or None before the prior."""
        return self._estimate

    @property
    def history_len(self) -> int:
        return len(self._entries)

    @property
    def relocalization(self) -> Relocalization | None:
        """The latest relocalization attempt (None: none yet, or ``relocalize`` off)."""
        return None if self._reloc is None else self._reloc.last

    # -- internals ------------------------------------------------------------------

    def may_fuse_again(self, kind: str | None, index: int, sensor_odom: Sequence[float],
                       t_ref: float) -> bool:
        """Whether an observation of map feature (``kind``, ``index``) that would be fused
        (associated, inside the gate), seen from transducer pose ``sensor_odom`` (x, y,
        yaw in ``odom`` at its reference time ``t_ref``), may be: it differs enough from
        every pose that feature was fused from lately (:data:`FUSED_POSES_KEPT` of them;
        :func:`moved_enough`, ``LocalizerConfig.update_min_d`` / ``update_min_a``).
        If not, the observation is counted (``skipped["no_motion_since_fused"]``) and
        taken as a confirmation of the pose for the status, as a fused one would be."""
        c = self.config
        seen = self._fused_at.get((str(kind), index))
        if seen is None or not seen.near(sensor_odom, c.update_min_d, c.update_min_a):
            return True
        self.stats.skipped["no_motion_since_fused"] += 1
        self._consecutive_rejected = 0
        self.confirm(t_ref, str(kind), index)
        return False

    def confirm(self, t_s: float, kind: str, index: int) -> None:
        """Record that map feature (``kind`` ``"point"`` or ``"wall"``, ``index`` into
        the map's points or walls) confirmed the pose at ``t_s`` [s]: it was fused, or
        would have been (:meth:`may_fuse_again`); ``kind``
        :data:`~sonarloc.localize.confirmed.POSE` (index -1): a fix of the whole pose (a
        relocalization). The status is ``tracking`` only while the features confirmed in
        the last ``dead_reckoning_after_s`` pin all three degrees of freedom
        (:func:`~sonarloc.localize.confirmed.missing_dof`)."""
        self._confirmed.add(t_s, kind, index)

    def map_var_m2(self, kind: str | None, index: int, t_s: float = math.nan) -> float:
        """Variance [m²] of map feature (``kind``, ``index``)'s position as one update at
        ``t_s`` [s] takes it: the larger of its SD (``sd_rel_m`` or else ``sd_m``, if the
        map gives one) and ``LocalizerConfig.map_sd_m``, squared, times one plus the
        feature's recent fusions (:meth:`map_uses`; none with ``t_s`` NaN)."""
        sd = self.fmap.sd_m(kind, index)
        var = max(sd if math.isfinite(sd) else 0.0, self.config.map_sd_m) ** 2
        if var > 0 and math.isfinite(t_s):
            var *= 1.0 + self.map_uses(kind, index, t_s)
        return var

    def map_var_all(self, t_s: float = math.nan) -> Array:
        """(P + W,) :meth:`map_var_m2` of every point, then every wall, at ``t_s``."""
        sd = np.concatenate([self.fmap.point_sd_m, self.fmap.wall_sd_m])
        var = np.maximum(np.where(np.isfinite(sd), sd, 0.0), self.config.map_sd_m) ** 2
        if math.isfinite(t_s):
            var = var * (1.0 + self._uses_all(t_s))
        return var

    def map_var_grown_m2(self, t_s: float) -> Array | None:
        """(P + W,) what the features' recent fusions add to their map variances at
        ``t_s`` [s] (:meth:`map_var_m2` at ``t_s`` less without fusions; the batch
        replay's share of :meth:`map_uses`); None where nothing can grow
        (``map_error_memory_s`` 0, or no map error)."""
        if self.config.map_error_memory_s <= 0 or not self._map_base_var.any():
            return None
        return self.map_var_all(t_s) - self._map_base_var

    def map_uses(self, kind: str | None, index: int, t_s: float) -> float:
        """How many times map feature (``kind``, ``index``) was fused lately, as seen at
        ``t_s`` [s]: each fusion counts ``exp(-age / map_error_memory_s)`` (0 without a
        map error: ``map_var_all`` 0). A feature's position error is one constant that
        every reading of it shares: fused ``n`` times within the pose's memory, its
        variance taken ``1 + n`` times larger keeps the information the pose draws
        from it about ``1 / var`` rather than ``n / var``."""
        k = self.feature_slot(kind, index)
        n = float(self._map_n[k])
        if n == 0.0:
            return 0.0
        age = max(t_s - float(self._map_t[k]), 0.0)
        return n * math.exp(-age / self.config.map_error_memory_s)

    def feature_slot(self, kind: str | None, index: int) -> int:
        """Index of map feature (``kind``, ``index``) among the points, then the walls
        (:meth:`map_var_all`)."""
        return index + (self.fmap.n_points if kind == "wall" else 0)

    def _uses_all(self, t_s: float) -> Array:
        """(P + W,) :meth:`map_uses` of every point, then every wall."""
        if not self._map_n.any():
            return np.zeros_like(self._map_n)
        age = np.maximum(t_s - self._map_t, 0.0)
        return self._map_n * np.exp(-age / self.config.map_error_memory_s)

    def note_fused(self, kind: str | None, index: int, sensor_odom: Sequence[float],
                   t_s: float = math.nan) -> None:
        """Remember that map feature (``kind``, ``index``) was fused from transducer pose
        ``sensor_odom`` (in ``odom``; :meth:`may_fuse_again`) at ``t_s`` [s]
        (:meth:`map_uses`)."""
        key = (str(kind), index)
        seen = self._fused_at.get(key)
        if seen is None:
            seen = self._fused_at[key] = _FusedPoses()
        seen.add(sensor_odom)
        k = self.feature_slot(kind, index)
        if self.config.map_error_memory_s > 0 and self._map_base_var[k] > 0 and \
                math.isfinite(t_s):
            t_new = max(t_s, float(self._map_t[k]))
            self._map_n[k] = self.map_uses(kind, index, t_new) + 1.0
            self._map_t[k] = t_new

    def _forget_uses(self) -> None:
        self._map_n[:] = 0.0

    def _rejected(self, t_ref: float) -> None:
        if self._consecutive_rejected == 0:
            self._reject_start_t = t_ref
        self._consecutive_rejected += 1

    def _maybe_relocalize(self, t: float, odom: Array) -> None:
        """Lost (or no prior): try a global relocalization; restart the filter at a fix."""
        assert self._reloc is not None
        if not self._reloc.due(t):
            return
        if not self._unknown:
            status, _ = self._status(t, self._entries[-1].state)
            if status != "lost":
                return
            if math.isfinite(self._reject_start_t):
                # fits from before the trouble began may come from elsewhere (a kidnap)
                self._reloc.forget_before(self._reject_start_t - 1.0)
        r = self._reloc.solve(t)
        self.stats.relocalization[r.status] += 1
        if not r.found:
            return
        pose, cov = r.pose_in_map(odom)
        cov = ekf.symmetrize(cov + np.diag([0.01**2, 0.01**2, math.radians(0.5) ** 2]))
        self._entries[:] = [_Entry(t, odom, Gaussian(pose, cov), frame=self.odom_joiner.frame)]
        self._times[:] = [t]
        self._fused_at.clear()
        self._forget_uses()
        self._unknown = False
        self._consecutive_rejected = 0
        self._reject_start_t = math.nan
        self._confirmed.clear()
        self.confirm(t, POSE, -1)

    def _append(self, e: _Entry) -> None:
        if not math.isfinite(self._odom_start_t):
            self._odom_start_t = e.t
        self._entries.append(e)
        self._times.append(e.t)

    def _trim(self) -> None:
        horizon = self._times[-1] - self.config.history_s
        k = bisect.bisect_left(self._times, horizon)
        k = min(k, len(self._entries) - 1)
        if k > 64 or (k > 0 and len(self._entries) > 4096):
            del self._entries[:k]
            del self._times[:k]

    def _odom_at(self, t: float, i: int) -> Array:
        """Odometry pose at time t, given entries[i-1].t <= t < entries[i].t (or i = len)."""
        a = self._entries[i - 1]
        if i >= len(self._entries) or t <= a.t:
            return a.odom
        b = self._entries[i]
        span = b.t - a.t
        if span <= 0:
            return a.odom
        f = (t - a.t) / span  # linear in x, y; the short way round in yaw
        ax, ay, ath = (float(v) for v in a.odom)
        bx, by, bth = (float(v) for v in b.odom)
        dth = (bth - ath + math.pi) % (2.0 * math.pi) - math.pi
        yaw = (ath + f * dth + math.pi) % (2.0 * math.pi) - math.pi
        return np.array([ax + f * (bx - ax), ay + f * (by - ay), yaw])

    def _replay(self, start: int) -> None:
        noise = self.config.odom_noise
        for j in range(start, len(self._entries)):
            prev, e = self._entries[j - 1], self._entries[j]
            state = self.reset_state(prev.state) if e.reset else \
                ekf.predict(prev.state, se2.between(prev.odom, e.odom), noise)
            if isinstance(e.obs, EchoObservation):
                state, _ = echoes.update(state, e.obs)
            elif e.obs is not None and e.feature is not None:
                state, _ = ekf.update(state, e.obs, e.feature, gate_probability=None)
            e.state = state
            self.stats.replayed_steps += 1

    def _drain_pending(self, t_odom: float) -> None:
        if not self._pending:
            return
        ready = [r for r in self._pending if r.t_s <= t_odom]
        if not ready:
            return
        self._pending = deque(r for r in self._pending if r.t_s > t_odom)
        # in time order (stable: arrival order among equal times), so a reading that came
        # just after a later one (two drivers, two queues) still reaches the segmenter,
        # which drops readings older than the last
        ready.sort(key=operator.attrgetter("t_s"))
        for r in ready:
            self._process_tof(r)

    def _in_odom_gap(self, t: float, i: int) -> bool:
        """Whether ``t`` (entries[i-1].t <= t < entries[i].t, or i = len) lies strictly
        inside an odometry gap the robot moved across (``LocalizerConfig.odom_gap_s``)."""
        if i >= len(self._entries):
            return False
        a, b = self._entries[i - 1], self._entries[i]
        return in_odom_gap(t, a.t, a.odom, b.t, b.odom, self.config.odom_gap_s)

    def _transducer_pose(self, t: float, i: int, sensor: int, pan_deg: float | None
                         ) -> tuple[Array, Array]:
        """(base_link pose in odom at t, transducer pose in base_link); ``i`` as in
        :meth:`_odom_at`."""
        base = self._odom_at(t, i)
        mount = self._mounts[sensor]
        if pan_deg is not None:
            mount = np.array([mount[0], mount[1], mount[2] + math.radians(pan_deg)])
        return base, mount

    def _process_tof(self, r: TofRecord) -> None:
        if self.config.method == "odometry":
            return
        if r.t_s < self._times[0]:
            self.stats.skipped[self._too_old(r.t_s)] += 1
            return
        i = max(bisect.bisect_right(self._times, r.t_s), 1)
        if i < len(self._entries) and self._entries[i].reset and \
                r.t_s > self._entries[i - 1].t:
            self.stats.skipped["tof_across_odom_reset"] += 1   # no pose between the two
            return
        if self._in_odom_gap(r.t_s, i):
            self.stats.skipped["tof_in_odom_gap"] += 1
            return
        base, mount = self._transducer_pose(r.t_s, i, r.sensor, r.pan_deg)
        if self.config.method in ("conventional", "specular"):
            if r.tof_us is None or not (r.tof_us > 0):
                return
            rng = 0.5e-6 * self._c_mps * r.tof_us
            if rng > self.config.max_range_m:
                return
            kind: Literal["range_axis", "range_bearing"] = \
                "range_axis" if self.config.method == "conventional" else "range_bearing"
            self.add_observation(Observation(kind, np.array([rng, 0.0]), self._conv_cov,
                                             mount, t_s=r.t_s), r.t_s)
            return
        if self._source is None:
            n = self.segment_max_readings(r.pan_deg is not None)
            if self._source_factory is not None:
                self._source = self._source_factory(self._c_mps)
                if isinstance(self._source, SegmentFitSource) and \
                        self._source.max_readings is None:
                    self._source.max_readings = n
                if isinstance(self._source, SegmentFitSource) and \
                        self._source.min_echoes is None:
                    self._source.min_echoes = self.segment_min_echoes
                if isinstance(self._source, SegmentFitSource) and \
                        self._source.sweep_away_deg is None:
                    self._source.sweep_away_deg = \
                        self.segment_sweep_away_deg(r.pan_deg is not None)
            else:
                self._source = SegmentFitSource(
                    self._c_mps, max_readings=n, min_echoes=self.segment_min_echoes,
                    sweep_away_deg=self.segment_sweep_away_deg(r.pan_deg is not None))
        if isinstance(self._source, SegmentFitSource):
            if r.t_s < self._last_pushed_t:  # the segmenter would drop it: say so
                self.stats.skipped["tof_out_of_order"] += 1
                return
            self._last_pushed_t = r.t_s
        bx, by, bth = (float(v) for v in base)
        mx, my, mth = (float(v) for v in mount)
        c, s = math.cos(bth), math.sin(bth)
        px, py, pth = bx + c * mx - s * my, by + s * mx + c * my, bth + mth  # base ⊕ mount
        tof = math.nan if r.tof_us is None else float(r.tof_us)
        if self._pool is not None and isinstance(self._source, SegmentFitSource):
            self._submit(self._source, self._source.take(r.t_s, px, py, pth, tof, r.sensor),
                         r.t_s)
            return
        for lm in self._source.push(r.t_s, px, py, pth, tof, r.sensor):
            self.add_landmark(lm)

    def _landmark_observation(self, lm: Landmark) -> Observation | None:
        """A fitted landmark (odom frame) as an observation relative to base_link at ref."""
        p = np.asarray(lm.params, dtype=float)
        cov = np.asarray(lm.cov, dtype=float)
        if p.shape != (3,) or cov.shape != (3, 3) or not (np.all(np.isfinite(p))
                                                          and np.all(np.isfinite(cov))):
            return None
        if lm.ref_t_s < self._times[0] - 1e-9:
            return None
        i = max(bisect.bisect_right(self._times, lm.ref_t_s), 1)
        base = self._odom_at(lm.ref_t_s, i)
        ref_pose = np.asarray(lm.ref_pose, dtype=float)
        sensor = se2.between(base, ref_pose)
        view = lm.extra.get("view_xy")
        if isinstance(view, tuple) and len(view) == 2:
            # a cylinder's fitted surface point faces where its echoes came from
            sensor[:2] = se2.inverse_transform_points(base, np.asarray(view, dtype=float))
        c = self.config
        pos = cov[:2, :2] * c.fit_cov_scale
        if lm.kind == "point":
            z = se2.inverse_transform_points(base, p[:2])
            ct, st = math.cos(base[2]), math.sin(base[2])
            rot_t = np.array([[ct, st], [-st, ct]])
            r = rot_t @ pos @ rot_t.T + np.eye(2) * c.fit_sd_floor_m**2
            kind: Literal["point", "line"] = "point"
        else:
            z = se2.inverse_transform_line(base, p[:2])
            alpha = p[1]
            rho_b = p[0] - base[0] * math.cos(alpha) - base[1] * math.sin(alpha)
            sign = -1.0 if rho_b < 0 else 1.0
            j = np.array([[sign, sign * (base[0] * math.sin(alpha) - base[1] * math.cos(alpha))],
                          [0.0, 1.0]])
            r = j @ pos @ j.T + np.diag([c.fit_sd_floor_m**2,
                                         math.radians(c.fit_sd_floor_deg) ** 2])
            kind = "line"
        r = 0.5 * (r + r.T)
        return Observation(kind, z, r, sensor, float(p[2]), float(cov[2, 2]), lm.ref_t_s)

    def _status(self, t: float, state: Gaussian) -> tuple[Status, str]:
        c = self.config
        cov = state.cov                 # (3, 3): items 0 and 4 are the x and y variances
        if not (np.isfinite(cov).all() and np.isfinite(state.mean).all()):
            return "lost", "the estimate is not finite"   # never reported as good
        sd = math.sqrt(max(cov.item(0), cov.item(4), 0.0))
        if sd > c.lost_sd_m:
            return "lost", f"position SD {sd:.2f} m exceeds {c.lost_sd_m:g} m"
        if self._consecutive_rejected >= c.lost_after_rejections:
            reason = (f"{self._consecutive_rejected} observations in a row rejected by the "
                      f"map")
            if self._reloc is not None and self._reloc.last is not None and \
                    not self._reloc.last.found:
                reason += f"; relocalization: {self._reloc.last.reason}"
            return "lost", reason
        window = c.dead_reckoning_after_s
        if not math.isfinite(self._confirmed.newest_s):
            since = t - self._start_t
            if since <= window:     # the prior is what the landmarks have to confirm
                return "dead_reckoning", f"no landmark fused yet ({since:.1f} s since " \
                    f"the prior)"
            return "dead_reckoning", f"no landmark fused for {since:.1f} s"
        since = t - self._confirmed.newest_s
        if since > window:
            return "dead_reckoning", f"no landmark fused for {since:.1f} s"
        recent = self._confirmed.recent(t - window)
        if recent != self._dof_memo[0]:  # (the same few features for many odom records)
            self._dof_memo = (recent, missing_dof(self.fmap, recent, window))
        missing = self._dof_memo[1]
        if missing:
            return "dead_reckoning", missing
        return "tracking", "ok"

    def _make_estimate(self, t_s: float) -> PoseEstimate:
        last = self._entries[-1]
        status, reason = self._status(last.t, last.state)
        odom = last.odom if last.frame is None else np.array(raw_pose(last.odom.tolist(),
                                                                      last.frame))
        m2o = se2.compose(last.state.mean, se2.inverse(odom))
        return PoseEstimate(t_s, last.state, odom, m2o, status, reason)

    def reset_state(self, state: Gaussian) -> Gaussian:
        """The belief across an odometry reset or jump: ``state`` kept, its covariance
        grown by ``LocalizerConfig.odom_reset_sd_m`` / ``odom_reset_sd_deg``."""
        return Gaussian(state.mean, ekf.symmetrize(state.cov + self._reset_cov))

    def _odom_restart(self, restart: Restart) -> Gaussian:
        """An odometry reset or jump (online): counted; the segments the fitter holds
        open are closed, fitted and fused (their readings are in the old odometry's
        stretch); returns the belief across it (:meth:`reset_state` of the latest)."""
        if restart == "reset":
            self.stats.odom_resets += 1
        else:
            self.stats.odom_jumps += 1
        if self._source is not None:
            self._flush_source()
            if not isinstance(self._source, SegmentFitSource):
                self._source = None   # a LandmarkSource's flush ends its stream
        return self.reset_state(self._entries[-1].state)


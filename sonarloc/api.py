"""Embedding sonarloc in a robot's software (a ROS node, a control loop): one object.

:class:`LocalizerNode` wraps the :class:`~sonarloc.localize.localizer.Localizer` (online
segmentation and fitting of the TOF curves, EKF against a map) behind the calls a node
makes: feed readings and odometry as they arrive, read pose, covariance, the
``map -> odom`` transform, recent landmarks and the status. Units are SI, angles in
radians, frames per REP-105 (``map``, ``odom``, ``base_link``). See docs/API.md.

>>> from sonarloc.api import LocalizerNode
>>> node = LocalizerNode.from_map_file("maps/room.geojson",
...                                    sensors=[(0, 0.2, 0.0, 0.0), (1, 0.0, 0.2, 90.0)])
>>> node.set_pose(1.0, 1.0, 0.0, sd_xy_m=0.05, sd_yaw_rad=0.03)
>>> est = node.odometry(0.00, 0.0, 0.0, 0.0)
>>> est.status, est.reason    # `tracking` once landmarks pin x, y and yaw
('dead_reckoning', 'no landmark fused yet (0.0 s since the prior)')
>>> node.reading(0.01, sensor=0, tof_us=40_000.0)   # an echo 6.9 m ahead
>>> node.reading(0.04, sensor=1, tof_us=None)       # no echo
>>> round(node.pose[0], 3), node.covariance.shape
(1.0, (3, 3))
"""

from __future__ import annotations

import math
import numbers
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarloc.fit.result import Landmark
from sonarloc.io.logfile import InitRecord, Record, SensorMount
from sonarloc.localize.features import FeatureMap
from sonarloc.localize.localizer import (
    FusionOutcome,
    LandmarkSource,
    Localizer,
    LocalizerConfig,
    PoseEstimate,
)


@dataclass(frozen=True)
class LandmarkReport:
    """A fitted landmark as the node saw it.

    ``landmark``: the fit in ``odom`` (:class:`~sonarloc.fit.result.Landmark`: kind,
    params, cov, kappa_us, status, reference time and pose). ``in_map``: the same moved
    into ``map`` with the estimate of ``map -> odom`` when the landmark was fused (None
    before the first estimate). ``fused``: matched to a map feature and used by the filter;
    ``outcome``: why not, otherwise (``gated``, ``ambiguous``, ``no_candidate``, fit
    status, ...).
    """

    landmark: Landmark
    in_map: Landmark | None
    fused: bool
    outcome: str


def _real(name: str, v: object) -> float:
    """``v`` as a float; ValueError unless it is a real number (int, float, a NumPy
    scalar; not a bool, a string, None or an array: a call with those is a bug in the
    caller, not a fault of the data). Non-finite values pass: they are data faults,
    skipped and counted by the Localizer."""
    if isinstance(v, bool) or not isinstance(v, numbers.Real):
        raise ValueError(f"`{name}` must be a real number, got {v!r}")
    return float(v)


def _sensor_id(v: object) -> int:
    """A sensor id as an int; ValueError unless it is an integer (not a bool, a float
    or a string: ``True`` would silently be sensor 1)."""
    if isinstance(v, bool) or not isinstance(v, numbers.Integral):
        raise ValueError(f"`sensor` must be an integer id, got {v!r}")
    return int(v)


class _HookedLocalizer(Localizer):
    """A Localizer that tells the node about every landmark it was given."""

    def __init__(self, *args: Any, on_landmark: Callable[[Landmark, FusionOutcome], None],
                 **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._on_landmark = on_landmark

    def add_landmark(self, lm: Landmark) -> FusionOutcome:
        out = super().add_landmark(lm)
        self._on_landmark(lm, out)
        return out


class LocalizerNode:
    """Pose of a robot from sonar readings and wheel odometry against a map.

    Parameters
    ----------
    fmap : the map's features (``FeatureMap.from_map(load_map(path))``), or use
        :meth:`from_map_file`.
    sensors : transducer mounts in ``base_link``: ``(id, x_m, y_m, yaw_deg)`` tuples or
        :class:`~sonarloc.io.logfile.SensorMount`; may also come later with
        :meth:`set_rig` or a ``rig`` record.
    speed_of_sound_mps : the speed of sound (343 m/s at 20 °C).
    config : :class:`~sonarloc.localize.localizer.LocalizerConfig` (method, noise,
        gates, status thresholds; ``fit_workers`` to fit in the background, then
        :meth:`close` the node or use it in a ``with`` block).
    keep_landmarks : how many recent :class:`LandmarkReport` to keep (memory is bounded).
    landmark_source : advanced: a factory ``(speed_of_sound_mps) -> LandmarkSource`` to
        replace the built-in online fitter.
    """

    def __init__(self, fmap: FeatureMap, sensors: Iterable[SensorMount | Sequence[float]] = (),
                 *, speed_of_sound_mps: float = 343.0, config: LocalizerConfig | None = None,
                 keep_landmarks: int = 500,
                 landmark_source: Callable[[float], LandmarkSource] | None = None) -> None:
        if keep_landmarks < 0:
            raise ValueError(f"`keep_landmarks` must be >= 0, got {keep_landmarks!r}")
        self._reports: deque[LandmarkReport] = deque(maxlen=keep_landmarks or None)
        self._keep = keep_landmarks > 0
        self.localizer = _HookedLocalizer(fmap, config, landmark_source=landmark_source,
                                          on_landmark=self._landmark)
        mounts = [self._mount(s) for s in sensors]
        if mounts:
            self.set_rig(mounts, speed_of_sound_mps)

    @classmethod
    def from_map_file(cls, path: str | Path, sensors: Iterable[SensorMount | Sequence[float]]
                      = (), **kwargs: Any) -> LocalizerNode:
        """A node for the map GeoJSON at ``path`` (FORMATS.md section 3)."""
        from sonarloc.maps.geojson import load_map

        return cls(FeatureMap.from_map(load_map(path)), sensors, **kwargs)

    # -- inputs ---------------------------------------------------------------------------

    @staticmethod
    def _mount(s: SensorMount | Sequence[float]) -> SensorMount:
        if isinstance(s, SensorMount):
            return s
        if len(s) != 4:
            raise ValueError(f"a sensor must be (id, x_m, y_m, yaw_deg), got {s!r}")
        sid = s[0]
        if isinstance(sid, bool) or not float(sid).is_integer():
            raise ValueError(f"sensor id must be an integer, got {sid!r}")
        return SensorMount(int(sid), float(s[1]), float(s[2]), float(s[3]))

    def set_rig(self, sensors: Iterable[SensorMount | Sequence[float]],
                speed_of_sound_mps: float = 343.0) -> None:
        """Transducer mounts in ``base_link`` and the speed of sound."""
        self.localizer.set_rig([self._mount(s) for s in sensors], speed_of_sound_mps)

    def set_pose(self, x_m: float, y_m: float, yaw_rad: float, *, sd_xy_m: float = 0.1,
                 sd_yaw_rad: float = math.radians(5.0), t_s: float = math.nan) -> None:
        """Prior of ``base_link`` in ``map`` (e.g. rviz's "2D Pose Estimate");
        (re)starts the filter at the next odometry message, whose time may be earlier
        than the last one's (a restarted clock). ValueError for a non-finite pose or
        time (``t_s`` NaN: unknown) or a non-positive SD: a prior like that would
        corrupt every later estimate."""
        for name, v in (("x_m", x_m), ("y_m", y_m), ("yaw_rad", yaw_rad)):
            if not math.isfinite(_real(name, v)):
                raise ValueError(f"`{name}` must be finite, got {v!r}")
        for name, v in (("sd_xy_m", sd_xy_m), ("sd_yaw_rad", sd_yaw_rad)):
            if not (math.isfinite(_real(name, v)) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        if math.isinf(_real("t_s", t_s)):
            raise ValueError(f"`t_s` must be finite (or NaN: unknown), got {t_s!r}")
        self.localizer.set_prior(t_s, x_m, y_m, yaw_rad, sd_xy_m, sd_yaw_rad)

    def odometry(self, t_s: float, x_m: float, y_m: float, yaw_rad: float,
                 reset: bool = False) -> PoseEstimate | None:
        """Wheel odometry: pose of ``base_link`` in ``odom`` at ``t_s`` (integrated).

        Returns the new estimate (None before :meth:`set_pose`). A message older than
        the last one, or with a NaN or infinite value, is skipped (counted in
        ``stats.skipped``: ``odom_time_backwards``, ``bad_odom``) and the current
        estimate returned. ``reset=True``: the odometry restarted (the base controller
        rebooted; this pose begins a new odometry frame): the pose estimate is kept
        across it, not moved by the difference (``stats.odom_resets``; an unflagged
        jump faster than ``LocalizerConfig.odom_max_speed_mps`` or
        ``odom_max_yaw_rate_rad_s`` is taken as one too, ``stats.odom_jumps``), and
        ``map_to_odom`` follows the new frame. ValueError if an argument is not a real
        number, or ``reset`` not a bool.
        """
        if not isinstance(reset, (bool, np.bool_)):
            raise ValueError(f"`reset` must be a bool, got {reset!r}")
        return self.localizer.on_odom(_real("t_s", t_s), _real("x_m", x_m), _real("y_m", y_m),
                                      _real("yaw_rad", yaw_rad), bool(reset))

    def reading(self, t_s: float, sensor: int, tof_us: float | None,
                pan_rad: float | None = None) -> None:
        """One sonar reading: first-echo time of flight in µs (None = no echo).

        Readings are processed once odometry has reached their time (so the transducer
        pose is interpolated, never extrapolated), in time order. A garbage reading is
        skipped and counted in ``stats.skipped``: an unknown sensor (``unknown_sensor``),
        a NaN or infinite time or pan angle, a zero, negative or infinite TOF
        (``bad_tof``), one older than a reading already used (``tof_out_of_order``).
        ValueError if an argument has the wrong type (``sensor`` not an integer, a value
        not a real number).
        """
        self.localizer.on_tof(_real("t_s", t_s), _sensor_id(sensor),
                              None if tof_us is None else _real("tof_us", tof_us),
                              None if pan_rad is None else _real("pan_rad", pan_rad))

    def feed(self, rec: Record) -> PoseEstimate | None:
        """A log record or a record from a driver (:func:`sonarloc.io.drivers.open_driver`):
        rig, init, odom and tof are used, truth is ignored; data faults in them are
        skipped and counted as in :meth:`reading` and :meth:`odometry`, a non-finite
        init raises as :meth:`set_pose` does. ValueError for anything but a record."""
        if not isinstance(rec, Record):
            raise ValueError(f"`feed` takes a sonarloc.io.logfile record (rig, init, odom, "
                             f"tof, truth), got {type(rec).__name__}")
        if isinstance(rec, InitRecord):
            sd_xy, sd_yaw = rec.prior_sds()
            self.set_pose(rec.x_m, rec.y_m, math.radians(rec.yaw_deg), sd_xy_m=sd_xy,
                          sd_yaw_rad=sd_yaw, t_s=rec.t_s)
            return None
        return self.localizer.handle(rec)

    def finish(self) -> None:
        """End of stream: fit and fuse what the online fitter still holds (with
        ``LocalizerConfig.fit_workers``: waits for the fits in flight and fuses them)."""
        self.localizer.finish()

    def warm_up(self) -> None:
        """Build the landmark fitter's and the fusion's tables before the first reading
        (see :meth:`Localizer.warm_up`): call it once while the robot starts up, so the
        first call that fits and fuses is not the slowest of the run."""
        self.localizer.warm_up()

    def close(self) -> None:
        """Stop the background fit workers (``LocalizerConfig.fit_workers``; nothing to do
        without them). Fits still in flight are dropped (counted in
        ``stats.skipped["fit_dropped_at_close"]``): call :meth:`finish` first to fuse
        them. ``with LocalizerNode(...) as node:`` closes the node on leaving."""
        self.localizer.close()

    def __enter__(self) -> LocalizerNode:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- outputs --------------------------------------------------------------------------

    @property
    def estimate(self) -> PoseEstimate | None:
        """The latest :class:`~sonarloc.localize.localizer.PoseEstimate` (or None)."""
        return self.localizer.estimate

    def _require(self) -> PoseEstimate:
        est = self.localizer.estimate
        if est is None:  # say why, and what brings one (a node relocalizing needs no prior)
            how = ("wait for relocalization's fix, or call set_pose()"
                   if self.localizer.config.relocalize else "call set_pose() and odometry() first")
            raise RuntimeError(f"no estimate yet ({self.reason}): {how}")
        return est

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x_m, y_m, yaw_rad) of ``base_link`` in ``map``."""
        est = self._require()
        return est.x_m, est.y_m, est.yaw_rad

    @property
    def covariance(self) -> NDArray[np.float64]:
        """(3, 3) covariance of (x, y, yaw) [m², m·rad, rad²]."""
        return np.array(self._require().state.cov, dtype=float)

    @property
    def map_to_odom(self) -> tuple[float, float, float]:
        """Pose of ``odom`` in ``map`` (x_m, y_m, yaw_rad): the transform a node broadcasts."""
        x, y, yaw = (float(v) for v in self._require().map_to_odom)
        return x, y, yaw

    @property
    def status(self) -> str:
        """``initializing``, ``tracking``, ``dead_reckoning`` or ``lost``."""
        est = self.localizer.estimate
        return "initializing" if est is None else est.status

    @property
    def reason(self) -> str:
        """Why the status is what it is (e.g. "no landmark fused for 6.2 s")."""
        est = self.localizer.estimate
        if est is None:
            reloc = self.localizer.relocalization
            if reloc is not None:  # started without a prior (config relocalize=True)
                return f"relocalizing: {reloc.reason}"
            return "no prior or no odometry yet"
        return est.reason

    def landmarks(self, since_t_s: float = -math.inf) -> list[LandmarkReport]:
        """Recent fitted landmarks (reference time >= ``since_t_s``), oldest first."""
        return [r for r in self._reports if r.landmark.ref_t_s >= since_t_s]

    @property
    def stats(self) -> Any:
        """Counters of the Localizer (odom, tof, landmarks, fused, rejections, and in
        ``skipped`` the inputs dropped, by reason; ``stats.summary()`` says it in a line)."""
        return self.localizer.stats

    def _landmark(self, lm: Landmark, outcome: FusionOutcome) -> None:
        if not self._keep:
            return
        est = self.localizer.estimate
        in_map = lm.transformed(est.map_to_odom) \
            if est is not None else None
        self._reports.append(LandmarkReport(lm, in_map, outcome.fused, outcome.reason))

"""A differential-drive robot following a route, and its wheel odometry.

The true pose (``base_link`` in ``map``) and the odometry pose (``base_link`` in
``odom``, REP-105: starts at 0, 0, 0 and drifts) are kept apart. Odometry integrates
*measured* wheel travel with the *believed* wheelbase, so it has the classic
systematic errors -- unequal wheel scale (heading drift on straight runs) and a
wheelbase error (heading error proportional to the angle turned) -- plus random
wheel-travel noise growing with the square root of the distance. All randomness comes
from a seeded generator.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from shapely.geometry import LineString


@dataclass(frozen=True)
class Pose2:
    """A planar pose: position [m] and heading [rad, CCW from +x]."""

    x: float
    y: float
    yaw: float

    @property
    def yaw_deg(self) -> float:
        """Heading in degrees, wrapped to (-180, 180]."""
        d = math.degrees(math.atan2(math.sin(self.yaw), math.cos(self.yaw)))
        return 180.0 if d == -180.0 else d

    def compose(self, x_m: float, y_m: float, yaw_rad: float) -> Pose2:
        """This pose followed by a relative pose given in this pose's frame."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return Pose2(self.x + c * x_m - s * y_m, self.y + s * x_m + c * y_m, self.yaw + yaw_rad)


class Route:
    """A polyline to follow, parametrised by arc length (closed if first == last point).

    Parameters
    ----------
    coords : (n, 2) vertices [m], at least two distinct.
    """

    def __init__(self, coords: NDArray[np.float64] | LineString):
        pts = np.asarray(coords.coords if isinstance(coords, LineString) else coords, float)
        if pts.ndim != 2 or pts.shape[1] < 2 or pts.shape[0] < 2:
            raise ValueError(f"`coords` must be (n>=2, 2) route vertices, got shape {pts.shape}")
        pts = pts[:, :2]
        if not np.all(np.isfinite(pts)):
            raise ValueError("route vertices must be finite")
        seg = np.hypot(*np.diff(pts, axis=0).T)
        keep = np.r_[True, seg > 1e-9]
        self.points = pts[keep]
        if len(self.points) < 2:
            raise ValueError("a route needs two distinct points")
        seg = np.hypot(*np.diff(self.points, axis=0).T)
        self.s = np.r_[0.0, np.cumsum(seg)]
        self.length = float(self.s[-1])
        self.closed = bool(np.hypot(*(self.points[0] - self.points[-1])) < 1e-6)

    def _wrap_s(self, s: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.mod(s, self.length) if self.closed else np.clip(s, 0.0, self.length)

    def points_at(self, s: NDArray[np.float64]) -> NDArray[np.float64]:
        """Points (..., 2) at arc lengths ``s`` (wrapping on a closed route, else clamped)."""
        w = self._wrap_s(np.asarray(s, dtype=float))
        j = np.clip(np.searchsorted(self.s, w, side="right") - 1, 0, len(self.s) - 2)
        f = (w - self.s[j]) / (self.s[j + 1] - self.s[j])
        return self.points[j] + f[..., None] * (self.points[j + 1] - self.points[j])

    def point_at(self, s: float) -> tuple[float, float]:
        """Point at arc length ``s``."""
        p = self.points_at(np.asarray(s, dtype=float))
        return float(p[0]), float(p[1])

    def heading_at(self, s: float) -> float:
        """Direction of the route at arc length ``s`` [rad]."""
        w = float(self._wrap_s(np.asarray(s, dtype=float)))
        j = int(np.clip(np.searchsorted(self.s, w, side="right") - 1, 0, len(self.s) - 2))
        d = self.points[j + 1] - self.points[j]
        return math.atan2(d[1], d[0])

    def project(self, x: float, y: float, s_hint: float, window_m: float = 1.0) -> float:
        """Arc length of the route point nearest to (x, y) within [s_hint - window/2,
        s_hint + window], sampled every 2 cm.

        The window keeps the progress local where the route passes near itself. The
        result is unwrapped (may exceed ``length`` on a closed route).
        """
        ss = s_hint + np.arange(-window_m / 2, window_m + 1e-9, 0.02)
        if not self.closed:
            ss = np.clip(ss, 0.0, self.length)
        pts = self.points_at(ss)
        j = int(np.argmin(np.hypot(pts[:, 0] - x, pts[:, 1] - y)))
        return float(ss[j])


@dataclass(frozen=True)
class DriveParams:
    """Differential drive and route follower (pure pursuit) settings."""

    speed_mps: float = 0.3
    wheelbase_m: float = 0.4
    lookahead_m: float = 0.4
    max_yaw_rate_rps: float = 1.0
    dt_s: float = 0.01

    def __post_init__(self) -> None:
        for name in ("speed_mps", "wheelbase_m", "lookahead_m", "max_yaw_rate_rps", "dt_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")


@dataclass(frozen=True)
class OdometryModel:
    """Wheel-odometry errors (UMBmark-style: systematic + random).

    Attributes
    ----------
    scale_left, scale_right : relative error of each wheel's travel (effective radius).
    wheelbase_error : relative error of the wheelbase the odometry believes in.
    noise_m_per_sqrt_m : SD of each wheel's travel error per sqrt(metre travelled).

    The defaults (an uncalibrated but decent robot) drift by about 0.3 deg of heading
    per metre driven straight (wheel scale difference / wheelbase) and 1 % of every turn
    (wheelbase error): some 8 deg and decimetres over a 17 m lap of ``maps/room.geojson``.
    """

    scale_left: float = 0.002
    scale_right: float = 0.0
    wheelbase_error: float = 0.01
    noise_m_per_sqrt_m: float = 0.003

    def __post_init__(self) -> None:
        for name in ("scale_left", "scale_right", "wheelbase_error"):
            v = getattr(self, name)
            if not (math.isfinite(v) and -0.5 < v < 0.5):
                raise ValueError(f"`{name}` must be within (-0.5, 0.5), got {v!r}")
        if not (math.isfinite(self.noise_m_per_sqrt_m) and self.noise_m_per_sqrt_m >= 0):
            raise ValueError(f"`noise_m_per_sqrt_m` must be non-negative, "
                             f"got {self.noise_m_per_sqrt_m!r}")

    @staticmethod
    def perfect() -> OdometryModel:
        return OdometryModel(0.0, 0.0, 0.0, 0.0)


def _arc(p: Pose2, dist: float, dyaw: float) -> Pose2:
    """Move along an arc of length ``dist`` turning by ``dyaw`` (exact for constant curvature)."""
    if abs(dyaw) < 1e-9:
        mid = p.yaw + dyaw / 2
        return Pose2(p.x + dist * math.cos(mid), p.y + dist * math.sin(mid), p.yaw + dyaw)
    r = dist / dyaw
    return Pose2(p.x + r * (math.sin(p.yaw + dyaw) - math.sin(p.yaw)),
                 p.y - r * (math.cos(p.yaw + dyaw) - math.cos(p.yaw)), p.yaw + dyaw)


class Robot:
    """A differential-drive robot: true pose, route follower and odometry (thin state).

    Parameters
    ----------
    start : true initial pose in ``map``.
    route : route to follow, or None to stand still.
    drive, odometry : settings.
    rng : seeded generator for the odometry noise.
    """

    def __init__(self, start: Pose2, route: Route | None = None,
                 drive: DriveParams = DriveParams(),
                 odometry: OdometryModel = OdometryModel(),
                 rng: np.random.Generator | None = None):
        self.truth = start
        self.odom = Pose2(0.0, 0.0, 0.0)
        self.route = route
        self.drive = drive
        self.odometry = odometry
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.t_s = 0.0
        self.distance_m = 0.0
        self._s = route.project(start.x, start.y, 0.0, route.length) if route else 0.0
        self.finished = route is None

    @staticmethod
    def at_route_start(route: Route, drive: DriveParams = DriveParams(),
                       odometry: OdometryModel = OdometryModel(),
                       rng: np.random.Generator | None = None) -> Robot:
        """A robot placed at the route's first point, heading along it."""
        x, y = route.point_at(0.0)
        return Robot(Pose2(x, y, route.heading_at(0.0)), route, drive, odometry, rng)

    def _command(self) -> tuple[float, float]:
        """Pure pursuit: (speed, yaw rate) toward the route point one lookahead ahead."""
        if self.route is None or self.finished:
            return 0.0, 0.0
        d = self.drive
        p = self.truth
        self._s = self.route.project(p.x, p.y, self._s)
        if not self.route.closed and self._s >= self.route.length - 1e-3:
            self.finished = True
            return 0.0, 0.0
        gx, gy = self.route.point_at(self._s + d.lookahead_m)
        alpha = math.atan2(gy - p.y, gx - p.x) - p.yaw
        alpha = math.atan2(math.sin(alpha), math.cos(alpha))
        ld = max(math.hypot(gx - p.x, gy - p.y), 1e-6)
        v = d.speed_mps
        if abs(alpha) > math.pi / 2:  # facing away: turn on the spot
            v = 0.0
        omega = 2.0 * d.speed_mps * math.sin(alpha) / ld
        omega = max(-d.max_yaw_rate_rps, min(d.max_yaw_rate_rps, omega))
        if not self.route.closed:  # slow down at the end of an open route
            v = min(v, max(0.05, self.route.length - self._s))
        return v, omega

    def step(self, dt_s: float) -> None:
        """Advance truth and odometry by ``dt_s`` (one control step)."""
        v, omega = self._command()
        b = self.drive.wheelbase_m
        dl = (v - omega * b / 2) * dt_s
        dr = (v + omega * b / 2) * dt_s
        self.truth = _arc(self.truth, (dl + dr) / 2, (dr - dl) / b)
        o = self.odometry
        if dl != 0.0 or dr != 0.0:
            noise = self.rng.standard_normal(2) * o.noise_m_per_sqrt_m
            ml = dl * (1 + o.scale_left) + noise[0] * math.sqrt(abs(dl))
            mr = dr * (1 + o.scale_right) + noise[1] * math.sqrt(abs(dr))
            self.odom = _arc(self.odom, (ml + mr) / 2, (mr - ml) / (b * (1 + o.wheelbase_error)))
        self.distance_m += abs(dl + dr) / 2
        self.t_s += dt_s

    def advance_to(self, t_s: float) -> None:
        """Integrate up to time ``t_s`` in steps of at most ``drive.dt_s``."""
        while self.t_s < t_s - 1e-12:
            self.step(min(self.drive.dt_s, t_s - self.t_s))
        self.t_s = max(self.t_s, t_s)

"""Synthetic readings of simple reflectors straight from the physics functions.

A small, exact generator for tests and benchmarks of the fitter (the full simulator
with maps, occlusion by shapes and rigs lives in :mod:`sonarloc.world`): for each
ping, every reflector's off-axis angle gives a random threshold delay
(:func:`sonarloc.physics.tiers.echo_delays_us`), the echo arrives at To + delay, and
:func:`sonarloc.physics.apply_module` keeps the nearest detected crossing, adds
jitter, blanking, range gate and counting.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.fit.model import wrap_angle
from sonarloc.io.scancsv import ScanReadings
from sonarloc.physics.tiers import echo_delays_us
from sonarloc.physics.tof import ModuleParams, apply_module

Array = NDArray[np.float64]


@dataclass(frozen=True)
class Reflector:
    """A point (``x_m, y_m``) or a wall (``x cos(alpha) + y sin(alpha) = rho``).

    For walls, ``half_length_m`` limits the wall to that distance either side of the
    foot of the perpendicular from the origin (inf = unbounded).
    """

    kind: str
    a: float          # x_m (point) or rho_m (line)
    b: float          # y_m (point) or alpha_rad (line)
    kappa_us: float
    half_length_m: float = float("inf")

    @staticmethod
    def point(x_m: float, y_m: float, kappa_us: float) -> Reflector:
        return Reflector("point", float(x_m), float(y_m), float(kappa_us))

    @staticmethod
    def polar(range_m: float, bearing_deg: float, kappa_us: float,
              origin: tuple[float, float] = (0.0, 0.0)) -> Reflector:
        b = np.deg2rad(bearing_deg)
        return Reflector.point(origin[0] + range_m * np.cos(b), origin[1] + range_m * np.sin(b),
                               kappa_us)

    @staticmethod
    def line(rho_m: float, alpha_rad: float, kappa_us: float,
             half_length_m: float = float("inf")) -> Reflector:
        return Reflector("line", float(rho_m), float(alpha_rad), float(kappa_us),
                         float(half_length_m))

    def range_bearing(self, x: ArrayLike, y: ArrayLike) -> tuple[Array, Array, Array]:
        """Range [m], frame bearing [rad] of the reflecting point, visibility, from (x, y)."""
        x = np.asarray(x, dtype=float)
        y = np.asarray(y, dtype=float)
        if self.kind == "point":
            dx, dy = self.a - x, self.b - y
            return np.hypot(dx, dy), np.arctan2(dy, dx), np.ones(x.shape, dtype=bool)
        c, s = np.cos(self.b), np.sin(self.b)
        d = self.a - (x * c + y * s)
        R = np.abs(d)
        bearing = np.where(d >= 0, self.b, wrap_angle(self.b + np.pi))
        foot_t = -x * s + y * c          # position of the foot along the wall
        visible = np.abs(foot_t) <= self.half_length_m
        return R, bearing, visible


def simulate_readings(
    t_s: ArrayLike, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
    reflectors: Sequence[Reflector], rng: np.random.Generator,
    params: ModuleParams = ModuleParams(), tier: str = "gauss",
    sensor: ArrayLike | None = None,
) -> ScanReadings:
    """TOF readings of a transducer at the given poses looking at ``reflectors``.

    Parameters
    ----------
    t_s, x_m, y_m, yaw_rad : (n,) ping times and transducer poses in the frame.
    reflectors : what is in the scene (nearest detected echo wins).
    tier : ``gauss``, ``piston`` or ``auto`` (see :mod:`sonarloc.physics.tiers`).
    """
    t = np.asarray(t_s, dtype=float)
    x = np.broadcast_to(np.asarray(x_m, dtype=float), t.shape)
    y = np.broadcast_to(np.asarray(y_m, dtype=float), t.shape)
    yaw = np.broadcast_to(np.asarray(yaw_rad, dtype=float), t.shape)
    tm = np.full(t.shape + (max(len(reflectors), 1),), np.nan)
    for j, ref in enumerate(reflectors):
        R, bearing, visible = ref.range_bearing(x, y)
        theta = wrap_angle(bearing - yaw)
        delay, _ = echo_delays_us(theta, np.full(t.shape, ref.kappa_us), tier, rng, params)
        tm[:, j] = np.where(visible, 2e6 * R / params.c_mps + delay, np.nan)
    tof = apply_module(tm, rng, params)
    sens = (np.zeros(t.shape, dtype=np.int64) if sensor is None
            else np.broadcast_to(np.asarray(sensor, dtype=np.int64), t.shape).copy())
    return ScanReadings(t.copy(), x.copy(), y.copy(), wrap_angle(yaw), tof, sens)


def pan_scan(reflectors: Sequence[Reflector], rng: np.random.Generator,
             start_deg: float = -40.0, stop_deg: float = 40.0, step_deg: float = 0.3,
             at: tuple[float, float, float] = (0.0, 0.0, 0.0), repeat: int = 1,
             params: ModuleParams = ModuleParams(), tier: str = "gauss",
             ping_period_s: float = 0.03) -> ScanReadings:
    """A stationary panning scan from ``at`` = (x_m, y_m, yaw_deg) over [start, stop] deg."""
    n = int(np.floor((stop_deg - start_deg) / step_deg + 1e-9)) + 1
    angles = np.repeat(start_deg + step_deg * np.arange(n), repeat)
    yaw = np.deg2rad(at[2] + angles)
    t = ping_period_s * np.arange(angles.size)
    return simulate_readings(t, at[0], at[1], yaw, reflectors, rng, params, tier)


ROTATION_SCENE = tuple(Reflector.polar(r, b, k) for r, b, k in (
    (1.5, 0, 0.67), (2.0, 50, 2.68), (2.5, 100, 0.67), (1.2, 150, 0.15),
    (3.0, -160, 0.67), (1.8, -100, 2.68), (2.2, -50, 0.67), (2.8, -20, 2.68)))
"""Eight reflectors around a rotating sensor (range m, bearing deg, kappa us): poles, rods
and a plane at 1.2-3 m, some arcs overlapping a nearer one (benchmarks/bench_fit.py
section 4, the large scan CSV)."""


def rotation_scan(n_readings: int, rng: np.random.Generator, step_deg: float = 1.0,
                  ping_period_s: float = 0.01,
                  reflectors: Sequence[Reflector] = ROTATION_SCENE) -> ScanReadings:
    """A sensor at the origin in continuous rotation, ``step_deg`` per ping, over
    ``reflectors`` (default :data:`ROTATION_SCENE`): ``n_readings`` readings."""
    i = np.arange(n_readings)
    return simulate_readings(ping_period_s * i, 0.0, 0.0, np.deg2rad(i * step_deg),
                             reflectors, rng)

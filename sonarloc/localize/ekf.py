"""EKF core: pure ``predict`` / ``update`` over a frozen :class:`Gaussian` pose state.

The state is the pose of ``base_link`` in ``map``: mean ``(..., 3)`` = (x_m, y_m,
yaw_rad), covariance ``(..., 3, 3)``. Every function broadcasts over leading batch axes
(one filter or a Monte-Carlo batch, same call) and returns new objects; nothing is
mutated and nothing is stored between calls.

* :func:`predict` composes the state with an odometry increment (the pose of the new
  ``base_link`` seen from the old one) and adds the increment's noise
  (:class:`OdomNoise`, growing with distance travelled and angle turned).
* :func:`update` fuses one observation of one map feature: a reflecting point's
  position in ``base_link`` (from a fit), a wall (rho, alpha) in ``base_link`` (from a
  fit), or a range/bearing seen from a transducer (the conventional sonar model).
  Observations refer to the robot pose at the fit's reference reading, which lies in the
  past when the fit completes. ``delta`` expresses that pose relative to the state's
  pose (``pose_ref = mean ⊕ delta``, e.g. the inverse odometry increment since the
  reference time), the update linearises through it and adds ``delta_cov`` to the
  measurement noise. The :class:`~sonarloc.localize.localizer.Localizer` instead
  rewinds a short history to the reference time and passes the small remainder.

Numerics (as in robot_localization): angle innovations are wrapped before gating; the
gate is the squared Mahalanobis distance against the chi-square quantile
:func:`chi2_gate` (default 99 %, dof = observation size; ``scipy.stats.chi2.ppf``); the
gain comes from ``solve`` (never an inverse); the covariance update is in Joseph form
and symmetrised. Numerical trouble (a non-positive-definite innovation covariance) is
reported in the :class:`Innovation`, never raised.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc import se2

Array = NDArray[np.float64]

#: Default gate probability: an observation is accepted when its squared Mahalanobis
#: distance is below the 99 % quantile of chi-square with dof = its dimension.
GATE_PROBABILITY = 0.99

ObsKind = Literal["point", "line", "range_bearing", "range_axis"]
FeatureKind = Literal["point", "wall"]


@functools.lru_cache(maxsize=64)
def chi2_gate(dof: int, probability: float = GATE_PROBABILITY) -> float:
    """Gate on the squared Mahalanobis distance: ``scipy.stats.chi2.ppf(probability, dof)``.

    9.21 for dof 2 at 99 %, 11.34 for dof 3 at 99 %. Computed as that ``ppf`` computes
    it, ``2 gammaincinv(dof / 2, probability)`` (the same numbers), from scipy.special:
    importing scipy.stats costs ~0.35 s CPU at the start of a drive.
    """
    if dof < 1:
        raise ValueError(f"`dof` must be a positive integer, got {dof!r}")
    if not 0.0 < probability < 1.0:
        raise ValueError(f"`probability` must be in (0, 1), got {probability!r}")
    from scipy.special import gammaincinv

    return float(2.0 * gammaincinv(0.5 * dof, probability))


def symmetrize(m: Array) -> Array:
    """``(m + mᵀ) / 2`` over the last two axes."""
    return 0.5 * (m + np.swapaxes(m, -1, -2))


def _t(m: Array) -> Array:
    return np.swapaxes(m, -1, -2)


@dataclass(frozen=True)
class Gaussian:
    """Pose belief of ``base_link`` in ``map``: ``mean (..., 3)`` (m, m, rad), ``cov (..., 3, 3)``.

    Immutable by convention: functions return new instances and never write into
    ``mean`` or ``cov``.
    """

    mean: Array
    cov: Array

    def __post_init__(self) -> None:
        mean = np.asarray(self.mean, dtype=float)
        cov = np.asarray(self.cov, dtype=float)
        if mean.shape[-1:] != (3,):
            raise ValueError(f"`mean` must have shape (..., 3), got {mean.shape}")
        if cov.shape != mean.shape + (3,):
            raise ValueError(f"`cov` must have shape {mean.shape + (3,)}, got {cov.shape}")
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "cov", cov)

    @classmethod
    def of_lists(cls, mean: Sequence[float], cov: Sequence[Sequence[float]]) -> Gaussian:
        """A single belief from Python floats: ``mean`` (3,), ``cov`` (3, 3) nested (the
        float loops of the batch replay); the same as ``Gaussian(np.array(mean),
        np.array(cov))`` without the shape checks (the lists have those shapes)."""
        g = object.__new__(cls)
        g.__dict__["mean"] = np.array(mean, dtype=float)
        c0, c1, c2 = cov
        g.__dict__["cov"] = np.array([*c0, *c1, *c2], dtype=float).reshape(3, 3)
        return g

    @classmethod
    def from_pose(cls, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                  sd_xy_m: float, sd_yaw_rad: float) -> Gaussian:
        """A prior with independent position (``sd_xy_m`` each axis) and yaw uncertainty."""
        for name, sd in (("sd_xy_m", sd_xy_m), ("sd_yaw_rad", sd_yaw_rad)):
            if not (math.isfinite(sd * sd) and sd > 0):   # its square too: 1e200 overflows
                raise ValueError(f"`{name}` must be positive and finite, got {sd!r}")
        x, y, th = np.broadcast_arrays(np.asarray(x_m, float), np.asarray(y_m, float),
                                       np.asarray(yaw_rad, float))
        mean = np.stack([x, y, se2.wrap_angle(th)], axis=-1)
        cov = np.zeros(mean.shape + (3,))
        cov[..., 0, 0] = cov[..., 1, 1] = sd_xy_m**2
        cov[..., 2, 2] = sd_yaw_rad**2
        return cls(mean, cov)

    @property
    def batch_shape(self) -> tuple[int, ...]:
        return tuple(self.mean.shape[:-1])

    def is_spd(self) -> NDArray[np.bool_]:
        """Symmetric, finite and positive definite (all leading minors > 0), per batch element."""
        p = self.cov
        sym = np.all(np.abs(p - _t(p)) <= 1e-12 * (1.0 + np.abs(p)), axis=(-1, -2))
        finite = np.all(np.isfinite(p), axis=(-1, -2)) & np.all(np.isfinite(self.mean), axis=-1)
        m1 = p[..., 0, 0]
        m2 = p[..., 0, 0] * p[..., 1, 1] - p[..., 0, 1] * p[..., 1, 0]
        with np.errstate(invalid="ignore"):
            m3 = np.linalg.det(np.where(finite[..., None, None], p, 0.0))
        return np.asarray(sym & finite & (m1 > 0) & (m2 > 0) & (m3 > 0))


@dataclass(frozen=True)
class OdomNoise:
    """Noise of an odometry increment (dx, dy, dyaw) in the old ``base_link`` frame.

    Variances grow linearly with the distance ``d`` travelled and the angle ``|dyaw|``
    turned, so splitting a motion into more steps leaves the total unchanged (a random
    walk per metre and per radian):

    * along-track (x): ``along_var_per_m·d + xy_var_per_rad·|dyaw|``  [m²]
    * cross-track (y): ``cross_var_per_m·d + xy_var_per_rad·|dyaw|``  [m²]
    * yaw: ``yaw_var_per_m·d + yaw_var_per_rad·|dyaw|``  [rad²]
    """

    along_var_per_m: float = 0.01**2
    cross_var_per_m: float = 0.005**2
    xy_var_per_rad: float = 0.002**2
    yaw_var_per_m: float = math.radians(0.5) ** 2
    yaw_var_per_rad: float = math.radians(1.0) ** 2

    def __post_init__(self) -> None:
        for name in ("along_var_per_m", "cross_var_per_m", "xy_var_per_rad",
                     "yaw_var_per_m", "yaw_var_per_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"`{name}` must be non-negative, got {value!r}")

    def cov(self, increment: ArrayLike) -> Array:
        """Covariance ``(..., 3, 3)`` of increments ``(..., 3)`` (m, m, rad), in their frame."""
        u = np.asarray(increment, dtype=float)
        d = np.hypot(u[..., 0], u[..., 1])
        turn = np.abs(se2.wrap_angle(u[..., 2]))
        q = np.zeros(u.shape + (3,))
        q[..., 0, 0] = self.along_var_per_m * d + self.xy_var_per_rad * turn
        q[..., 1, 1] = self.cross_var_per_m * d + self.xy_var_per_rad * turn
        q[..., 2, 2] = self.yaw_var_per_m * d + self.yaw_var_per_rad * turn
        return q


def predict(state: Gaussian, increment: ArrayLike, noise: OdomNoise = OdomNoise(),
            increment_cov: ArrayLike | None = None) -> Gaussian:
    """Move the belief by an odometry increment.

    Parameters
    ----------
    state : Gaussian, batch shape (...)
    increment : (..., 3)
        Pose of the new ``base_link`` in the old one (m, m, rad):
        ``se2.between(odom_old, odom_new)``.
    noise : OdomNoise
        Increment noise model, used when ``increment_cov`` is None.
    increment_cov : (..., 3, 3), optional
        Explicit covariance of the increment in its own frame.

    Returns
    -------
    Gaussian
        ``mean ⊕ increment`` with ``P' = F P Fᵀ + G Q Gᵀ`` (F, G: Jacobians of ⊕).
    """
    u = np.asarray(increment, dtype=float)
    if state.mean.ndim == 1 and u.shape == (3,) and increment_cov is None:
        return _predict_one(state, u, noise)
    q = noise.cov(u) if increment_cov is None else np.asarray(increment_cov, dtype=float)
    mean = se2.compose(state.mean, u)
    f, g = se2.compose_jacobians(state.mean, u)
    cov = f @ state.cov @ _t(f) + g @ q @ _t(g)
    return Gaussian(mean, symmetrize(cov))


def _predict_one(state: Gaussian, u: Array, noise: OdomNoise) -> Gaussian:
    """:func:`predict` for one filter, in scalar arithmetic (same numbers to rounding,
    less overhead): :func:`predict_lists` on the belief's floats."""
    mean, cov = predict_lists(state.mean.tolist(), state.cov.tolist(), u.tolist(), noise)
    return Gaussian.of_lists(mean, cov)


def predict_lists(mean: Sequence[float], cov: Sequence[Sequence[float]],
                  u: Sequence[float], noise: OdomNoise
                  ) -> tuple[list[float], list[list[float]]]:
    """:func:`predict` of one filter given as Python floats: ``mean`` (3,), ``cov``
    (3, 3) nested, increment ``u`` (3,) (m, m, rad); returns the new mean and covariance
    as lists. ``F = I + (a, b, 0) e₃ᵀ`` makes ``F P Fᵀ`` a few products; for loops that
    keep a belief in floats between steps (the batch replay)."""
    x, y, th = mean
    dx, dy, dth = u
    c, s = math.cos(th), math.sin(th)
    d = math.hypot(dx, dy)
    turn = abs((dth + math.pi) % (2.0 * math.pi) - math.pi)
    qx = noise.along_var_per_m * d + noise.xy_var_per_rad * turn
    qy = noise.cross_var_per_m * d + noise.xy_var_per_rad * turn
    qt = noise.yaw_var_per_m * d + noise.yaw_var_per_rad * turn
    a, b = -s * dx - c * dy, c * dx - s * dy
    (p00, p01, p02), (p10, p11, p12), (p20, p21, p22) = cov
    # F P: rows 0 and 1 gain a (b) times row 2; then (F P) Fᵀ: columns likewise
    f00, f01, f02 = p00 + a * p20, p01 + a * p21, p02 + a * p22
    f10, f11, f12 = p10 + b * p20, p11 + b * p21, p12 + b * p22
    m00, m01 = f00 + a * f02, f01 + b * f02
    m10, m11 = f10 + a * f12, f11 + b * f12
    m20, m21 = p20 + a * p22, p21 + b * p22
    # + G Q Gᵀ with G = rot(th) ⊕ 1 and Q diagonal; symmetrised
    gxy = c * s * (qx - qy)
    o01 = 0.5 * (m01 + m10) + gxy
    o02 = 0.5 * (f02 + m20)
    o12 = 0.5 * (f12 + m21)
    return ([x + c * dx - s * dy, y + s * dx + c * dy,
             (th + dth + math.pi) % (2.0 * math.pi) - math.pi],
            [[m00 + c * c * qx + s * s * qy, o01, o02],
             [o01, m11 + s * s * qx + c * c * qy, o12],
             [o02, o12, p22 + qt]])


def predict_chain(state: Gaussian, increments: ArrayLike, noise: OdomNoise = OdomNoise()
                  ) -> Gaussian:
    """:func:`predict` applied ``n`` times in a row, every intermediate belief returned.

    The same numbers as ``n`` calls of :func:`predict` (to rounding), in closed form over
    the whole chain: the motion Jacobians ``F_k = I + v_k e₃ᵀ`` of one filter multiply to
    ``I + (W_k - W_j) e₃ᵀ`` (``W``: the mean's path turned by 90 deg), so every
    covariance is a cumulative sum. Used to replay long stretches of odometry between
    landmark updates without a Python loop.

    Parameters
    ----------
    state : Gaussian, one filter (mean (3,), cov (3, 3)).
    increments : (n, 3)
        Odometry increments (m, m, rad), each in the frame of the previous pose.
    noise : increment noise model (:meth:`OdomNoise.cov`).

    Returns
    -------
    Gaussian
        Batch shape (n,): the belief after each increment.
    """
    u = np.asarray(increments, dtype=float).reshape(-1, 3)
    m0 = np.asarray(state.mean, dtype=float)
    if m0.shape != (3,):
        raise ValueError(f"`state` must be one filter (mean shape (3,)), got {m0.shape}")
    n = len(u)
    if n == 0:
        return Gaussian(np.zeros((0, 3)), np.zeros((0, 3, 3)))
    dth = u[:, 2]
    th = m0[2] + np.concatenate(([0.0], np.cumsum(dth)))  # unwrapped yaw before/after
    c, s = np.cos(th[:-1]), np.sin(th[:-1])
    step_x = c * u[:, 0] - s * u[:, 1]
    step_y = s * u[:, 0] + c * u[:, 1]
    wx = np.cumsum(step_x)  # position relative to the start
    wy = np.cumsum(step_y)
    mean = np.stack([m0[0] + wx, m0[1] + wy, se2.wrap_angle(th[1:])], axis=-1)
    d = np.hypot(u[:, 0], u[:, 1])
    turn = np.abs(se2.wrap_angle(dth))
    qx = noise.along_var_per_m * d + noise.xy_var_per_rad * turn
    qy = noise.cross_var_per_m * d + noise.xy_var_per_rad * turn
    qt = noise.yaw_var_per_m * d + noise.yaw_var_per_rad * turn
    # W_k = (-y_k, x_k) relative to the start; Φ_kj = I + (W_k - W_j) e₃ᵀ
    w = np.stack([-wy, wx], axis=-1)                           # (n, 2)
    a_xx = np.cumsum(c * c * qx + s * s * qy)
    a_xy = np.cumsum(c * s * (qx - qy))
    a_yy = np.cumsum(s * s * qx + c * c * qy)
    s0 = np.cumsum(qt)
    s1 = np.cumsum(qt[:, None] * w, axis=0)                    # (n, 2)
    s2 = np.cumsum(qt[:, None, None] * w[:, :, None] * w[:, None, :], axis=0)  # (n, 2, 2)
    cov = np.zeros((n, 3, 3))
    # Σ_j A_j + qt_j (w e₃ᵀ + e₃ wᵀ + w wᵀ), w = W_k - W_j
    top = (s0[:, None, None] * w[:, :, None] * w[:, None, :] - w[:, :, None] * s1[:, None, :]
           - s1[:, :, None] * w[:, None, :] + s2)
    cov[:, 0, 0] = a_xx + top[:, 0, 0]
    cov[:, 0, 1] = a_xy + top[:, 0, 1]
    cov[:, 1, 0] = a_xy + top[:, 1, 0]
    cov[:, 1, 1] = a_yy + top[:, 1, 1]
    col = s0[:, None] * w - s1
    cov[:, 0:2, 2] = col
    cov[:, 2, 0:2] = col
    cov[:, 2, 2] = s0
    # the prior carried along: Φ_k0 P0 Φ_k0ᵀ
    phi = np.tile(np.eye(3), (n, 1, 1))
    phi[:, 0:2, 2] = w
    cov += phi @ np.asarray(state.cov, dtype=float) @ _t(phi)
    return Gaussian(mean, symmetrize(cov))


def chain_increments(a: ArrayLike, cov_a: ArrayLike, b: ArrayLike, cov_b: ArrayLike
                     ) -> tuple[Array, Array]:
    """``a ⊕ b`` of two independent uncertain increments and its covariance (..., 3, 3).

    Covariances are in each increment's own (starting) frame, as :meth:`OdomNoise.cov`.
    """
    ja, jb = se2.compose_jacobians(a, b)
    ab = se2.compose(a, b)
    # express cov_a (in a's start frame) as a perturbation of the pose a: a ⊕ b moves with
    # it through ja; b's perturbation goes through jb. Both are in the start frame of a.
    cov = ja @ np.asarray(cov_a, dtype=float) @ _t(ja) + jb @ np.asarray(cov_b, dtype=float) \
        @ _t(jb)
    return ab, symmetrize(cov)


def invert_increment(a: ArrayLike, cov_a: ArrayLike) -> tuple[Array, Array]:
    """``a⁻¹`` and its covariance ``J cov_a Jᵀ`` (J: Jacobian of the inverse)."""
    j = se2.inverse_jacobian(a)
    return se2.inverse(a), symmetrize(j @ np.asarray(cov_a, dtype=float) @ _t(j))


# --------------------------------------------------------------------------- observations


@dataclass(frozen=True)
class Observation:
    """One measurement relative to the robot pose at its reference time.

    ``kind``:

    * ``"point"``: ``z`` = (x_m, y_m) of a reflecting point in ``base_link``;
    * ``"line"``: ``z`` = (rho_m, alpha_rad) of a wall ``x cos a + y sin a = rho`` in
      ``base_link`` (rho >= 0);
    * ``"range_bearing"``: ``z`` = (range_m, bearing_rad) seen from the transducer
      ``sensor``, bearing measured from its axis (CCW); a wall is seen at its
      normal-incidence point (specular);
    * ``"range_axis"``: the same, but the echo is taken to come from the beam axis: a
      wall is predicted at the range where the axis meets it (ray casting, the textbook
      sonar model), points as in ``range_bearing``.

    ``cov``: (..., 2, 2) covariance of ``z``. ``sensor``: (..., 3) pose of the
    (reference) transducer in ``base_link``; a point feature with a radius reflects at
    its surface point facing the transducer. ``kappa_us`` / ``kappa_var_us2``: fitted
    reflector strength and its variance (NaN when unknown), used by data association.
    ``t_s``: the reference time.
    """

    kind: ObsKind
    z: Array
    cov: Array
    sensor: Array = field(default_factory=lambda: np.zeros(3))
    kappa_us: float = math.nan
    kappa_var_us2: float = math.nan
    t_s: float = math.nan

    def __post_init__(self) -> None:
        if self.kind not in ("point", "line", "range_bearing", "range_axis"):
            raise ValueError(f"`kind` must be point, line, range_bearing or range_axis, got "
                             f"{self.kind!r}")
        z = np.asarray(self.z, dtype=float)
        cov = np.asarray(self.cov, dtype=float)
        if z.shape[-1:] != (2,) or cov.shape[-2:] != (2, 2):
            raise ValueError(f"`z` must be (..., 2) and `cov` (..., 2, 2), got {z.shape}, "
                             f"{cov.shape}")
        object.__setattr__(self, "z", z)
        object.__setattr__(self, "cov", cov)
        object.__setattr__(self, "sensor", np.asarray(self.sensor, dtype=float))

    @property
    def angle_index(self) -> int | None:
        """Index of the angular component of ``z`` (wrapped in innovations), or None."""
        return None if self.kind == "point" else 1


@dataclass(frozen=True)
class Feature:
    """One map feature (or a batch of same-kind features) in the ``map`` frame.

    ``kind == "point"``: ``params`` (..., 2) = centre (x_m, y_m) and ``radius_m`` (a
    pole reflects at its surface); ``"wall"``: ``params`` (..., 2) = (rho_m, alpha_rad)
    of the infinite line through the wall segment.
    """

    kind: FeatureKind
    params: Array
    radius_m: Array | float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("point", "wall"):
            raise ValueError(f"`kind` must be point or wall, got {self.kind!r}")
        params = np.asarray(self.params, dtype=float)
        if params.shape[-1:] != (2,):
            raise ValueError(f"`params` must be (..., 2), got {params.shape}")
        object.__setattr__(self, "params", params)


# Measurement functions: (predicted z (..., 2), Jacobian wrt the pose (..., 2, 3)).


def _sensor_in_map(pose: Array, sensor: Array) -> tuple[Array, Array]:
    """Transducer position in map (..., 2) and its Jacobian wrt the pose (..., 2, 3)."""
    th = pose[..., 2]
    c, s = np.cos(th), np.sin(th)
    sx, sy = sensor[..., 0], sensor[..., 1]
    pos = np.stack([pose[..., 0] + c * sx - s * sy, pose[..., 1] + s * sx + c * sy], axis=-1)
    shape = pos.shape[:-1]
    j = np.zeros(shape + (2, 3))
    j[..., 0, 0] = 1.0
    j[..., 1, 1] = 1.0
    j[..., 0, 2] = -s * sx - c * sy
    j[..., 1, 2] = c * sx - s * sy
    return pos, j


def point_in_base(pose: ArrayLike, point: ArrayLike, radius_m: ArrayLike = 0.0,
                  sensor: ArrayLike = (0.0, 0.0, 0.0)) -> tuple[Array, Array]:
    """Reflecting point of a map point feature in ``base_link``, and d/d(pose).

    Parameters
    ----------
    pose : (..., 3) base_link in map.
    point : (..., 2) feature centre in map (m).
    radius_m : (...) feature radius; the reflecting point is the surface point facing
        the transducer.
    sensor : (..., 3) transducer pose in base_link.

    Returns
    -------
    z : (..., 2) metres, H : (..., 2, 3)
    """
    p = np.asarray(pose, dtype=float)
    c0 = np.asarray(point, dtype=float)
    r = np.asarray(radius_m, dtype=float)
    th = p[..., 2]
    c, s = np.cos(th), np.sin(th)
    q = c0
    dq = None
    if np.any(r != 0):
        spos, js = _sensor_in_map(p, np.asarray(sensor, dtype=float))
        v = spos - c0
        length = np.maximum(np.hypot(v[..., 0], v[..., 1]), 1e-9)
        u = v / length[..., None]
        q = c0 + r[..., None] * u
        # d q / d spos = r (I - u uᵀ) / |v|
        proj = np.eye(2) - u[..., :, None] * u[..., None, :]
        dq = (r / length)[..., None, None] * proj @ js
    dx = q[..., 0] - p[..., 0]
    dy = q[..., 1] - p[..., 1]
    zx = c * dx + s * dy
    zy = -s * dx + c * dy
    z = np.stack([zx, zy], axis=-1)
    h = np.zeros(z.shape[:-1] + (2, 3))
    h[..., 0, 0] = -c
    h[..., 0, 1] = -s
    h[..., 1, 0] = s
    h[..., 1, 1] = -c
    h[..., 0, 2] = zy
    h[..., 1, 2] = -zx
    if dq is not None:
        rt = np.zeros(z.shape[:-1] + (2, 2))
        rt[..., 0, 0] = c
        rt[..., 0, 1] = s
        rt[..., 1, 0] = -s
        rt[..., 1, 1] = c
        h = h + rt @ dq
    return z, h


def wall_in_base(pose: ArrayLike, wall: ArrayLike) -> tuple[Array, Array]:
    """A map wall (rho, alpha) seen in ``base_link`` (rho >= 0), and d/d(pose).

    ``pose``: (..., 3); ``wall``: (..., 2) (m, rad). Returns z (..., 2), H (..., 2, 3).
    """
    p = np.asarray(pose, dtype=float)
    w = np.asarray(wall, dtype=float)
    ca, sa = np.cos(w[..., 1]), np.sin(w[..., 1])
    rho = w[..., 0] - p[..., 0] * ca - p[..., 1] * sa
    sign = np.where(rho < 0, -1.0, 1.0)
    alpha = w[..., 1] + np.where(rho < 0, math.pi, 0.0) - p[..., 2]
    z = np.stack([np.abs(rho), se2.wrap_angle(alpha)], axis=-1)
    h = np.zeros(z.shape[:-1] + (2, 3))
    h[..., 0, 0] = -sign * ca
    h[..., 0, 1] = -sign * sa
    h[..., 1, 2] = -1.0
    return z, h


def range_bearing_point(pose: ArrayLike, sensor: ArrayLike, point: ArrayLike,
                        radius_m: ArrayLike = 0.0) -> tuple[Array, Array]:
    """Range to the surface of a point feature and its bearing from the transducer axis.

    ``pose`` (..., 3) base_link in map; ``sensor`` (..., 3) transducer in base_link;
    ``point`` (..., 2) centre in map; ``radius_m`` (...). Returns z = (range_m,
    bearing_rad) (..., 2) and H (..., 2, 3).
    """
    p = np.asarray(pose, dtype=float)
    sen = np.asarray(sensor, dtype=float)
    spos, js = _sensor_in_map(p, sen)
    d = np.asarray(point, dtype=float) - spos
    dist2 = np.maximum(d[..., 0] ** 2 + d[..., 1] ** 2, 1e-18)
    dist = np.sqrt(dist2)
    rng = dist - np.asarray(radius_m, dtype=float)
    bearing = se2.wrap_angle(np.arctan2(d[..., 1], d[..., 0]) - p[..., 2] - sen[..., 2])
    z = np.stack([rng, bearing], axis=-1)
    # d range / d spos = -d/|d| ; d phi / d spos = (dy, -dx)/|d|^2
    dz_ds = np.stack([np.stack([-d[..., 0] / dist, -d[..., 1] / dist], axis=-1),
                      np.stack([d[..., 1] / dist2, -d[..., 0] / dist2], axis=-1)], axis=-2)
    h = dz_ds @ js
    h[..., 1, 2] -= 1.0
    return z, h


def range_bearing_wall(pose: ArrayLike, sensor: ArrayLike, wall: ArrayLike
                       ) -> tuple[Array, Array]:
    """Perpendicular range to a wall and the bearing of its normal from the transducer axis.

    ``pose`` (..., 3); ``sensor`` (..., 3) in base_link; ``wall`` (..., 2) (rho, alpha)
    in map. Returns z = (range_m, bearing_rad) (..., 2) and H (..., 2, 3).
    """
    p = np.asarray(pose, dtype=float)
    sen = np.asarray(sensor, dtype=float)
    w = np.asarray(wall, dtype=float)
    spos, js = _sensor_in_map(p, sen)
    ca, sa = np.cos(w[..., 1]), np.sin(w[..., 1])
    signed = w[..., 0] - spos[..., 0] * ca - spos[..., 1] * sa
    sign = np.where(signed < 0, -1.0, 1.0)
    direction = w[..., 1] + np.where(signed < 0, math.pi, 0.0)
    z = np.stack([np.abs(signed), se2.wrap_angle(direction - p[..., 2] - sen[..., 2])], axis=-1)
    dr_ds = np.stack([-sign * ca, -sign * sa], axis=-1)[..., None, :]
    h = np.zeros(z.shape[:-1] + (2, 3))
    h[..., 0:1, :] = dr_ds @ js
    h[..., 1, 2] = -1.0
    return z, h


def axis_range_wall(pose: ArrayLike, sensor: ArrayLike, wall: ArrayLike
                    ) -> tuple[Array, Array]:
    """Range along the transducer axis to where it meets a wall (ray casting), bearing 0.

    ``pose`` (..., 3); ``sensor`` (..., 3) in base_link; ``wall`` (..., 2) in map. Returns
    z = (range_m, 0) (..., 2) and H (..., 2, 3); range is inf where the axis points away
    from the wall.
    """
    z, h, _ = _axis_range_wall(pose, sensor, wall)
    return z, h


def _axis_range_wall(pose: ArrayLike, sensor: ArrayLike, wall: ArrayLike
                     ) -> tuple[Array, Array, Array]:
    """:func:`axis_range_wall` and dr/dpsi (...), the range's rate of change with the
    direction the echo is taken from (0 where the axis misses the wall)."""
    p = np.asarray(pose, dtype=float)
    sen = np.asarray(sensor, dtype=float)
    w = np.asarray(wall, dtype=float)
    spos, js = _sensor_in_map(p, sen)
    ca, sa = np.cos(w[..., 1]), np.sin(w[..., 1])
    signed = w[..., 0] - spos[..., 0] * ca - spos[..., 1] * sa
    sign = np.where(signed < 0, -1.0, 1.0)
    d = np.abs(signed)
    nx, ny = sign * ca, sign * sa  # normal pointing from the transducer to the wall
    psi = p[..., 2] + sen[..., 2]
    ax, ay = np.cos(psi), np.sin(psi)
    cos_t = ax * nx + ay * ny
    hit = cos_t > 1e-6
    cos_safe = np.where(hit, cos_t, 1.0)
    rng = np.where(hit, d / cos_safe, np.inf)
    z = np.stack([rng, np.zeros_like(rng)], axis=-1)
    h = np.zeros(z.shape[:-1] + (2, 3))
    # r = d / cos_t: dr/ds = -n / cos_t ; dr/dpsi = -d (a_perp . n) / cos_t^2
    dr_ds = np.stack([-nx / cos_safe, -ny / cos_safe], axis=-1)[..., None, :]
    h[..., 0:1, :] = dr_ds @ js
    dr_dpsi = np.where(hit, -d * (-ay * nx + ax * ny) / cos_safe**2, 0.0)
    h[..., 0, 2] += dr_dpsi
    h = np.where(hit[..., None, None], h, 0.0)
    return z, h, dr_dpsi


def measurement_cov(pose: ArrayLike, obs: Observation, feature: Feature) -> Array:
    """Covariance of ``obs.z``'s error against ``measure``'s prediction (..., 2, 2).

    ``obs.cov``, except for a ``range_axis`` reading of a wall: the echo comes from
    somewhere in the beam, not from its axis, so the bearing's variance ``obs.cov[1, 1]``
    (how far off the axis the echo may come from) enters the range through the ray's
    slope, ``(dr/dpsi)^2 var(bearing)`` with ``r = d / cos(incidence)``: nothing at
    normal incidence, an SD of ``0.12 d`` at 30 deg for a 10 deg SD. Before, an oblique wall's axis
    range had the range SD alone (1 cm) and the conventional EKF was overconfident there
    (NEES 9.6 on the room drives, benchmarks/results/localize.md)."""
    cov = np.asarray(obs.cov, dtype=float)
    if obs.kind != "range_axis" or feature.kind != "wall":
        return cov
    _, _, dr_dpsi = _axis_range_wall(pose, obs.sensor, feature.params)
    out = np.array(np.broadcast_to(cov, dr_dpsi.shape + (2, 2)))
    out[..., 0, 0] += dr_dpsi**2 * cov[..., 1, 1]
    return out


def measure(pose: ArrayLike, obs: Observation, feature: Feature) -> tuple[Array, Array]:
    """Predicted ``obs.z`` of ``feature`` from ``pose`` and its Jacobian (..., 2, 3)."""
    if obs.kind == "point":
        if feature.kind != "point":
            raise ValueError(f"a point observation needs a point feature, got {feature.kind!r}")
        return point_in_base(pose, feature.params, feature.radius_m, obs.sensor)
    if obs.kind == "line":
        if feature.kind != "wall":
            raise ValueError(f"a line observation needs a wall feature, got {feature.kind!r}")
        return wall_in_base(pose, feature.params)
    if feature.kind == "point":
        return range_bearing_point(pose, obs.sensor, feature.params, feature.radius_m)
    if obs.kind == "range_axis":
        return axis_range_wall(pose, obs.sensor, feature.params)
    return range_bearing_wall(pose, obs.sensor, feature.params)


# --------------------------------------------------------------------------- update


@dataclass(frozen=True)
class Innovation:
    """What an update saw: wrapped innovation ``nu (..., 2)``, its covariance ``S (..., 2, 2)``,
    squared Mahalanobis distance ``d2 (...)``, the ``gate`` it was held against (inf when
    not gated), and per batch element whether it was ``accepted`` or ``singular``
    (S not positive definite: the state is left unchanged).
    """

    nu: Array
    S: Array
    d2: Array
    gate: float
    accepted: NDArray[np.bool_]
    singular: NDArray[np.bool_]

    @property
    def reason(self) -> str:
        """One word for a single (unbatched) update: accepted, gated or singular."""
        if np.all(self.accepted):
            return "accepted"
        if np.any(self.singular):
            return "singular"
        return "gated"


def innovation(z: ArrayLike, z_pred: ArrayLike, angle_index: int | None) -> Array:
    """``z - z_pred`` (..., n) with component ``angle_index`` wrapped into [-pi, pi)."""
    nu = np.asarray(z, dtype=float) - np.asarray(z_pred, dtype=float)
    if angle_index is not None:
        nu[..., angle_index] = se2.wrap_angle(nu[..., angle_index])
    return nu


def _joseph(mean: Array, p: Array, nu: Array, h: Array, r: Array, gate: float
            ) -> tuple[Array, Array, Array, Array, NDArray[np.bool_], NDArray[np.bool_]]:
    """Kalman update of an n-dim Gaussian; returns mean, cov, S, d2, accepted, singular."""
    n = p.shape[-1]
    hp = h @ p
    s = symmetrize(hp @ _t(h) + r)
    m = s.shape[-1]
    finite = np.all(np.isfinite(s), axis=(-1, -2)) & np.all(np.isfinite(nu), axis=-1)
    s_safe = np.where(finite[..., None, None], s, np.eye(m))
    if m == 1:
        spd = s_safe[..., 0, 0] > 0
    elif m == 2:
        spd = (s_safe[..., 0, 0] > 0) & (
            s_safe[..., 0, 0] * s_safe[..., 1, 1] - s_safe[..., 0, 1] ** 2 > 0)
    else:
        spd = np.all(np.linalg.eigvalsh(s_safe) > 0, axis=-1)
    singular = np.asarray(~(finite & spd))
    s_safe = np.where(singular[..., None, None], np.eye(m), s_safe)
    # K = P Hᵀ S⁻¹ = (S⁻¹ H P)ᵀ  (S, P symmetric): one solve gives the gain and S⁻¹ nu
    sol = np.linalg.solve(s_safe, np.concatenate([hp, nu[..., None]], axis=-1))
    kt = sol[..., :, :n]
    d2 = np.einsum("...i,...i->...", nu, sol[..., :, n])
    d2 = np.where(singular, np.inf, d2)
    accepted = np.asarray(~singular & (d2 <= gate))
    k = _t(kt)
    new_mean = mean + np.einsum("...ij,...j->...i", k, nu)
    ikh = np.eye(n) - k @ h
    with np.errstate(over="ignore", invalid="ignore"):
        cov = symmetrize(ikh @ p @ _t(ikh) + k @ r @ kt)
    # a belief so wide that the update overflows (a prior of 1e150 m): singular, unchanged
    if not (np.isfinite(cov).all() and np.isfinite(new_mean).all()):
        overflow = ~(np.all(np.isfinite(cov), axis=(-1, -2))
                     & np.all(np.isfinite(new_mean), axis=-1))
        singular = np.asarray(singular | overflow)
        accepted = np.asarray(accepted & ~overflow)
    if not np.all(accepted):
        new_mean = np.where(accepted[..., None], new_mean, mean)
        cov = np.where(accepted[..., None, None], cov, p)
    return new_mean, cov, s, d2, accepted, singular


def kalman_update(state: Gaussian, nu: ArrayLike, h: ArrayLike, r: ArrayLike,
                  gate: float = math.inf) -> tuple[Gaussian, Innovation]:
    """Linear(ised) Kalman update with a given innovation ``nu (..., m)``.

    ``h``: (..., m, 3) Jacobian; ``r``: (..., m, m) measurement covariance; ``gate``:
    elements with ``d2 = nuᵀ S⁻¹ nu`` above it are left unchanged. Gain from
    ``solve(S, H P)``; covariance ``(I-KH) P (I-KH)ᵀ + K R Kᵀ``, symmetrised.
    """
    nu_a = np.asarray(nu, dtype=float)
    mean, cov, s, d2, accepted, singular = _joseph(
        state.mean, state.cov, nu_a, np.asarray(h, dtype=float), np.asarray(r, dtype=float),
        gate)
    mean[..., 2] = se2.wrap_angle(mean[..., 2])
    return Gaussian(mean, cov), Innovation(nu_a, s, d2, gate, accepted, singular)


def since_reference(mean: ArrayLike, increment: ArrayLike, increment_cov: ArrayLike
                    ) -> tuple[Array, Array, Array]:
    """``delta``, ``delta_cov``, ``delta_cross`` for :func:`update` of a delayed observation.

    For the common case that the odometry ``increment`` (..., 3) from the reference pose to
    the current one, with covariance ``increment_cov`` (..., 3, 3), has been applied by
    :func:`predict` since the reference time and no update came in between: then the
    increment's noise is inside the state's covariance, and ``delta_cross`` (the
    covariance of the current pose error with the error of ``delta``) makes the update
    exact to first order. ``mean`` (..., 3): the current pose.
    """
    inc = np.asarray(increment, dtype=float)
    q = np.asarray(increment_cov, dtype=float)
    delta, delta_cov = invert_increment(inc, q)
    ref = se2.compose(mean, delta)
    _, g = se2.compose_jacobians(ref, inc)
    cross = g @ q @ _t(se2.inverse_jacobian(inc))
    return delta, delta_cov, cross


def update(state: Gaussian, obs: Observation, feature: Feature, *,
           delta: ArrayLike | None = None, delta_cov: ArrayLike | None = None,
           delta_cross: ArrayLike | None = None,
           gate_probability: float | None = GATE_PROBABILITY) -> tuple[Gaussian, Innovation]:
    """Fuse one observation of one map feature.

    Parameters
    ----------
    state : Gaussian, batch shape (...)
        Belief of the pose that ``delta`` is relative to (normally the current pose).
    obs : Observation
        Measured relative to the robot pose at the reference time.
    feature : Feature
        The associated map feature (see :mod:`sonarloc.localize.associate`).
    delta : (..., 3), optional
        Pose at the reference time seen from the state's pose (``pose_ref = mean ⊕
        delta``), e.g. the inverse of the odometry increment since the reference time.
        The Jacobian is taken through the composition.
    delta_cov : (..., 3, 3), optional
        Covariance of ``delta``'s error; the update then runs on the joint Gaussian of
        (pose, delta error).
    delta_cross : (..., 3, 3), optional
        Covariance of the pose error with ``delta``'s error (zero when omitted:
        independent). :func:`since_reference` gives all three for a delay without
        intervening updates. With updates in between, rewind instead (as the
        :class:`~sonarloc.localize.localizer.Localizer` does).
    gate_probability : float or None
        Chi-square gate (dof 2) on the squared Mahalanobis distance; None: no gate
        (association has already gated).

    Returns
    -------
    (Gaussian, Innovation)
        The new belief (unchanged where gated or singular) and what the update saw.
    """
    mean = state.mean
    gate = math.inf if gate_probability is None else chi2_gate(2, gate_probability)
    if delta is None:
        z_pred, h = measure(mean, obs, feature)
        nu = innovation(obs.z, z_pred, obs.angle_index)
        return kalman_update(state, nu, h, measurement_cov(mean, obs, feature), gate)
    d = np.asarray(delta, dtype=float)
    pose_ref = se2.compose(mean, d)
    z_pred, h_ref = measure(pose_ref, obs, feature)
    r_cov = measurement_cov(pose_ref, obs, feature)
    ja, jb = se2.compose_jacobians(mean, d)
    nu = innovation(obs.z, z_pred, obs.angle_index)
    if delta_cov is None:
        return kalman_update(state, nu, h_ref @ ja, r_cov, gate)
    # joint Gaussian of (pose, delta error): update both, keep the pose block
    qd = np.asarray(delta_cov, dtype=float)
    cross = np.zeros(qd.shape) if delta_cross is None else np.asarray(delta_cross, float)
    shape = np.broadcast_shapes(state.cov.shape, qd.shape, cross.shape)[:-2]
    p_aug = np.zeros(shape + (6, 6))
    p_aug[..., :3, :3] = state.cov
    p_aug[..., :3, 3:] = cross
    p_aug[..., 3:, :3] = _t(np.broadcast_to(cross, shape + (3, 3)))
    p_aug[..., 3:, 3:] = qd
    h_aug = np.concatenate(np.broadcast_arrays(h_ref @ ja, h_ref @ jb), axis=-1)
    mean_aug = np.concatenate([np.broadcast_to(mean, shape + (3,)), np.zeros(shape + (3,))],
                              axis=-1)
    new_mean, cov, s, d2, accepted, singular = _joseph(
        mean_aug, p_aug, nu, h_aug, r_cov, gate)
    out_mean = new_mean[..., :3].copy()
    out_mean[..., 2] = se2.wrap_angle(out_mean[..., 2])
    return (Gaussian(out_mean, np.ascontiguousarray(cov[..., :3, :3])),
            Innovation(nu, s, d2, gate, accepted, singular))


def nees(state: Gaussian, truth: ArrayLike) -> Array:
    """Normalised estimation error squared ``eᵀ P⁻¹ e`` (...), yaw error wrapped."""
    e = np.asarray(truth, dtype=float) - state.mean
    e[..., 2] = se2.wrap_angle(e[..., 2])
    sol = np.linalg.solve(state.cov, e[..., None])[..., 0]
    return np.asarray(np.einsum("...i,...i->...", e, sol))

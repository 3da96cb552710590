"""Planar poses (x_m, y_m, yaw_rad): composition, inverse, relative pose, Jacobians.

A pose ``a`` maps points of its child frame into its parent frame: ``p_parent =
R(yaw) p_child + (x, y)``. ``compose(a, b)`` is ``a ⊕ b`` (b expressed in a's frame),
``between(a, b)`` is ``a⁻¹ ⊕ b`` (b seen from a), as for REP-105 transforms
(``map→base_link = map→odom ⊕ odom→base_link``). Every function broadcasts over
leading batch axes: poses are ``(..., 3)``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def wrap_angle(angle_rad: ArrayLike) -> Array:
    """Angles wrapped into [-pi, pi); any shape."""
    a = np.asarray(angle_rad, dtype=float)
    return np.asarray((a + math.pi) % (2.0 * math.pi) - math.pi)


def _split(pose: ArrayLike) -> tuple[Array, Array, Array]:
    p = np.asarray(pose, dtype=float)
    if p.shape[-1:] != (3,):
        raise ValueError(f"`pose` must have a last axis of length 3, got shape {p.shape}")
    return p[..., 0], p[..., 1], p[..., 2]


def compose(a: ArrayLike, b: ArrayLike) -> Array:
    """``a ⊕ b``: pose b (given in a's frame) in a's parent frame. Shapes broadcast, (..., 3)."""
    ax, ay, ath = _split(a)
    bx, by, bth = _split(b)
    c, s = np.cos(ath), np.sin(ath)
    return np.stack([ax + c * bx - s * by, ay + s * bx + c * by, wrap_angle(ath + bth)], axis=-1)


def inverse(a: ArrayLike) -> Array:
    """``a⁻¹`` so that ``compose(a, inverse(a))`` is the identity. (..., 3)."""
    ax, ay, ath = _split(a)
    c, s = np.cos(ath), np.sin(ath)
    return np.stack([-c * ax - s * ay, s * ax - c * ay, wrap_angle(-ath)], axis=-1)


def between(a: ArrayLike, b: ArrayLike) -> Array:
    """``a⁻¹ ⊕ b``: pose b seen from pose a (the odometry increment from a to b). (..., 3)."""
    ax, ay, ath = _split(a)
    bx, by, bth = _split(b)
    c, s = np.cos(ath), np.sin(ath)
    dx, dy = bx - ax, by - ay
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(bth - ath)], axis=-1)


def between_floats(a: Sequence[float], b: Sequence[float]) -> list[float]:
    """:func:`between` of one pair of poses given as Python floats (same arithmetic, no
    array overhead; for loops that keep poses in floats, such as the batch replay)."""
    ax, ay, ath = a
    bx, by, bth = b
    c, s = math.cos(ath), math.sin(ath)
    dx, dy = bx - ax, by - ay
    return [c * dx + s * dy, -s * dx + c * dy, (bth - ath + math.pi) % (2.0 * math.pi) - math.pi]


def compose_floats(a: Sequence[float], b: Sequence[float]) -> list[float]:
    """:func:`compose` of one pair of poses given as Python floats (as
    :func:`between_floats`)."""
    ax, ay, ath = a
    bx, by, bth = b
    c, s = math.cos(ath), math.sin(ath)
    return [ax + c * bx - s * by, ay + s * bx + c * by,
            (ath + bth + math.pi) % (2.0 * math.pi) - math.pi]


def compose_jacobians(a: ArrayLike, b: ArrayLike) -> tuple[Array, Array]:
    """Jacobians of ``a ⊕ b`` with respect to ``a`` and to ``b``: two ``(..., 3, 3)`` arrays."""
    ax, ay, ath = _split(a)
    bx, by, _ = _split(b)
    c, s = np.cos(ath), np.sin(ath)
    shape = np.broadcast_shapes(np.shape(ath), np.shape(bx))
    ja = np.zeros(shape + (3, 3))
    ja[..., 0, 0] = 1.0
    ja[..., 1, 1] = 1.0
    ja[..., 2, 2] = 1.0
    ja[..., 0, 2] = -s * bx - c * by
    ja[..., 1, 2] = c * bx - s * by
    jb = np.zeros(shape + (3, 3))
    jb[..., 0, 0] = c
    jb[..., 0, 1] = -s
    jb[..., 1, 0] = s
    jb[..., 1, 1] = c
    jb[..., 2, 2] = 1.0
    return ja, jb


def inverse_jacobian(a: ArrayLike) -> Array:
    """Jacobian ``(..., 3, 3)`` of ``inverse(a)`` with respect to ``a``."""
    ax, ay, ath = _split(a)
    c, s = np.cos(ath), np.sin(ath)
    j = np.zeros(np.shape(ath) + (3, 3))
    j[..., 0, 0] = -c
    j[..., 0, 1] = -s
    j[..., 0, 2] = s * ax - c * ay
    j[..., 1, 0] = s
    j[..., 1, 1] = -c
    j[..., 1, 2] = c * ax + s * ay
    j[..., 2, 2] = -1.0
    return j


def rotation(yaw_rad: ArrayLike) -> Array:
    """Rotation matrices ``(..., 2, 2)`` of angles ``(...)``."""
    th = np.asarray(yaw_rad, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


def transform_points(pose: ArrayLike, points: ArrayLike) -> Array:
    """Points ``(..., 2)`` of the pose's child frame into its parent frame."""
    x, y, th = _split(pose)
    p = np.asarray(points, dtype=float)
    c, s = np.cos(th), np.sin(th)
    return np.stack([x + c * p[..., 0] - s * p[..., 1], y + s * p[..., 0] + c * p[..., 1]],
                    axis=-1)


def inverse_transform_points(pose: ArrayLike, points: ArrayLike) -> Array:
    """Points ``(..., 2)`` of the parent frame seen in the pose's child frame."""
    x, y, th = _split(pose)
    p = np.asarray(points, dtype=float)
    c, s = np.cos(th), np.sin(th)
    dx, dy = p[..., 0] - x, p[..., 1] - y
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=-1)


def transform_line(pose: ArrayLike, line: ArrayLike) -> Array:
    """A line ``(rho, alpha)`` of the pose's child frame in its parent frame, ``rho >= 0``.

    The line is ``x cos(alpha) + y sin(alpha) = rho``. ``line``: (..., 2) (metres, radians).
    """
    x, y, th = _split(pose)
    ln = np.asarray(line, dtype=float)
    alpha = ln[..., 1] + th
    rho = ln[..., 0] + x * np.cos(alpha) + y * np.sin(alpha)
    flip = rho < 0
    return np.stack([np.abs(rho), wrap_angle(np.where(flip, alpha + math.pi, alpha))], axis=-1)


def inverse_transform_line(pose: ArrayLike, line: ArrayLike) -> Array:
    """A line ``(rho, alpha)`` of the parent frame seen in the pose's child frame, ``rho >= 0``."""
    x, y, th = _split(pose)
    ln = np.asarray(line, dtype=float)
    alpha = ln[..., 1]
    rho = ln[..., 0] - x * np.cos(alpha) - y * np.sin(alpha)
    flip = rho < 0
    return np.stack([np.abs(rho), wrap_angle(np.where(flip, alpha + math.pi, alpha) - th)],
                    axis=-1)


def interpolate(a: ArrayLike, b: ArrayLike, frac: ArrayLike) -> Array:
    """Pose a fraction of the way from a to b (linear in x, y; shortest way in yaw). (..., 3)."""
    pa = np.asarray(a, dtype=float)
    pb = np.asarray(b, dtype=float)
    f = np.asarray(frac, dtype=float)[..., None]
    out = pa + f * (pb - pa)
    dth = wrap_angle(pb[..., 2] - pa[..., 2])
    out[..., 2] = wrap_angle(pa[..., 2] + f[..., 0] * dth)
    return out

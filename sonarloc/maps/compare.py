"""A built map against a surveyed (or simulated, true) one: each built feature's error.

Used to check what ``sd_m`` says (``benchmarks/bench_map_sd.py``): a feature's error
divided by its ``sd_m`` is about 1 (points: up to ~1.4, the error being 2-D) when the
stated SD is honest.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc import se2
from sonarloc.localize.features import FeatureMap
from sonarloc.maps.build import BuiltFeature
from sonarloc.maps.geojson import Map

#: a built wall is compared with true walls within this angle of its direction
WALL_ANGLE_DEG = 10.0


def feature_errors(features: Sequence[BuiltFeature], true_map: Map, gate_m: float = 0.5
                   ) -> list[tuple[BuiltFeature, float]]:
    """Each built feature with its error [m] against ``true_map``.

    A point's error is its distance from the nearest true point feature (pole, rod,
    corner, ...); a wall's is the larger distance of its two ends from the line of the
    nearest true wall within :data:`WALL_ANGLE_DEG` of its direction. Features with
    nothing true within ``gate_m`` [m] are left out (a ghost, or a feature off by more).
    """
    true = FeatureMap.from_map(true_map)
    cos_max = math.cos(math.radians(WALL_ANGLE_DEG))
    out: list[tuple[BuiltFeature, float]] = []
    for f in features:
        if f.kind == "wall":
            d = f.coords[1] - f.coords[0]
            err = math.inf
            for a, b in true.wall_ends:
                e = b - a
                if abs(float(d @ e)) < cos_max * np.hypot(*d) * np.hypot(*e):
                    continue
                nrm = np.array([-e[1], e[0]]) / np.hypot(*e)
                err = min(err, max(abs(float((p - a) @ nrm)) for p in f.coords))
        elif len(true.point_xy):
            err = float(np.min(np.hypot(*(true.point_xy - f.coords).T)))
        else:
            err = math.inf
        if err <= gate_m:
            out.append((f, err))
    return out


def rigid_alignment(features: Sequence[BuiltFeature], true_map: Map, gate_m: float = 0.5
                    ) -> NDArray[np.float64]:
    """The rigid motion (x_m, y_m, yaw_rad: built map frame -> true frame) that best puts
    the built point features' centres onto their nearest true points within ``gate_m``
    (least squares, Kabsch; trimmed: refitted without pairs further apart than 3 times
    the median and 2 cm, matched again after each fit); the identity with fewer than
    two pairs.

    A map built without a pose track is in the frame of the log's ``init`` pose, whose
    error (its SDs) moves every feature alike: errors after this motion are the map's
    own shape error.
    """
    true = FeatureMap.from_map(true_map)
    built = np.array([f.coords for f in features if f.kind != "wall"], dtype=float)
    motion = np.zeros(3)
    if len(true.point_xy) == 0 or len(built) < 2:
        return motion
    for _ in range(5):
        at = se2.transform_points(motion, built)
        d = np.hypot(*(at[:, None, :] - true.point_xy[None, :, :]).transpose(2, 0, 1))
        near = np.argmin(d, axis=1)
        dist = d[np.arange(len(at)), near]
        keep = dist <= gate_m
        if keep.sum() >= 3:
            keep &= dist <= max(3.0 * float(np.median(dist[keep])), 0.02)
        if keep.sum() < 2:
            return motion
        p, q = built[keep], true.point_xy[near[keep]]
        pm, qm = p.mean(axis=0), q.mean(axis=0)
        u, _, vt = np.linalg.svd((p - pm).T @ (q - qm))
        rot = (u @ vt).T
        if np.linalg.det(rot) < 0:  # pragma: no cover - a reflection fits better: no motion
            return np.zeros(3)
        new = np.array([*(qm - rot @ pm), math.atan2(rot[1, 0], rot[0, 0])])
        if np.allclose(new, motion, atol=1e-12):
            break
        motion = new
    return motion


def moved(features: Sequence[BuiltFeature], motion: ArrayLike) -> list[BuiltFeature]:
    """The features moved by the rigid motion ``motion`` (x_m, y_m, yaw_rad)."""
    return [replace(f, coords=se2.transform_points(motion, np.asarray(f.coords, dtype=float)))
            for f in features]

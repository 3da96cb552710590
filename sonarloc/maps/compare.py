"""A built map against a surveyed (or simulated, true) one: each built feature's error.

Used to check what ``sd_m`` says (``benchmarks/bench_map_sd.py``): a feature's error
divided by its ``sd_m`` is about 1 (points: up to ~1.4, the error being 2-D) when the
stated SD is honest.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

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

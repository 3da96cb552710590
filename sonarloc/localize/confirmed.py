"""Which map features confirmed the pose lately, and whether together they pin it.

The :class:`~sonarloc.localize.localizer.Localizer` says ``tracking`` only while the
map features confirmed (fused, or associated and inside the gate but skipped because
the robot has not moved since: ``LocalizerConfig.update_min_d``) within the last
``dead_reckoning_after_s`` constrain all three degrees of freedom of the pose (x, y,
yaw) together:

* two point features at least :data:`MIN_POINT_SEPARATION_M` apart, or
* a point feature and a wall, or
* two walls at least :data:`MIN_WALL_ANGLE_DEG` apart in direction.

A single point (or points closer than that) leaves the yaw and the position on a
circle around it unconstrained; a single wall (or walls within that angle of
parallel) leaves the position along it unconstrained. The filter's covariance need not
say so (linearised, it is overconfident in those directions), so the status checks
the geometry itself. A whole-pose fix (a global relocalization) confirms all three.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np

from sonarloc.localize.features import FeatureMap

#: Two point features closer than this [m] count as one for the status.
MIN_POINT_SEPARATION_M = 0.1
#: Two walls whose directions differ by less than this [deg] (modulo 180) count as
#: parallel for the status.
MIN_WALL_ANGLE_DEG = 5.0
#: Kind of a confirmation of the whole pose (a relocalization fix), not of one feature.
POSE = "pose"


class ConfirmedFeatures:
    """The latest time [s] each map feature (``("point" | "wall", index)``, or
    ``(POSE, -1)`` for a whole-pose fix) confirmed the pose: at most one entry per map
    feature, and entries older than the window of the latest :meth:`recent` query are
    dropped (queries come in time order)."""

    __slots__ = ("_t", "_newest")

    def __init__(self) -> None:
        self._t: dict[tuple[str, int], float] = {}
        self._newest = -math.inf

    def add(self, t_s: float, kind: str, index: int) -> None:
        """Record that feature (``kind``, ``index``) confirmed the pose at ``t_s``."""
        key = (kind, int(index))
        old = self._t.get(key)
        if old is None or t_s > old:
            self._t[key] = t_s
        self._newest = max(self._newest, t_s)

    def clear(self) -> None:
        self._t.clear()
        self._newest = -math.inf

    @property
    def newest_s(self) -> float:
        """Time of the latest confirmation [s] (-inf: none)."""
        return self._newest

    def __len__(self) -> int:
        return len(self._t)

    def recent(self, since_s: float) -> list[tuple[str, int]]:
        """The features confirmed at or after ``since_s`` (older entries are dropped:
        call with non-decreasing ``since_s``)."""
        old = [k for k, t in self._t.items() if t < since_s]
        for k in old:
            del self._t[k]
        return sorted(self._t)


def _names(ids: Sequence[str], limit: int = 3) -> str:
    shown = ", ".join(ids[:limit])
    return shown + (f" and {len(ids) - limit} more" if len(ids) > limit else "")


def _spread_deg(alpha_rad: Iterable[float]) -> float:
    """Largest angle [deg] between two of the line directions ``alpha_rad`` (modulo 180
    deg: a wall and its opposite face are the same direction)."""
    a = np.mod(np.asarray(list(alpha_rad), dtype=float), math.pi)
    if a.size < 2:
        return 0.0
    d = np.abs(a[:, None] - a[None, :])
    return float(np.degrees(np.max(np.minimum(d, math.pi - d))))


def missing_dof(fmap: FeatureMap, features: Iterable[tuple[str, int]], window_s: float
                ) -> str:
    """What the confirmed ``features`` (``("point" | "wall", index)`` of ``fmap``, or
    ``(POSE, -1)``) leave unconstrained of the pose, as the status reason says it ("" when
    they pin all three degrees of freedom; see the module docstring). ``window_s``: the
    window they were confirmed in [s], for the text."""
    feats = list(features)
    if any(kind == POSE for kind, _ in feats):
        return ""
    pts = sorted({i for kind, i in feats if kind == "point"})
    walls = sorted({i for kind, i in feats if kind == "wall"})
    if pts and walls:
        return ""
    when = f"confirmed in the last {window_s:g} s"
    if pts:
        xy = fmap.point_xy[pts]
        d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
        if float(np.max(d)) >= MIN_POINT_SEPARATION_M:
            return ""
        ids = [fmap.point_id[i] for i in pts]
        if len(pts) == 1:
            return f"only one point landmark ({ids[0]}) {when}: yaw unconstrained"
        return (f"only point landmarks less than {MIN_POINT_SEPARATION_M:g} m apart "
                f"({_names(ids)}) {when}: yaw unconstrained")
    if walls:
        if _spread_deg(fmap.wall_line[walls, 1]) >= MIN_WALL_ANGLE_DEG:
            return ""
        ids = [fmap.wall_id[i] for i in walls]
        if len(walls) == 1:
            return f"only one wall ({ids[0]}) {when}: position along it unconstrained"
        return (f"only walls within {MIN_WALL_ANGLE_DEG:g} deg of parallel ({_names(ids)}) "
                f"{when}: position along them unconstrained")
    return f"no landmark {when}"

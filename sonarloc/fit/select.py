"""Model selection: point or line, Gaussian or piston beam, one reflector or two.

Every choice is recorded in the result's ``extra`` (``kind_basis``, ``tier_basis``)
so a user can see what was chosen and whether the data could tell:

* **kind**: where the transducer moved within the segment, a point and a line are
  both fitted and the likelihoods compared (``kind_basis = "motion"``); if they fit
  equally well, or the segment was taken from one spot (a pan cannot tell a pole
  from a wall), the reflector strength decides: kappa below ``kappa_wall_us`` is a
  wall-like specular reflector (``kind_basis = "strength"``).
* **tier**: the piston beam is fitted only where, at the Gaussian fit, the two beams
  predict readings that differ by more than the tolerance the physics uses
  (:data:`sonarloc.physics.tiers.GAUSS_TOLERANCE_US`) or detection probabilities
  that differ; it is kept only if it explains the data better.
* **overlap**: residuals that run in long same-sign blocks with an excess chi-square
  say two reflectors were merged; the result is then ``UNRESOLVED``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from sonarloc.fit import model as M
from sonarloc.fit.lsq import BatchFit, FitConfig, SegmentBatch, _take, fit_batch
from sonarloc.physics.tiers import GAUSS_TOLERANCE_US

if TYPE_CHECKING:  # pragma: no cover
    from sonarloc.fit.landmarks import _Choice

KAPPA_WALL_US = 0.32
"""Kappa [us] below which a reflector is taken for a wall when motion cannot tell
(geometric mean of the paper's plane 0.15 us and pole 0.67 us)."""

KIND_THRESHOLD = 9.0
"""Difference of -2 log-likelihood (same number of parameters) that decides point
against line (a likelihood ratio of e^4.5 ~ 90)."""

TIER_THRESHOLD = 4.0
"""Difference of -2 log-likelihood for the piston beam to replace the Gaussian one."""


def choose_kind(point: BatchFit, line: BatchFit | None, moving: NDArray[np.int64],
                cfg: FitConfig, kappa_wall_us: float = KAPPA_WALL_US,
                threshold: float = KIND_THRESHOLD
                ) -> tuple[list[str], list[list[str]], list[dict[str, object]]]:
    """Kind per segment, notes and extra fields (``kind_basis``, ``kind_dcost``)."""
    B = point.local.shape[0]
    row_of = {int(b): j for j, b in enumerate(moving.tolist())}
    kinds: list[str] = []
    notes: list[list[str]] = []
    extra: list[dict[str, object]] = []
    for b in range(B):
        by_strength = "line" if point.local[b, 2] < kappa_wall_us else "point"
        j = row_of.get(b)
        if j is None or line is None:
            kinds.append(by_strength)
            notes.append([])
            extra.append({"kind_basis": "strength",
                          "kind_note": "one viewpoint: point and line give the same readings"})
            continue
        d = float(point.robust_cost[b] - line.robust_cost[j])   # > 0: line fits better
        if d > threshold:
            kinds.append("line")
            extra.append({"kind_basis": "motion", "kind_dcost": d})
        elif d < -threshold:
            kinds.append("point")
            extra.append({"kind_basis": "motion", "kind_dcost": d})
        else:
            kinds.append(by_strength)
            extra.append({"kind_basis": "strength", "kind_dcost": d,
                          "kind_note": "motion too small to tell point from line"})
        notes.append([])
    return kinds, notes, extra


def _tier_differs(batch: SegmentBatch, j: int, fit: BatchFit, cfg: FitConfig) -> bool:
    """Whether Gaussian and piston beams predict distinguishable data at this fit."""
    mod = cfg.module
    p = fit.local[0]
    sel = fit.used[0]
    geo = M.geometry(fit.kind, p[0], p[1], batch.px[j, sel], batch.py[j, sel], batch.yaw[j, sel])
    gg, _, _ = M.beam_delay_factor(geo.theta, "gauss", mod, derivative=False)
    gp, _, _ = M.beam_delay_factor(geo.theta, "piston", mod, derivative=False)
    lim = mod.detection_limit_us
    dg = np.abs(np.minimum(p[2] * gg, lim) - np.minimum(p[2] * gp, lim))
    if np.any(dg > GAUSS_TOLERANCE_US):
        return True
    nv = batch.ne_valid[j]
    if cfg.detection and nv.any():
        ng = M.geometry(fit.kind, p[0], p[1], batch.ne_px[j, nv], batch.ne_py[j, nv],
                        batch.ne_yaw[j, nv])
        _, _, lg = M.beam_delay_factor(ng.theta, "gauss", mod, derivative=False)
        _, _, lp = M.beam_delay_factor(ng.theta, "piston", mod, derivative=False)
        from scipy.special import ndtr

        pg = ndtr(M.detection_z(p[2], lg, mod))
        pp = ndtr(M.detection_z(p[2], lp, mod))
        if np.any(np.abs(pg - pp) > 0.2):
            return True
    return False


def choose_tier(batch: SegmentBatch, choices: list[_Choice], cfg: FitConfig,
                threshold: float = TIER_THRESHOLD) -> None:
    """Refit with the piston beam where it matters; keep it where it fits better."""
    need = [j for j, ch in enumerate(choices) if _tier_differs(batch, j, ch.fit, cfg)]
    for j, ch in enumerate(choices):
        if j not in need:
            ch.extra["tier_basis"] = "gauss suffices: beams agree within the data"
    for kind in ("point", "line"):
        idx = np.array([j for j in need if choices[j].kind == kind], dtype=np.int64)
        if idx.size == 0:
            continue
        pist = fit_batch(_take(batch, idx), kind, "piston", cfg)
        for k, j in enumerate(idx.tolist()):
            ch = choices[j]
            d = float(ch.fit.robust_cost[0] - pist.robust_cost[k])  # > 0: piston better
            ch.extra["tier_dcost"] = d
            if d > threshold:
                ch.fit = pist.take(np.array([k]))
                ch.tier = "piston"
                ch.extra["tier_basis"] = "piston fits the data better"
            elif d < -threshold:
                ch.extra["tier_basis"] = "gauss fits the data better"
            else:
                ch.extra["tier_basis"] = "data cannot tell gauss from piston: gauss kept"


def _runs_z(signs: NDArray[np.bool_]) -> float:
    """Wald-Wolfowitz runs test statistic (negative: fewer runs than chance)."""
    n = signs.size
    n1 = int(signs.sum())
    n2 = n - n1
    if n1 == 0 or n2 == 0 or n < 8:
        return 0.0
    runs = 1 + int(np.count_nonzero(signs[1:] != signs[:-1]))
    mu = 2.0 * n1 * n2 / n + 1.0
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
    return (runs - mu) / math.sqrt(var) if var > 0 else 0.0


def overlap_check(batch: SegmentBatch, choices: list[_Choice], cfg: FitConfig,
                  runs_z_max: float = -4.0, chi2_ratio_min: float = 2.0) -> None:
    """Flag segments whose residuals show a second reflector (``extra['overlap']``)."""
    for j, ch in enumerate(choices):
        f = ch.fit
        used = f.used[0]
        n = int(used.sum())
        if n < 8:
            continue
        # order the echoes by off-axis angle at the fit
        p = f.local[0]
        geo = M.geometry(f.kind, p[0], p[1], batch.px[j, used], batch.py[j, used],
                         batch.yaw[j, used])
        order = np.argsort(geo.theta)
        r = f.resid[0][used][order]
        z = _runs_z(r > 0)
        ratio = float(f.chi2[0]) / max(n - 3, 1)
        ch.extra["runs_z"] = z
        if z < runs_z_max and ratio > chi2_ratio_min:
            ch.extra["overlap"] = (f"residuals run in blocks (runs z = {z:.1f}, "
                                   f"chi2/dof = {ratio:.1f}): two reflectors merged?")

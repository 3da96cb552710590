"""Model selection: point or line, Gaussian or piston beam, one reflector or two.

Every choice is recorded in the result's ``extra`` (``kind_basis``, ``tier_basis``)
so a user can see what was chosen and whether the data could tell:

* **kind**: where the transducer moved within the segment, a point and a line are
  both fitted and the likelihoods compared (``kind_basis = "motion"``); if they fit
  equally well, or the segment was taken from one spot (a pan cannot tell a pole
  from a wall), the reflector strength decides: kappa below ``kappa_wall_us`` is a
  wall-like specular reflector (``kind_basis = "strength"``).
* **tier**: other models are fitted only where the data can tell them from the
  Gaussian one: ``waveform`` (the simulated module: ripple jumps, late weak echoes;
  also the model of the simulator's ``auto`` tier) where, at the Gaussian fit, its
  predicted readings differ by more than the tolerance the physics uses
  (:data:`sonarloc.physics.tiers.GAUSS_TOLERANCE_US`) or its detection probabilities
  differ, and a score test says the residuals lean towards it; ``piston`` (side
  lobes) where they differ and the Gaussian fit does not explain the data (chi-square
  3 SDs above its mean, or a 4-sigma echo/no-echo event) or leans towards it.
  ``waveform`` replaces ``gauss`` when it fits better at all (same parameters), another
  tier only if it fits better by ``TIER_THRESHOLD``.
* **overlap**: residuals that run in long same-sign blocks with an excess chi-square
  say two reflectors were merged; the result is then ``UNRESOLVED``.

Everything is vectorised over the segments of a batch.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.special import ndtr

from sonarloc.fit import model as M
from sonarloc.fit.lsq import (
    BatchFit,
    FitConfig,
    SegmentBatch,
    _solve_pivoted,
    _take,
    fit_batch,
    tof_jacobian,
    tof_jacobian_at,
)
from sonarloc.physics.tiers import GAUSS_TOLERANCE_US

Array = NDArray[np.float64]

KAPPA_WALL_US = 0.32
"""Kappa [us] below which a reflector is taken for a wall when motion cannot tell
(geometric mean of the paper's plane 0.15 us and pole 0.67 us)."""

KIND_THRESHOLD = 9.0
"""Difference of -2 log-likelihood (same number of parameters) that decides point
against line (a likelihood ratio of e^4.5 ~ 90)."""

TIER_THRESHOLD = 4.0
"""Difference of -2 log-likelihood for another beam tier to replace the Gaussian one."""

WAVEFORM_THRESHOLD = 0.0
"""Difference of -2 log-likelihood for ``waveform`` to replace ``gauss`` or ``piston``:
none. The tiers have the same parameters, so the likelihood alone decides; the waveform
is the module's own processing, and a Gaussian fit that ties with it does so with a
kappa that absorbs the waveform's extra delay (biased high by 40-170 %), so a tie must
not go to ``gauss`` by default."""

WAVEFORM_SCORE_Z = 0.0
"""Score-test pre-screen for ``waveform``: fitted where its predictions differ from the
Gaussian fit's and the residuals lean its way at all (z > 0). A Gaussian fit whose
kappa absorbed the waveform's extra delay leaves residuals that barely lean, so the
stricter screen of the other tiers (``SCORE_Z``) kept such fits (measured: 10 % of
auto-tier poles, kappa +150 %); z > 0 finds as many as no screen at all, at half the
extra cost on Gaussian data."""

TIER_TIE = 9.0
"""Where ``gauss`` is kept and the waveform fit is worse by less than this (-2 log-
likelihood), kappa's variance gets the squared difference of the two fits' kappas
(``extra["kappa_waveform_us"]``): the data cannot say which strength is meant."""

SCORE_Z = 1.5
"""Score-test statistic above which the residuals of a Gaussian fit are taken to lean
towards another tier, which is then fitted (a cheap pre-screen: the likelihood ratio
decides, and for these nonlinear models it can exceed ``TIER_THRESHOLD`` already at a
score of 1.7)."""

SURPRISE = 16.0
"""An event whose probability under a fit is below exp(-SURPRISE/2) (a 4-sigma event)
says the fit's model does not explain the data."""

MOTION_BASELINE_M = 0.02
"""Transducer displacement within a segment above which point and line are both fitted."""

_FIELDS = ("local", "cov", "cost", "chi2", "n_used", "used", "resid", "arc", "converged",
           "robust_cost")


@dataclass
class Selection:
    """Per-segment results of the chosen models (arrays over the batch, as BatchFit).

    ``kind``/``tier``: (B,) object arrays of strings; ``extra``: one dict per segment
    with what was chosen and why.
    """

    kind: NDArray[np.object_]
    tier: NDArray[np.object_]
    local: Array
    cov: Array
    cost: Array
    chi2: Array
    n_used: NDArray[np.int64]
    used: NDArray[np.bool_]
    resid: Array
    arc: Array
    converged: NDArray[np.bool_]
    robust_cost: Array
    extra: list[dict[str, object]] = field(default_factory=list)

    @classmethod
    def from_fit(cls, fit: BatchFit) -> Selection:
        B = fit.local.shape[0]
        c = [getattr(fit, f).copy() for f in _FIELDS]
        return cls(np.full(B, fit.kind, dtype=object), np.full(B, fit.tier, dtype=object),
                   c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9],
                   [{} for _ in range(B)])

    def put(self, idx: NDArray[np.int64], fit: BatchFit) -> None:
        """Take the rows of ``fit`` (one per entry of ``idx``) for segments ``idx``."""
        self.kind[idx] = fit.kind
        self.tier[idx] = fit.tier
        for f in _FIELDS:
            getattr(self, f)[idx] = getattr(fit, f)

    def subset(self, idx: NDArray[np.int64]) -> Selection:
        """Rows ``idx`` (any kinds and tiers) as a new selection: arrays and ``extra``
        dicts copied, so adding to one leaves the other as it was."""
        c = [getattr(self, f)[idx] for f in _FIELDS]
        return Selection(self.kind[idx], self.tier[idx], c[0], c[1], c[2], c[3], c[4], c[5],
                         c[6], c[7], c[8], c[9], [dict(self.extra[j]) for j in idx.tolist()])

    def rows(self, idx: NDArray[np.int64]) -> BatchFit:
        """Rows ``idx`` as a BatchFit (they must share kind and tier)."""
        kinds, tiers = set(self.kind[idx]), set(self.tier[idx])
        if len(kinds) > 1 or len(tiers) > 1:
            raise ValueError("rows of mixed kind or tier")
        return BatchFit(str(kinds.pop()), str(tiers.pop()),
                        *(getattr(self, f)[idx] for f in _FIELDS))


def motion_baseline_m(batch: SegmentBatch) -> Array:
    """Largest distance (B,) of an echo's transducer position from the reference [m]."""
    return np.max(np.hypot(batch.px, batch.py) * batch.valid, axis=1)


def choose_kind(sel: Selection, line: BatchFit | None, moving: NDArray[np.int64],
                kappa_wall_us: float = KAPPA_WALL_US,
                threshold: float = KIND_THRESHOLD) -> None:
    """Point (already in ``sel``) or line (``line``: fits of segments ``moving``)."""
    by_strength = np.where(sel.local[:, 2] < kappa_wall_us, "line", "point")
    basis = np.full(sel.kind.shape, "strength", dtype=object)
    d = np.full(sel.kind.shape, np.nan)
    if line is not None and moving.size:
        d[moving] = sel.robust_cost[moving] - line.robust_cost   # > 0: line fits better
        take_line = moving[d[moving] > threshold]
        keep_point = moving[d[moving] < -threshold]
        basis[take_line] = "motion"
        basis[keep_point] = "motion"
        # undecided moving segments whose strength says wall take the line fit too
        undecided = moving[np.abs(d[moving]) <= threshold]
        wall = undecided[by_strength[undecided] == "line"]
        pick = np.concatenate([take_line, wall])
        if pick.size:
            rows = np.searchsorted(moving, pick)
            sel.put(pick, line.take(rows))
    fin = np.isfinite(d)
    # one viewpoint: the same fit, read as a wall
    sel.kind[(basis == "strength") & (sel.kind == "point") & (by_strength == "line") & ~fin] = (
        "line")
    for ex, bs, f, dv in zip(sel.extra, basis.tolist(), fin.tolist(), d.tolist(),
                             strict=True):
        ex["kind_basis"] = bs
        if f:
            ex["kind_dcost"] = dv
        if bs == "strength":
            ex["kind_note"] = ("motion too small to tell point from line" if f
                               else "one viewpoint: point and line give the same readings")


@dataclass(frozen=True)
class _GaussModel:
    """The Gaussian fits' model at the segments of :func:`_tier_model` (what the score
    and misfit tests need, from the same pass as the tier predictions)."""

    J: Array
    """Whitened TOF Jacobian (B, 3, Nd) (:func:`sonarloc.fit.lsq.tof_jacobian`)."""
    delay: Array
    """Mean delays of the echoes (B, Nd)."""
    sd: Array
    """TOF SDs of the echoes (B, Nd)."""
    log_p: Array
    """log P(echo) of the echoes (B, Nd) (zeros without the detection model)."""
    zn: Array | None
    """Detection margins z of the no-echo readings (B, Nn); None without the detection
    model or no-echo readings."""

    def rows(self, r: NDArray[np.int64]) -> tuple[Array, Array, Array]:
        """``(J, delay, sd)`` of rows ``r`` (for :func:`score_z`)."""
        return self.J[r], self.delay[r], self.sd[r]


def _tier_model(batch: SegmentBatch, sel: Selection, idx: NDArray[np.int64], kind: str,
                tiers: tuple[str, ...], cfg: FitConfig, jacobian: bool = False
                ) -> tuple[dict[str, tuple[Array, Array | None]], _GaussModel | None]:
    """:func:`_tier_predictions` and, with ``jacobian`` (``"gauss"`` among ``tiers``),
    the Gaussian fits' :class:`_GaussModel` from the same pass (the same numbers as
    :func:`sonarloc.fit.lsq.tof_jacobian_at` and :func:`misfit` compute)."""
    mod = cfg.module
    sub = _take(batch, idx)
    p = sel.local[idx]
    K = p[:, 2:3]
    geo = M.geometry(kind, p[:, 0:1], p[:, 1:2], sub.px, sub.py, sub.yaw)
    ng = (M.geometry(kind, p[:, 0:1], p[:, 1:2], sub.ne_px, sub.ne_py, sub.ne_yaw)
          if cfg.detection and sub.ne_valid.any() else None)
    out: dict[str, tuple[Array, Array | None]] = {}
    beams: dict[str, tuple[Array, Array, Array | None, Array | None, Array | None]] = {}
    gm = None
    for t in tiers:
        beam = M.BEAMS[t]
        if beam not in beams:
            g, dg, lg = M.beam_delay_factor(geo.theta, beam, mod,
                                            derivative=jacobian and beam == "gauss")
            z = M.detection_z(K, lg, mod) if cfg.detection else None
            zn = None if ng is None else M.detection_z(
                K, M.beam_delay_factor(ng.theta, beam, mod, derivative=False)[2], mod)
            beams[beam] = (g, dg, z, zn, None if zn is None else ndtr(zn))
        g, dg, z, zn, pr = beams[beam]
        if t == "gauss" and jacobian:
            assert dg is not None
            J, et, sd = tof_jacobian_at(geo, K, g, dg, z, t, mod)
            gm = _GaussModel(J, et.delay, sd, et.log_p, zn)
            out[t] = (et.delay, pr)
        else:
            out[t] = (M.mean_delay(K, g, mod, z, t)[0], pr)
    return out, gm


def _tier_predictions(batch: SegmentBatch, sel: Selection, idx: NDArray[np.int64], kind: str,
                      tiers: tuple[str, ...], cfg: FitConfig
                      ) -> dict[str, tuple[Array, Array | None]]:
    """Mean delays of the echoes (B, Nd) and detection probabilities of the no-echo
    readings (B, Nn; None without the detection model or no-echo readings) that each
    tier predicts at the fits of segments ``idx`` (one geometry for all tiers, one beam
    pattern and detection probabilities for the tiers that share it)."""
    return _tier_model(batch, sel, idx, kind, tiers, cfg)[0]


def _tiers_differ(batch: SegmentBatch, sel: Selection, idx: NDArray[np.int64], kind: str,
                  tier_a: str, tier_b: str, cfg: FitConfig,
                  pred: dict[str, tuple[Array, Array | None]] | None = None
                  ) -> NDArray[np.bool_]:
    """Whether two tiers predict distinguishable data at the fits of segments ``idx``:
    a used echo's mean delay differing by more than the physics' tolerance
    (:data:`sonarloc.physics.tiers.GAUSS_TOLERANCE_US`) or a no-echo reading's detection
    probability by more than 0.2. ``pred``: :func:`_tier_predictions` of both tiers at
    these segments, if already computed."""
    if pred is None:
        pred = _tier_predictions(batch, sel, idx, kind, (tier_a, tier_b), cfg)
    (da, pa), (db, pb) = pred[tier_a], pred[tier_b]
    need = np.any((np.abs(da - db) > GAUSS_TOLERANCE_US) & sel.used[idx], axis=1)
    if pa is not None and pb is not None:
        need |= np.any((np.abs(pa - pb) > 0.2) & batch.ne_valid[idx], axis=1)
    return need


def score_z(batch: SegmentBatch, sel: Selection, idx: NDArray[np.int64], kind: str,
            tier_a: str, tier_b: str, cfg: FitConfig, delay_b: Array | None = None,
            model_a: tuple[Array, Array, Array] | None = None) -> Array:
    """Score (Lagrange multiplier) test of tier ``tier_b`` against the fit in ``tier_a``.

    With the mean readings of the two tiers m_a, m_b at the fit, the test asks whether
    moving the model from m_a towards m_b would explain the residuals: z = e.d / |d|
    with e the standardised residuals and d = (m_b - m_a)/s with the directions the fit
    already has (its Jacobian) projected out. z ~ N(0, 1) when ``tier_a`` is right;
    large z says the data lean towards ``tier_b``. Costs one model evaluation (two
    without ``delay_b``, ``tier_b``'s mean delays (B, Nd) at the fits if known; none
    with ``model_a``, the whitened Jacobian, mean delays and SDs of ``tier_a`` there,
    :func:`sonarloc.fit.lsq.tof_jacobian`'s outputs).
    """
    mod = cfg.module
    p = sel.local[idx]
    if model_a is not None:
        J, da, sd = model_a
    else:
        sub = _take(batch, idx)
        J, da, sd = tof_jacobian(kind, tier_a, p, sub, cfg)
    if delay_b is None:
        sub = _take(batch, idx)
        geo = M.geometry(kind, p[:, 0:1], p[:, 1:2], sub.px, sub.py, sub.yaw)
        g, _, lg = M.beam_delay_factor(geo.theta, tier_b, mod, derivative=False)
        K = p[:, 2:3]
        z = M.detection_z(K, lg, mod) if cfg.detection else None
        delay_b = M.mean_delay(K, g, mod, z, tier_b)[0]
    db = delay_b
    used = sel.used[idx]
    d = np.where(used, (db - da) / sd, 0.0)
    J = J * used[:, None, :]
    JJ = np.matmul(J, np.swapaxes(J, 1, 2))
    # (pivoted, least squares where singular: two columns can be proportional, e.g.
    # range and kappa where every used echo has the same off-axis angle)
    coef = _solve_pivoted(JJ, np.einsum("bkn,bn->bk", J, d))
    d_perp = d - np.einsum("bk,bkn->bn", coef, J)
    norm = np.sqrt((d_perp * d_perp).sum(1))
    e = sel.resid[idx] * used
    return np.where(norm > 1e-9, (e * d_perp).sum(1) / np.maximum(norm, 1e-9), 0.0)


def misfit(batch: SegmentBatch, sel: Selection, idx: NDArray[np.int64], kind: str,
           cfg: FitConfig, surprise: float = SURPRISE,
           model: tuple[Array, Array | None] | None = None) -> NDArray[np.bool_]:
    """Segments whose fit does not explain their data as the noise model says.

    The TOF chi-square exceeds its mean by 3 SDs (dof + 3 sqrt(2 dof)), or some echo
    or no-echo event had a probability below exp(-surprise / 2) under the fit.
    ``model``: log P(echo) of the echoes (B, Nd) and the detection margins z of the
    no-echo readings (B, Nn or None) under the fits, if known (:class:`_GaussModel`).
    """
    mod = cfg.module
    n = sel.n_used[idx]
    dof = np.maximum(n - 3, 1)
    bad = sel.chi2[idx] > dof + 3.0 * np.sqrt(2.0 * dof)
    if not cfg.detection:
        return bad
    if model is not None:
        lp, zn = model
        return bad | (-2.0 * _worst_log_p(lp, sel.used[idx], zn, batch.ne_valid[idx])
                      > surprise)
    sub = _take(batch, idx)
    p = sel.local[idx]
    tier = sel.tier[idx]
    for t in set(tier):
        j = np.flatnonzero(tier == t)
        s2 = _take(sub, j)
        K = p[j, 2:3]
        geo = M.geometry(kind, p[j, 0:1], p[j, 1:2], s2.px, s2.py, s2.yaw)
        g, _, lg = M.beam_delay_factor(geo.theta, str(t), mod, derivative=False)
        lp = M.echo_terms(K, g, M.detection_z(K, lg, mod), mod, want_info=False).log_p
        zn = None
        if s2.ne_valid.any():
            ng = M.geometry(kind, p[j, 0:1], p[j, 1:2], s2.ne_px, s2.ne_py, s2.ne_yaw)
            _, _, lgn = M.beam_delay_factor(ng.theta, str(t), mod, derivative=False)
            zn = M.detection_z(K, lgn, mod)
        bad[j] |= -2.0 * _worst_log_p(lp, sel.used[idx][j], zn, s2.ne_valid) > surprise
    return bad


def _worst_log_p(log_p: Array, used: NDArray[np.bool_], zn: Array | None,
                 ne_valid: NDArray[np.bool_]) -> Array:
    """The least probable event of each segment (B,): log P(echo) of the used echoes
    (B, Nd) and log P(no echo) of the valid no-echo readings at margins ``zn`` (B, Nn;
    None: none counted)."""
    worst = np.min(np.where(used, log_p, 0.0), axis=1)
    if zn is not None and ne_valid.any():
        lpn = M.noecho_terms(zn, want_info=False)[0]
        worst = np.minimum(worst, np.min(np.where(ne_valid, lpn, 0.0), axis=1))
    return worst


REBRACKET_DCOST = 100.0
"""An alternative tier refined from the Gaussian fit is bracketed again on the grid only
when it stays worse than its bar by more than this (-2 log-likelihood): a wrong basin
shows as hundreds of units, a tier the data do not follow (eq. 3 data) as a few tens.
Measured: where the fresh bracket changed the tier it had stayed 185-265 above the bar
(rods and poles at 2.8-3 m whose Gaussian fit collapsed to a flat curve, the continuous
rotation of benchmarks/bench_fit.py section 4; an auto-tier plane of
benchmarks/bench_fit_quality.py); of the 1153 refinements of that rotation that stayed
10-100 above it, none came below the bar after a fresh bracket (one came within
``TIER_TIE``, a kappa SD). Bracketing those again (a threshold of 10) was two thirds of
the re-bracketing cost."""


HOPELESS_DCOST = 200.0
"""A fit of an alternative tier (refined from the Gaussian fit, or bracketed again on the
grid by :func:`_rebracket`) is given up when, after
:data:`sonarloc.fit.lsq.STOP_CHECK_ITER` steps, it is still more than this above its bar
(-2 log-likelihood): such fits only creep on (the wall-strength segments of a continuous
rotation: all 26 passes, 0.5-13 per step, ending 230-1100 above the bar). Refined ones
that far above are bracketed again (``REBRACKET_DCOST`` is lower); the fit kept is the
better of the two, so only a hopeless alternative's reported likelihood gain
(``dcost_waveform``, ``dcost_piston``: where it stopped, a lower bound of the gain)
changes. Measured on the 200,000-reading rotation of benchmarks/bench_fit.py section 4:
from that step on, fits still more than 200 above their bar came
down by at most 158 (refined from the Gaussian fit) and 220 (bracketed again; none of
them ended within 21 of the bar, none of those that did reach it or came within
``TIER_TIE`` was given up)."""


def _rebracket(batch: SegmentBatch, idx: NDArray[np.int64], alt: BatchFit, bar: Array,
               cfg: FitConfig) -> BatchFit:
    """Refit, bracketed on the grid, the rows of ``alt`` (another tier refined from the
    Gaussian fit of segments ``idx``) whose -2 log-likelihood stayed above ``bar`` by
    more than ``REBRACKET_DCOST``: a
    Gaussian fit whose kappa compensates for the missing late weak echoes can sit in
    another basin of the other tier's objective; keep the better of the two."""
    redo = np.flatnonzero(alt.robust_cost > bar + REBRACKET_DCOST)
    if redo.size == 0:
        return alt
    fresh = fit_batch(batch, alt.kind, alt.tier, replace(cfg, start="grid"), rows=idx[redo],
                      stop_above=bar[redo] + HOPELESS_DCOST)
    better = fresh.robust_cost < alt.robust_cost[redo]
    if not better.any():
        return alt
    rows = redo[better]
    merged = {f: getattr(alt, f).copy() for f in _FIELDS}
    for f in _FIELDS:
        merged[f][rows] = getattr(fresh, f)[better]
    return BatchFit(alt.kind, alt.tier, *(merged[f] for f in _FIELDS))


def choose_tier(batch: SegmentBatch, sel: Selection, cfg: FitConfig,
                threshold: float = TIER_THRESHOLD) -> None:
    """Try the other tiers where the data can tell them from the Gaussian fit.

    ``waveform`` (the simulated module: ripple jumps, late weak echoes) is fitted where
    its predictions differ from the Gaussian fit's and the residuals lean towards it
    (:func:`score_z` above ``WAVEFORM_SCORE_Z``) and replaces ``gauss`` when its
    likelihood is higher (``WAVEFORM_THRESHOLD``); ``piston`` (eq. 3 with side lobes)
    where its predictions differ and the Gaussian fit does not explain the data or leans
    towards it (``SCORE_Z``), replacing ``gauss`` only if it lowers -2 log-likelihood by
    more than ``threshold``. The best alternative past its bar wins. An alternative
    refined from the Gaussian fit that stays worse than its bar is bracketed again on
    the grid (:func:`_rebracket`).
    """
    B = sel.kind.shape[0]
    basis = np.full(B, "gauss: the tiers agree within the data", dtype=object)
    dcost = {t: np.full(B, np.nan) for t in ("waveform", "piston")}
    kappa_alt = np.full(B, np.nan)
    for kind in ("point", "line"):
        idx = np.flatnonzero((sel.kind == kind) & (sel.tier == "gauss"))
        if idx.size == 0:
            continue
        base = sel.robust_cost[idx].copy()
        bars = {"waveform": base - WAVEFORM_THRESHOLD, "piston": base - threshold}
        best_cost = np.full(idx.size, np.inf)   # the best alternative past its bar
        best: list[tuple[str, BatchFit, NDArray[np.int64]]] = []
        choice = np.full(idx.size, -1)
        # one model pass at the Gaussian fits for the predictions of every tier and the
        # score and misfit tests
        pred, gm = _tier_model(batch, sel, idx, kind, ("gauss", "waveform", "piston"), cfg,
                               jacobian=True)
        assert gm is not None
        try_w = _tiers_differ(batch, sel, idx, kind, "gauss", "waveform", cfg, pred)
        differ_w = try_w.copy()
        if try_w.any():   # and the residuals lean towards it (score test)
            rw = np.flatnonzero(try_w)
            try_w[rw] = score_z(batch, sel, idx[rw], kind, "gauss", "waveform", cfg,
                                pred["waveform"][0][rw], gm.rows(rw)) > WAVEFORM_SCORE_Z
        try_p = _tiers_differ(batch, sel, idx, kind, "gauss", "piston", cfg, pred)
        if try_p.any():
            rp = np.flatnonzero(try_p)
            try_p[rp] = misfit(batch, sel, idx[rp], kind, cfg, model=(
                gm.log_p[rp], None if gm.zn is None else gm.zn[rp])) | (np.abs(score_z(
                    batch, sel, idx[rp], kind, "gauss", "piston", cfg, pred["piston"][0][rp],
                    gm.rows(rp))) > SCORE_Z)
        for tier, mask in (("waveform", try_w), ("piston", try_p)):
            rows = np.flatnonzero(mask)
            if rows.size == 0:
                continue
            alt = fit_batch(batch, kind, tier, cfg, start=sel.rows(idx[rows]), rows=idx[rows],
                            stop_above=bars[tier][rows] + HOPELESS_DCOST)
            alt = _rebracket(batch, idx[rows], alt, bars[tier][rows], cfg)
            dcost[tier][idx[rows]] = base[rows] - alt.robust_cost   # > 0: tier better
            wins = (alt.robust_cost < bars[tier][rows]) & (alt.robust_cost < best_cost[rows])
            best_cost[rows[wins]] = alt.robust_cost[wins]
            choice[rows[wins]] = len(best)
            best.append((tier, alt, rows))
        tried = try_w | try_p
        basis[idx[differ_w & ~tried]] = "gauss: residuals do not lean towards another tier"
        basis[idx[tried]] = "data cannot tell: gauss kept"
        for k, (tier, alt, rows) in enumerate(best):
            if tier == "waveform":
                # gauss kept while the module's own model nearly ties: kappa depends on
                # the model (the Gaussian one absorbs the waveform's extra delay), so its
                # SD covers the waveform fit's kappa
                near = np.flatnonzero((choice[rows] == -1)
                                      & (alt.robust_cost - base[rows] < TIER_TIE))
                for r in near.tolist():
                    b = int(idx[rows[r]])
                    dk = float(alt.local[r, 2] - sel.local[b, 2])
                    sel.cov[b, 2, 2] += dk * dk
                    kappa_alt[b] = float(alt.local[r, 2])
            pick = np.flatnonzero(choice[rows] == k)
            if pick.size:
                sel.put(idx[rows[pick]], alt.take(pick))
                basis[idx[rows[pick]]] = f"{tier} fits the data better"
        # piston chosen (side lobes seen): its weak side-lobe echoes may be late as the
        # module's waveform makes them; try waveform from the piston fit where it leans so
        pst = idx[(sel.tier[idx] == "piston") & ~try_w]
        if pst.size:
            lean = misfit(batch, sel, pst, kind, cfg) | (score_z(
                batch, sel, pst, kind, "piston", "waveform", cfg) > WAVEFORM_SCORE_Z)
            rows2 = pst[lean]
            if rows2.size:
                alt = fit_batch(batch, kind, "waveform", cfg, start=sel.rows(rows2),
                                rows=rows2, stop_above=sel.robust_cost[rows2]
                                - WAVEFORM_THRESHOLD + HOPELESS_DCOST)
                alt = _rebracket(batch, rows2, alt,
                                 sel.robust_cost[rows2] - WAVEFORM_THRESHOLD, cfg)
                d = sel.robust_cost[rows2] - alt.robust_cost
                dcost["waveform"][rows2] = d
                win = d > WAVEFORM_THRESHOLD
                if win.any():
                    sel.put(rows2[win], alt.take(np.flatnonzero(win)))
                    basis[rows2[win]] = "waveform fits the data better (after piston)"
    # (Python values; each segment's keys in this order)
    for ex, bs in zip(sel.extra, basis.tolist(), strict=True):
        ex["tier_basis"] = bs
    for t, d in dcost.items():
        key, dv = f"dcost_{t}", d.tolist()
        for b in np.flatnonzero(np.isfinite(d)).tolist():
            sel.extra[b][key] = dv[b]
    ka = np.where(sel.tier == "gauss", kappa_alt, np.nan)
    for b in np.flatnonzero(np.isfinite(ka)).tolist():
        sel.extra[b]["kappa_waveform_us"] = float(ka[b])


def runs_z(signs: NDArray[np.bool_], n: NDArray[np.int64]) -> Array:
    """Wald-Wolfowitz runs statistic per row of the first ``n`` signs (negative: fewer
    runs than chance, i.e. residuals in blocks); 0 where undefined."""
    B, N = signs.shape
    valid = np.arange(N)[None, :] < n[:, None]
    n1 = (signs & valid).sum(1).astype(float)
    n2 = n.astype(float) - n1
    change = (signs[:, 1:] != signs[:, :-1]) & valid[:, 1:]
    runs = 1.0 + change.sum(1)
    nf = n.astype(float)
    mu = 2.0 * n1 * n2 / np.maximum(nf, 1.0) + 1.0
    var = 2.0 * n1 * n2 * (2.0 * n1 * n2 - nf) / np.maximum(nf * nf * (nf - 1.0), 1.0)
    ok = (n1 > 0) & (n2 > 0) & (n >= 8) & (var > 0)
    return np.where(ok, (runs - mu) / np.sqrt(np.where(ok, var, 1.0)), 0.0)


RUNS_Z_MAX = -4.0
"""The overlap test's bound on the runs statistic: residuals in blocks (below this) with
a chi-square per degree of freedom above :data:`CHI2_RATIO_MIN` suggest a second
reflector."""

CHI2_RATIO_MIN = 2.0
"""The overlap test's bound on the chi-square per degree of freedom (:data:`RUNS_Z_MAX`)."""


def overlap_check(batch: SegmentBatch, sel: Selection, cfg: FitConfig,
                  runs_z_max: float = RUNS_Z_MAX, chi2_ratio_min: float = CHI2_RATIO_MIN
                  ) -> None:
    """Flag segments whose residuals show a second reflector (``extra['overlap']``)."""
    for kind in ("point", "line"):
        idx = np.flatnonzero(sel.kind == kind)
        if idx.size == 0:
            continue
        sub = _take(batch, idx)
        p = sel.local[idx]
        geo = M.geometry(kind, p[:, 0:1], p[:, 1:2], sub.px, sub.py, sub.yaw)
        used = sel.used[idx]
        order = np.argsort(np.where(used, geo.theta, np.inf), axis=1)
        signs = np.take_along_axis(sel.resid[idx] > 0, order, axis=1)
        n = used.sum(1)
        z = runs_z(signs, n)
        for b, zj, reason in zip(idx.tolist(), z.tolist(),
                                 overlap_reasons(z, sel.chi2[idx], n, runs_z_max,
                                                 chi2_ratio_min), strict=True):
            sel.extra[b]["runs_z"] = zj
            if reason:
                sel.extra[b]["overlap"] = reason


def overlap_reasons(z: Array, chi2: Array, n: NDArray[np.int64],
                    runs_z_max: float = RUNS_Z_MAX, chi2_ratio_min: float = CHI2_RATIO_MIN
                    ) -> list[str]:
    """The overlap test of :func:`overlap_check` from each segment's runs statistic
    ``z``, chi-square and number of used echoes ``n``: why a second reflector is
    suspected ('' where not)."""
    ratio = chi2 / np.maximum(n - 3, 1)
    flag = (z < runs_z_max) & (ratio > chi2_ratio_min)
    return [f"residuals run in blocks (runs z = {zj:.1f}, chi2/dof = {rj:.1f}): two "
            "reflectors merged?" if fj else ""
            for zj, rj, fj in zip(z.tolist(), ratio.tolist(), flag.tolist(), strict=True)]


def past_wall_ends(batch: SegmentBatch, sel: Selection, rows: NDArray[np.int64]
                   ) -> NDArray[np.bool_]:
    """No-echo readings (B, Nn) of segments ``rows`` that may lie past the ends of the
    wall they were fitted as (the others' none): the foot of their normal on the fitted
    line lies outside the span of the echoes' feet.

    A wall echoes from the foot of the normal only (specular), whatever the beam's
    direction; the echoes' feet show where the wall is, not where it ends. A no-echo
    reading whose foot lies beyond them says nothing about the beam and the wall's
    strength: the wall may just have ended there. Read as a beam too far off axis, a
    transducer that faced a wall squarely and stopped hearing it at its end (the
    off-axis angle unchanged, ~0 deg) makes the wall as weak as the detection limit
    allows (kappa 4-11 us against 0.15): on a moving ring's 300 s drive (the room,
    ``ring16``, odometry poses) 46 of the 62 walls ``UNRESOLVED`` as weak were single
    walls, most of them seen by one transducer whose last readings' feet lay past the
    wall's end (the simulator's truth); kappa's excess also biased their range by
    ~-1.6 mm (kappa 11 us: 1.9 mm)."""
    out = np.zeros(batch.ne_valid.shape, dtype=bool)
    idx = rows[sel.kind[rows] == "line"]
    if idx.size == 0 or batch.ne_valid.shape[1] == 0:
        return out
    phi = sel.local[idx, 1:2]
    c, s = np.cos(phi), np.sin(phi)
    foot = -batch.px[idx] * s + batch.py[idx] * c              # along the line, (b, Nd)
    valid = batch.valid[idx]
    lo = np.min(np.where(valid, foot, np.inf), axis=1, keepdims=True)
    hi = np.max(np.where(valid, foot, -np.inf), axis=1, keepdims=True)
    ne_foot = -batch.ne_px[idx] * s + batch.ne_py[idx] * c
    tol = _WALL_END_TOLERANCE_M
    out[idx] = batch.ne_valid[idx] & ((ne_foot < lo - tol) | (ne_foot > hi + tol))
    return out


_WALL_END_TOLERANCE_M = 1e-3
"""How far past the echoes' feet a no-echo reading's foot must lie for
:func:`past_wall_ends` (rounding of the positions, not a physical length)."""


def _drop_past_wall_ends(batch: SegmentBatch, sel: Selection, moving: NDArray[np.int64],
                         cfg: FitConfig) -> SegmentBatch:
    """``batch`` without the no-echo readings :func:`past_wall_ends` finds among the
    line fits of segments ``moving``; the walls that had any refitted from their fits
    (once: the feet move little with the fit)."""
    past = past_wall_ends(batch, sel, moving)
    rows = np.flatnonzero(past.any(axis=1))
    if rows.size == 0:
        return batch
    # the readings kept moved to the front of their rows, in order: a batch's valid
    # columns are a prefix (fit_batch cuts its chunks to their counts: holes left here
    # would cut off valid no-echo readings, 458 of 127 walls on a moving ring's 300 s
    # drive, benchmarks/bench_fit.py section 4)
    keep = batch.ne_valid & ~past
    order = np.argsort(~keep, axis=1, kind="stable")
    ne_px, ne_py, ne_yaw = (np.take_along_axis(a, order, axis=1)
                            for a in (batch.ne_px, batch.ne_py, batch.ne_yaw))
    batch = replace(batch, ne_px=ne_px, ne_py=ne_py, ne_yaw=ne_yaw,
                    ne_valid=np.take_along_axis(keep, order, axis=1))
    sel.put(rows, fit_batch(batch, "line", "gauss", cfg, start=sel.rows(rows), rows=rows))
    for b in rows.tolist():
        sel.extra[b]["n_past_wall_end"] = int(past[b].sum())
    return batch


def select_models(batch: SegmentBatch, cfg: FitConfig) -> tuple[Selection, SegmentBatch]:
    """Fit every segment and choose its model: kind, then tier, then the overlap check.

    Returns the selection and the batch its models were fitted on: ``batch`` less the
    no-echo readings of walls that may lie past the wall's ends
    (:func:`past_wall_ends`; the kind is chosen with them)."""
    point = fit_batch(batch, "point", "gauss", cfg)
    sel = Selection.from_fit(point)
    moving = np.flatnonzero(motion_baseline_m(batch) > MOTION_BASELINE_M)
    line = fit_batch(batch, "line", "gauss", cfg, rows=moving) if moving.size else None
    choose_kind(sel, line, moving)
    batch = _drop_past_wall_ends(batch, sel, moving, cfg)
    choose_tier(batch, sel, cfg)
    # one viewpoint: point and line are the same fit; the final kappa decides
    still = np.array([ex["kind_basis"] == "strength" and "kind_dcost" not in ex
                      for ex in sel.extra], dtype=bool)
    sel.kind[still] = np.where(sel.local[still, 2] < KAPPA_WALL_US, "line", "point")
    overlap_check(batch, sel, cfg)
    return sel, batch

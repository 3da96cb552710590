"""Separable least squares (variable projection) for many segments at once.

For a fixed bearing ``phi`` the TOF model ``Tm_i = To + 2 (R_i - r)/c + kappa g_i`` is
linear in ``(To, kappa)``: the fit profiles out that pair with a 2x2 weighted solve on
a global grid of bearings spanning the segment's arc (plus a margin for partial U's),
adds the detection likelihood of the no-echo readings, takes the best node, and then
polishes all three parameters by Fisher scoring with Levenberg-Marquardt damping and
step acceptance only on decrease. The objective can only go down from the grid's
best node, so a fit cannot diverge; every array op runs over the whole batch.

The objective (half of it is minimised) is the negative log-likelihood

    sum_echo ((y_i - mean_i) / s_i)^2 - 2 log P(echo_i) - 2 sum_no-echo log P(no echo_j)

with ``y`` the readings less the counting bias (half a count), ``mean_i`` the mean TOF
of a detected echo (geometry + truncated log-normal delay), ``s_i`` the jitter model
(:func:`sonarloc.physics.jitter_sd_us`) plus counting variance, held fixed within a
reweighting round, and the detection probabilities of :mod:`sonarloc.fit.model`.
"""

from __future__ import annotations

import functools
import importlib
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from sonarloc.fit import model as M
from sonarloc.physics.tof import ModuleParams

Array = NDArray[np.float64]
FloatArray = NDArray[np.floating[Any]]
"""float64 or float32 (the float32 passes of ``FitConfig.float32``)."""

METHODS = ("full", "profile")
"""Refinement methods of :class:`FitConfig` (``method``)."""

STARTS = ("grid", "arc")
"""Starts of :class:`FitConfig` (``start``)."""


@dataclass(frozen=True)
class FitConfig:
    """Settings of the fitter.

    Attributes
    ----------
    module : the ranging module (speed of sound ``c_mps``, beam, detection limit,
        jitter, counting period). Change ``c_mps`` for another air temperature.
    detection : use the detection model (no-echo readings bound the arc; detected
        echoes' delays are truncated at the detection limit).
    grid_step_deg : largest spacing of the global bearing grid.
    margin_deg : how far beyond the arc covered by echoes a minimum may lie.
    rounds, iterations : reweighting rounds and (at most) damped Fisher-scoring steps
        per round. When the last round's steps run out, the covariance is that of the
        Fisher matrix at the last step's start (the objective is evaluated at its end,
        the derivatives are not).
    follow_variances : the TOF variances follow every accepted step (iteratively
        reweighted: a step is judged with the variances at its start, the next one
        taken with those at its end); otherwise they are held fixed within a round.
    tolerance : a fit has converged when the expected decrease of the objective
        (-log-likelihood; the Newton decrement) is below this.
    outlier_sigma : standardised residual beyond which an echo is dropped as a spike
        (at most ``max_outlier_fraction`` of a segment's echoes).
    flat_bearing_sd_deg : a fit whose bearing SD exceeds this is ``FLAT``.
    min_echoes : fewer echoes (after spikes) make a result ``TOO_FEW_POINTS``: three
        determine the three parameters exactly, leaving nothing to check the fit.
    min_fit_p : a fit whose TOF chi-square has a p-value below this is ``UNRESOLVED``
        (no single landmark explains the readings: merged reflectors, wall + corner).
    kappa_min_us : lower bound of kappa.
    kappa_lo_us, kappa_hi_us, kappa_soft_log_sd : a soft box prior on kappa: flat over
        [lo, hi], rising like a Gaussian in ln kappa (SD ``kappa_soft_log_sd``) outside;
        ``inf`` switches it off. Real reflectors lie between 0.15 us (plane) and the
        detection limit (12 us: weaker ones are never detected), so the box costs no
        fit anything, but keeps a partial arc from the degenerate "wall far off-axis"
        reading (kappa -> 0).
    kappa_guess_us : kappa of the conventional fallback result.
    second_start_dcost : a second local minimum of the grid profile within this much
        (-2 log-likelihood) of the best is refined too, and the better result kept.
    chunk_readings : segments are fitted in chunks of about this many padded readings
        (keeps the arrays in cache).
    grid_max_echoes : the grid bracket of a segment with more echoes than this uses
        this many, evenly spread from its first to its last echo and weighted up to the
        whole count; ``None``: all. The bracket needs the curve's shape, not every
        reading; the refinement always uses all.
    method : ``"full"``: refine all three parameters by damped Fisher scoring on the
        whole likelihood (TOF terms, detection terms of echoes and no-echo readings).
        ``"profile"``: refine the bearing on the profile of the echoes' weighted LS cost
        (for a fixed bearing the Gaussian/piston model is linear in (To, kappa)):
        ``profile_evals`` parabolas through a narrowing 3-point stencil, then (To,
        kappa) solved at the result; the covariance is that of the weighted Gauss-Newton
        matrix of the three parameters there. Echoes only (like a ``curve_fit``): no
        detection terms, untruncated mean delays; the grid bracket still uses the
        no-echo readings. Waveform-tier fits fall back to ``"full"`` without detection
        terms (so that costs of tiers fitted with one config compare).
    profile_evals : stencil evaluations of the ``"profile"`` method.
    profile_step_deg : half-width of the first stencil [deg]; each next one is a
        quarter of it, or the same where the minimum lay at the stencil's edge.
    final_derivatives : the last step's model pass computes derivatives too (the
        gradient and Fisher matrix at the result, not at the last step's start), and
        where the steps ran out before convergence the covariance adds the outer
        product of the Newton step still pending there: the mean squared error of an
        unconverged fit (its variance plus its expected distance to the converged one)
        rather than the variance of a converged one. A result whose pending step's
        expected decrease is below ``tolerance`` counts as converged.
    float32 : the model passes of the refinement in single precision, with the
        detection model (without: float64): readings relative to the model range (a
        moving batch's ranges formed in float64), branch-free normal tail probabilities
        (:func:`sonarloc.fit.model.log_sf32`), the objective summed in float64. Passes
        of pans about 3x cheaper, of moving batches (~10 segments a pass) ~1.2-1.3x;
        results within a few thousandths of an SD of the float64 ones (tests). On by
        default; ``float32=False`` for the float64 passes.
    start : where the refinement starts. ``"grid"``: the global bearing grid bracket.
        ``"arc"``: for stationary point segments (pans) whose echo arc is whole (a
        no-echo reading within 5 deg beyond each end, at most half as many no-echo
        readings among the echoes as echoes), a closed form from the arc's edges (each
        halfway between the outermost echo and the next no-echo reading): the bearing
        their midpoint (the detection limit cuts the arc at the same off-axis angle on
        both sides), kappa the detection limit over the beam factor at the half-width,
        To the readings' mean less the model's delays; one pass over the readings
        instead of the grid's nodes, and about 3x closer in bearing (0.4 deg RMS against
        1.2-1.4 on 0.3-1 deg pans). The other segments (moving, partial arcs at a scan's
        edge, occluded ends, coarse pans, echoes scattered off the arc) get the grid.
        The default: with the default's steps it reaches the grid-started fit's
        answers (benchmarks/results/fit.md) at about two thirds of its cost.
    arc_iterations : steps of the segments started from the arc (``None``:
        ``iterations``; those from the grid always take ``iterations``).
    """

    module: ModuleParams = field(default_factory=ModuleParams)
    detection: bool = True
    grid_step_deg: float = 3.0
    margin_deg: float = 12.0
    rounds: int = 2
    iterations: int = 12
    tolerance: float = 1e-3
    outlier_sigma: float = 4.5
    max_outlier_fraction: float = 0.2
    flat_bearing_sd_deg: float = 3.0
    min_echoes: int = 5
    min_fit_p: float = 1e-4
    kappa_min_us: float = 1e-3
    kappa_lo_us: float = 0.05
    kappa_hi_us: float = 20.0
    kappa_soft_log_sd: float = 0.5
    kappa_guess_us: float = 1.0
    second_start_dcost: float = 6.0
    chunk_readings: int = 65536
    follow_variances: bool = False
    grid_max_echoes: int | None = 32
    method: str = "full"
    profile_evals: int = 3
    profile_step_deg: float = 3.0
    final_derivatives: bool = False
    float32: bool = True
    start: str = "arc"
    arc_iterations: int | None = None

    def __post_init__(self) -> None:
        for name in ("grid_step_deg", "margin_deg", "outlier_sigma", "flat_bearing_sd_deg",
                     "kappa_min_us", "kappa_guess_us", "tolerance", "kappa_lo_us",
                     "kappa_hi_us", "kappa_soft_log_sd", "profile_step_deg"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        if self.arc_iterations is not None and not (
                isinstance(self.arc_iterations, int) and self.arc_iterations >= 1):
            raise ValueError("`arc_iterations` must be None or a positive integer, got "
                             f"{self.arc_iterations!r}")
        if self.start not in STARTS:
            raise ValueError(f"`start` must be one of {', '.join(STARTS)}; got {self.start!r}")
        if self.method not in METHODS:
            raise ValueError(f"`method` must be one of {', '.join(METHODS)}; got "
                             f"{self.method!r}")
        for name in ("rounds", "iterations", "chunk_readings", "min_echoes",
                     "profile_evals"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"`{name}` must be a positive integer, got {v!r}")
        if self.grid_max_echoes is not None and not (
                isinstance(self.grid_max_echoes, int) and self.grid_max_echoes >= 3):
            raise ValueError("`grid_max_echoes` must be None or an integer >= 3, got "
                             f"{self.grid_max_echoes!r}")
        if not (0.0 <= self.max_outlier_fraction < 1.0):
            raise ValueError(
                f"`max_outlier_fraction` must be in [0, 1), got {self.max_outlier_fraction!r}")

    @classmethod
    def batch(cls, **changes: Any) -> FitConfig:
        """Settings for bulk fitting of clean segments: a 6 deg grid bracket for every
        segment and one round whose variances follow every step (``follow_variances``).
        Same accuracy as the default on single-reflector segments
        (benchmarks/results/fit.md), about 1.5-2x faster than the grid-started fit
        (the model passes in float32: ``float32``, within a few thousandths of an SD of
        float64); the default's arc start (``start="arc"``) is
        faster still on pans whose arc is whole. On ill-posed segments (corners, merged
        wall and corner) it may settle elsewhere than the default, so the online
        pipeline keeps the default."""
        return replace(cls(grid_step_deg=6.0, rounds=1, follow_variances=True, float32=True,
                           chunk_readings=131072, start="grid"), **changes)

    @classmethod
    def fast(cls, **changes: Any) -> FitConfig:
        """The quickest sound settings: pans with a whole echo arc start from the arc's
        edges (``start="arc"``) and take one damped Gauss-Newton step; the rest
        (partial arcs, moving sensors, coarse pans) start from a 12 deg grid bracket (on
        at most 16 echoes of a segment) with (To, kappa) profiled again at its bearing
        and take two. Each step is kept only if it lowers the objective (so the fit
        cannot diverge). On the benchmark's pans the errors are the converged fit's (to
        about 0.15 SD), far below a per-segment ``curve_fit``'s
        (benchmarks/results/fit.md). The covariance is that of the Fisher matrix at the
        result plus the pending Newton step's outer product (``final_derivatives``): it
        covers the distance to the converged fit, so the reported SDs match the errors
        as the converged fit's do. The model passes run in float32 (``float32``; within
        a few hundredths of an SD of float64), in chunks of twice the default size (the
        arrays are half as large)."""
        return replace(cls(grid_step_deg=12.0, rounds=1, iterations=2, follow_variances=True,
                           grid_max_echoes=16, final_derivatives=True, float32=True,
                           chunk_readings=131072, start="arc", arc_iterations=1), **changes)

    @classmethod
    def profile(cls, **changes: Any) -> FitConfig:
        """The quickest settings: ``fast()``'s grid bracket, then the bearing refined on
        the profiled weighted-LS cost of all echoes (three narrowing 3-point stencils,
        each only exponentials and weighted sums), (To, kappa) solved there and the
        covariance of the Gauss-Newton matrix of the three parameters (calibrated for
        what this method uses). Echoes only: the no-echo readings' detection terms
        (which the default uses to bound the arc) are left out, so the bearing is that
        of the TOF curve alone: about a per-segment ``curve_fit``'s error, 4-5x the
        default's, more segments ``FLAT``, and no faster than ``fast()``
        (benchmarks/results/fit.md). For data whose no-echo readings cannot be trusted."""
        return replace(cls(grid_step_deg=12.0, rounds=1, iterations=1, follow_variances=True,
                           grid_max_echoes=16, method="profile", start="grid"), **changes)

    def with_speed_of_sound(self, c_mps: float) -> FitConfig:
        """The same settings with another speed of sound [m/s]."""
        return replace(self, module=replace(self.module, c_mps=float(c_mps)))


@dataclass(frozen=True)
class SegmentBatch:
    """Readings of ``B`` segments, padded, relative to each segment's reference pose.

    Echo arrays have shape (B, Nd), no-echo arrays (B, Nn); ``*_valid`` marks real
    entries. Positions are metres relative to ``ref_xy`` (B, 2) (the transducer
    position of each segment's last echo), angles are frame radians, ``tof_us`` is the
    raw reading in microseconds.
    """

    px: Array
    py: Array
    yaw: Array
    tof_us: Array
    valid: NDArray[np.bool_]
    ne_px: Array
    ne_py: Array
    ne_yaw: Array
    ne_valid: NDArray[np.bool_]
    ref_xy: Array
    ref_yaw: Array
    ref_t_s: Array

    @property
    def size(self) -> int:
        return int(self.px.shape[0])

    @property
    def n_echo(self) -> NDArray[np.int64]:
        return self.valid.sum(axis=1)

    @property
    def n_noecho(self) -> NDArray[np.int64]:
        return self.ne_valid.sum(axis=1)

    @functools.cached_property
    def moving(self) -> bool:
        """Whether any reading was taken away from its segment's reference position."""
        return bool(self.px.any() or self.py.any() or self.ne_px.any() or self.ne_py.any())

    @functools.cached_property
    def yaw32(self) -> NDArray[np.float32]:
        """``yaw`` in float32 (the float32 model passes)."""
        return self.yaw.astype(np.float32)

    @functools.cached_property
    def ne_yaw32(self) -> NDArray[np.float32]:
        """``ne_yaw`` in float32 (the float32 model passes)."""
        return self.ne_yaw.astype(np.float32)

    @functools.cached_property
    def yaw_bounds(self) -> tuple[float, float, float, float]:
        """Smallest and largest entries of ``yaw`` and of ``ne_yaw`` (padding included;
        +-inf where empty): tell :func:`_angle_diff` when no wrapping is needed."""
        def lo_hi(a: Array) -> tuple[float, float]:
            return (float(a.min()), float(a.max())) if a.size else (np.inf, -np.inf)
        return (*lo_hi(self.yaw), *lo_hi(self.ne_yaw))


def pack_segments(
    segments: Sequence[tuple[Array, Array, Array, Array, Array]],
) -> SegmentBatch:
    """Pad segments given as ``(t_s, x_m, y_m, yaw_rad, tof_us)`` arrays into a batch.

    The reference of each segment is its last reading with a finite echo (its last
    reading if it has none). Non-finite TOFs (NaN, inf) are no-echo readings.
    """
    n = len(segments)
    if n == 0:
        return pack_flat(np.zeros(0, dtype=np.int64), *(np.zeros(0),) * 5, n_segments=0)
    if any(len(seg) != 5 for seg in segments):
        b = next(b for b, seg in enumerate(segments) if len(seg) != 5)
        raise ValueError(f"segment {b}: expected 5 arrays of equal length")
    cols = list(zip(*segments, strict=True))                    # 5 tuples of n arrays
    try:        # fast path: sized arrays (no per-array Python work beyond len)
        sizes = np.array([np.fromiter(map(len, c), np.int64, n) for c in cols])
    except TypeError:   # scalars (0-d) among the arrays
        sizes = np.array([[np.size(a) for a in c] for c in cols], dtype=np.int64)
    lengths = sizes[0]
    if np.any(sizes != lengths):
        b = int(np.flatnonzero((sizes != lengths).any(0))[0])
        raise ValueError(f"segment {b}: expected 5 arrays of equal length")
    total = int(lengths.sum())
    flat = np.empty((5, total))
    for k in range(5):
        if total:
            np.concatenate(cols[k], axis=None, out=flat[k])
    return _pack_sorted(np.repeat(np.arange(n), lengths), lengths, flat[0], flat[1], flat[2],
                        flat[3], flat[4])


def pack_flat(seg: NDArray[np.int64], t_s: Array, x_m: Array, y_m: Array, yaw_rad: Array,
              tof_us: Array, n_segments: int | None = None) -> SegmentBatch:
    """Pad readings given as flat arrays with a segment index (non-decreasing) into a batch.

    Vectorised form of :func:`pack_segments`: ``seg`` (n,) the segment of each reading,
    sorted; the other arrays (n,) as there.
    """
    seg = np.asarray(seg, dtype=np.int64)
    B = int(n_segments if n_segments is not None else (seg.max() + 1 if seg.size else 0))
    t_s, x_m, y_m, yaw_rad, tof_us = (np.asarray(a, dtype=float)
                                      for a in (t_s, x_m, y_m, yaw_rad, tof_us))
    return _pack_sorted(seg, np.bincount(seg, minlength=B), t_s, x_m, y_m, yaw_rad, tof_us)


def _pack_sorted(seg: NDArray[np.int64], n_seg: NDArray[np.int64], t_s: Array, x_m: Array,
                 y_m: Array, yaw_rad: Array, tof_us: Array) -> SegmentBatch:
    """:func:`pack_flat` given the readings of each segment ``n_seg`` (B,) (float64
    arrays)."""
    B = n_seg.size
    det = np.isfinite(tof_us)
    i_e = np.flatnonzero(det)                     # echoes, in order
    c_e = np.bincount(seg[det], minlength=B)      # echoes of each segment
    c_n = n_seg - c_e
    end_e = np.cumsum(c_e)
    # reference: the last echo of each segment (its last reading if it has none)
    ref = np.zeros(B, dtype=np.int64)
    has_e = c_e > 0
    if i_e.size:
        ref[has_e] = i_e[end_e[has_e] - 1]
    if seg.size:
        no_e = np.flatnonzero(~has_e & (c_n > 0))
        if no_e.size:
            ref[no_e] = np.cumsum(n_seg)[no_e] - 1          # its last reading
    has = has_e | (c_n > 0)
    ref_xy = np.zeros((B, 2))
    ref_yaw = np.zeros(B)
    ref_t = np.zeros(B)
    if seg.size:
        ref_xy[has, 0], ref_xy[has, 1] = x_m[ref[has]], y_m[ref[has]]
        ref_yaw[has], ref_t[has] = yaw_rad[ref[has]], t_s[ref[has]]

    # positions relative to the reference (each segment's readings are one run of the
    # sorted order: a repeat, cheaper than a gather)
    rel: list[Array | None] = [x_m, y_m, yaw_rad, tof_us]
    if seg.size:
        for j in (0, 1):
            col = rel[j]
            assert col is not None
            if col.min() == col.max():      # all at one position (pans): zeros
                rel[j] = None
                continue
            d = col - np.repeat(ref_xy[:, j], n_seg)
            rel[j] = d if d.any() else None      # all at the reference (a pan): zeros

    def pad(sel: NDArray[np.bool_], count: NDArray[np.int64], k: int
            ) -> tuple[list[Array], NDArray[np.bool_]]:
        """The first ``k`` of (x, y, yaw, tof) of readings ``sel``, padded (tof with NaN,
        the rest with 0), and validity. The readings are sorted by segment, so a boolean
        compress and a boolean scatter into the row-major mask of the first ``count``
        columns of each row put them in place (no index arithmetic)."""
        width = max(int(count.max(initial=0)), 1)
        ok = np.arange(width)[None, :] < count[:, None]                     # (B, width)
        # one block for all columns (a large one gets huge pages: fewer page faults)
        block = np.zeros((k, B, width))
        if k > 3:
            block[3] = np.nan
        for j in range(k):
            col = rel[j]
            if col is not None:
                block[j][ok] = col[sel]
        return list(block), ok

    (px, py, yw, tof), valid = pad(det, c_e, 4)
    (npx, npy, nyw), nvalid = pad(~det, c_n, 3)
    return SegmentBatch(px, py, yw, tof, valid, npx, npy, nyw, nvalid, ref_xy, ref_yaw, ref_t)


@dataclass(frozen=True)
class BatchFit:
    """Result of :func:`fit_batch` for ``B`` segments (local parameters).

    ``local``: (B, 3) ``(r [m], phi [rad], kappa [us])`` seen from each reference pose;
    ``cov``: (B, 3, 3); ``cost``: (B,) -2 log-likelihood at the fit (TOF Gaussian
    terms with their variances' log-determinant, plus detection terms); ``chi2``: (B,)
    sum of squared standardised TOF residuals;
    ``n_used``: (B,) echoes used; ``used``: (B, Nd) echoes kept (not spikes);
    ``resid``: (B, Nd) standardised TOF residuals (0 where unused);
    ``arc``: (B, 2) bearing interval (lo, hi) [rad] covered by the echoes' beam axes,
    as seen from the reference (``hi - lo`` may exceed pi only for a full turn);
    ``converged``: (B,) last step below tolerance; ``robust_cost``: (B,) ``cost`` plus
    ``outlier_sigma^2`` per dropped echo (comparable between models fitted to the same
    readings).
    """

    kind: str
    tier: str
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

    def take(self, idx: NDArray[np.int64]) -> BatchFit:
        """The results of segments ``idx``."""
        return BatchFit(self.kind, self.tier, *(getattr(self, f)[idx] for f in (
            "local", "cov", "cost", "chi2", "n_used", "used", "resid", "arc", "converged",
            "robust_cost")))


def _profile_2x2(S0: Array, S1: Array, S2: Array, Sy: Array, Sgy: Array, Syy: Array,
                 kmin: float | Array, kmax: float | Array = np.inf
                 ) -> tuple[Array, Array, Array]:
    """LS of y = T + K g from its sums (S0 = sum w, S1 = sum w g, ...), kmin <= K <= kmax.

    Returns T, K and the weighted sum of squared residuals.
    """
    det = S0 * S2 - S1 * S1
    good = det > 1e-12 * np.maximum(S0 * S2, 1e-300)
    K = np.where(good, (S0 * Sgy - S1 * Sy) / np.where(good, det, 1.0), kmin)
    K = np.clip(K, kmin, np.maximum(kmax, kmin))
    T = (Sy - K * S1) / np.maximum(S0, 1e-300)
    sse = Syy - 2 * T * Sy - 2 * K * Sgy + T * T * S0 + 2 * T * K * S1 + K * K * S2
    return T, K, np.maximum(sse, 0.0)


def _axis_bearings(kind: str, batch: SegmentBatch, y: Array, tau: float
                   ) -> tuple[Array, Array]:
    """Where the landmark's ``phi`` is expected, per echo, and a wrap centre.

    Point: the bearing from the reference of each echo's beam-axis point; line: each
    echo's axis direction (the wall normal lies within the beam of every echo).
    The centre is that of the earliest minimum-TOF echo.
    """
    if kind == "line":
        bear = batch.yaw
    elif not _is_moving(batch):       # seen from the reference: the beam axis itself
        bear = np.where(batch.valid, M._wrap_fast(batch.yaw), 0.0)
    else:
        R = np.where(batch.valid, y / tau, 0.0)
        bear = np.arctan2(batch.py + R * np.sin(batch.yaw), batch.px + R * np.cos(batch.yaw))
    ymin_idx = np.argmin(np.where(batch.valid, y, np.inf), axis=1)
    centre = np.take_along_axis(bear, ymin_idx[:, None], axis=1)[:, 0]
    return bear, centre


def _evaluate(kind: str, tier: str, p: Array, batch: SegmentBatch, y: Array, use: NDArray,
              s2: Array, cfg: FitConfig, want_derivs: bool = True
              ) -> tuple[Array, Array, Array, Array]:
    """Objective F (B,), gradient of F/2 (B,3), Fisher matrix (B,3,3), resid (B,Nd).

    ``s2`` (B, Nd): fixed TOF variances; ``use`` (B, Nd) echoes taken into account.
    """
    F, grad, H, e, _ = _evaluate_s2(kind, tier, p, batch, y, use, s2, cfg, want_derivs)
    return F, grad, H, e


def _evaluate_s2(kind: str, tier: str, p: Array, batch: SegmentBatch, y: Array, use: NDArray,
                 s2: Array | None, cfg: FitConfig, want_derivs: bool = True
                 ) -> tuple[Array, Array, Array, Array, Array]:
    """:func:`_evaluate`, also returning the variances (B, Nd) it used; ``s2=None``: the
    variances at ``p`` itself (what :func:`_variances` gives, without evaluating the
    model twice)."""
    return _evaluate_core(kind, tier, p, batch, y, use, s2, cfg, want_derivs)[1:]


def _evaluate_core(kind: str, tier: str, p: Array, batch: SegmentBatch, y: Array,
                   use: NDArray, s2: Array | None, cfg: FitConfig, want_derivs: bool = True,
                   s2_other: Array | None = None
                   ) -> tuple[Array, Array, Array, Array, Array, Array]:
    """:func:`_evaluate_s2` preceded by the objective with the variances ``s2_other``
    instead (the same as the objective without them), from the same model pass."""
    if _use_float32(kind, tier, batch, cfg):
        return _evaluate32(kind, p, batch, y, use, s2, cfg, want_derivs, s2_other, tier)
    mod = cfg.module
    tau = M.us_per_m(mod)
    r, phi, K = p[:, 0:1], p[:, 1:2], p[:, 2:3]
    moving = _is_moving(batch)
    if moving:
        geo = M.geometry(kind, r, phi, batch.px, batch.py, batch.yaw, moving=True)
        theta, R = geo.theta, geo.R
    else:                      # stationary: R = r, theta = phi - yaw
        theta, R = _angle_diff(phi, batch.yaw, batch.yaw_bounds[:2]), r
    g, dlng, lng = M.beam_log_factor(theta, tier, mod, derivative=want_derivs)
    det = cfg.detection
    z = M.detection_z(K, lng, mod) if det else None
    et = M.echo_terms(K, g, z, mod, want_info=False, tier=tier)
    if s2 is None:
        s2 = M.tof_variance_us2(et.delay, mod, et.delay_var if tier == "waveform" else None)
    usef = use if use.dtype == np.float64 else use.astype(float)     # 1/0 (no mixed ops)
    w = usef / np.sqrt(s2)                                   # 1/s, 0 where unused
    res = y - tau * R - et.delay
    e = res * w
    F = np.einsum("bn,bn->b", e, e)
    F_other = F
    if s2_other is not None:
        F_other = np.einsum("bn,bn->b", res * res, usef / s2_other)
    if det:
        dF = 2.0 * np.einsum("bn,bn->b", et.log_p, usef)
        F -= dF
        F_other = F_other - dF if s2_other is not None else F
    B = p.shape[0]
    grad = np.zeros((B, 3))
    H = np.zeros((B, 3, 3))
    sa = M.sigma_a(mod)
    inv_ksa = 1.0 / (K * sa)                                 # d z / d kappa, (B, 1)
    if want_derivs:
        jk = et.ddelay_du * g                                # d mean / d kappa
        a = jk * K * dlng                                    # d mean / d theta
        cols: list[Array | None]
        if moving:
            cols = [tau * geo.dR_dr + a * geo.dtheta_dr, tau * geo.dR_dphi + a * geo.dtheta_dphi,
                    jk]
        else:
            cols = [np.full((B, 1), tau), a, jk]
        _gram(H, grad, cols, w * w, w * e)
        if det:
            dz = dlng / sa                                   # d z / d theta
            zc: list[Array | None] = ([dz * geo.dtheta_dr, dz * geo.dtheta_dphi, inv_ksa]
                                      if moving else [None, dz, inv_ksa])
            _gram(H, grad, zc, et.curv * usef, et.dlogp_dz * usef)
    prior = _kappa_prior(K[:, 0], grad, H, cfg, want_derivs)
    F = F + prior
    F_other = F_other + prior if s2_other is not None else F
    if not det:
        return F_other, F, grad, H, e, s2
    nv = batch.ne_valid
    if nv.shape[1] and nv.any():
        if moving:
            ng = M.geometry(kind, r, phi, batch.ne_px, batch.ne_py, batch.ne_yaw, moving=True)
            thn = ng.theta
        else:
            thn = _angle_diff(phi, batch.ne_yaw, batch.yaw_bounds[2:])
        _, dlgn, lgn = M.beam_log_factor(thn, tier, mod, derivative=want_derivs, want_g=False)
        zn = M.detection_z(K, lgn, mod)
        lpn, dlpn, _, curvn = M.noecho_terms(zn, want_info=False)
        nvf = nv.astype(float)
        dFn = 2.0 * np.einsum("bn,bn->b", lpn, nvf)
        F = F - dFn
        F_other = F_other - dFn if s2_other is not None else F
        if want_derivs:
            dzn = dlgn / sa
            zcn: list[Array | None] = ([dzn * ng.dtheta_dr, dzn * ng.dtheta_dphi, inv_ksa]
                                       if moving else [None, dzn, inv_ksa])
            _gram(H, grad, zcn, curvn * nvf, dlpn * nvf)
    return F_other, F, grad, H, e, s2


def _c_einsum() -> Any:
    """``np.einsum`` without its Python wrapper: numpy's C function, which ``np.einsum``
    calls as it is when ``optimize`` is off (the same sums, ~1 us less per call; a
    float32 model pass makes 20)."""
    for name in ("numpy._core.multiarray", "numpy.core.multiarray"):
        try:
            return importlib.import_module(name).c_einsum
        except (ImportError, AttributeError):
            continue
    return np.einsum      # pragma: no cover


_einsum = _c_einsum()


def _dot_rows(u: FloatArray, v: FloatArray) -> Array:
    """Row-wise dot products (B,) of (B, N) arrays, in their precision, as float64; ``u``
    may be a stack (K, B, N) of such arrays: (K, B), each row's as on its own."""
    return _einsum("...n,...n->...", u, v).astype(float)


def _dot64(u: FloatArray, v: FloatArray) -> Array:
    """Row-wise dot products (B,) of (B, N) float32 arrays summed in float64: the values
    cast first, then einsum's float64 kernel (the same products and sums as
    ``einsum(..., dtype=np.float64)``, tested; without its buffered casting, which
    copies row by row: 40 % less time on a pass's ~700 x 19 arrays)."""
    u64 = u.astype(np.float64)
    return _einsum("bn,bn->b", u64, u64 if v is u else v.astype(np.float64))


def _sum_rows(u: FloatArray) -> Array:
    """Row sums (B,) of a (B, N) array, in its precision, as float64; of a stack
    (K, B, N): (K, B), each row's as on its own."""
    return _einsum("...n->...", u).astype(float)


def _truncation_ratio32(h: FloatArray, m: FloatArray, dm: FloatArray, s: float
                        ) -> FloatArray:
    """Phi(-z-s) / Phi(-z) from the Mills ratio ``m = phi(z) / Phi(-z)``, its excess
    ``h = m - z`` and derivative ``dm = m h``: exp of the 4th-order Taylor series in ``s`` of
    log Phi(-z-s) - log Phi(-z), whose derivatives by z are minus m and its
    derivatives (m2 = dm (m - z) + m (dm - 1), m3 = m2 (m - z) + 2 dm (dm - 1) + m m2:
    polynomials in m and z). For ``s = 0.25`` (the amplitude SD) its log is within
    2.1e-6 of the exact one for every z (float32 rounding: 1e-7); it saves a second
    tail probability per echo."""
    mz = h                           # (Python float constants: float32 ops, NEP 50)
    m2 = dm * mz
    m2 += m * (dm - 1.0)
    m3 = m2 * mz
    m3 += 2.0 * dm * (dm - 1.0)
    m3 += m * m2
    acc = m3 * (s ** 3 / 24.0)
    acc += m2 * (s * s / 6.0)
    acc += dm * (s / 2.0)
    acc += m
    acc *= -s
    return np.exp(acc)


def _truncated_slope_far32(jk: NDArray[np.float32], z: NDArray[np.float32],
                           h: NDArray[np.float32], ratio: NDArray[np.float32],
                           g: NDArray[np.float32], scale: float, s: float) -> None:
    """Put into ``jk`` (the truncated mean delay's derivative by kappa, ``scale g (ratio
    + (ratio m - m1) / s)`` with m1 = phi(z+s) / Phi(-z)) the form that holds far beyond
    the detection limit, z >= :data:`sonarloc.fit.model.Z_CF`: there 1 + (ratio m - m1)
    / (s ratio) = 1 + (m(z) - m(z+s)) / s = (h(z) - h(z+s)) / s ~ 1/z^2 (h = m - z) is a
    small difference of numbers ~1 (and of the ratio's series error, 2e-6, times z / s),
    which float32 loses; the excess h from its continued fraction
    (:func:`sonarloc.fit.model.mills_excess_cf32`) keeps it (within 3e-4)."""
    far = np.flatnonzero(z >= np.float32(M.Z_CF))
    if far.size:
        zf = np.take(z, far)
        slope = np.take(h, far) - M.mills_excess_cf32(zf + np.float32(s))
        slope *= np.take(ratio, far)
        slope *= np.take(g, far)
        slope *= np.float32(scale / s)
        np.put(jk, far, slope)


def _use_float32(kind: str, tier: str, batch: SegmentBatch, cfg: FitConfig) -> bool:
    """Whether :func:`_evaluate32` does the model passes (``cfg.float32`` and the
    detection model; every tier, pans and moving batches alike)."""
    return cfg.float32 and cfg.detection


def _off_axis32(tier: str, mod: ModuleParams, phi: Array, yaw32: NDArray[np.float32],
                yaw: Array, bounds: tuple[float, float], derivative: bool,
                ddiv: float = 1.0, phi_bounds: tuple[float, float] | None = None
                ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """ln g (B, N) and d ln g / d theta / ``ddiv`` (None without ``derivative``) in
    float32 of readings whose off-axis angle is theta = phi - yaw (a stationary batch's,
    a wall's): :func:`_log_beam32` of it. ``phi_bounds``: (min, max) of ``phi`` if
    known (a pass has two calls)."""
    if M.BEAMS[tier] == "piston":
        # theta in float64: next to the piston beam's nulls ln g changes by ~1e5 per
        # rad, so the rounding of yaw (1e-7 rad) would show
        return _log_beam32(tier, mod, _angle_diff(phi, yaw, bounds, phi_bounds),
                           derivative, ddiv)
    lo, hi = bounds
    wrap = True
    if yaw.size:
        p_lo, p_hi = phi_bounds if phi_bounds is not None else (phi.min(), phi.max())
        wrap = not (p_hi - lo <= np.pi and p_lo - hi >= -np.pi)
    th = M._wrap_fast(phi - yaw).astype(np.float32) if wrap else phi.astype(np.float32) - yaw32
    return _log_beam32(tier, mod, th, derivative, ddiv)


def _log_beam32(tier: str, mod: ModuleParams, th: FloatArray, derivative: bool,
                ddiv: float = 1.0
                ) -> tuple[NDArray[np.float32], NDArray[np.float32] | None]:
    """ln g and d ln g / d theta / ``ddiv`` (None without ``derivative``) in float32 at
    off-axis angles ``th`` (float32 for the gauss beam, whose closed form is capped as
    :func:`sonarloc.fit.model.beam_log_factor`; float64 for the piston table's cubic,
    :meth:`sonarloc.fit.model._HermiteTable.lookup_log32`). ``th`` of the gauss beam is
    overwritten."""
    if M.BEAMS[tier] == "piston":
        table = M._piston_table(mod.diameter_m, mod.carrier_hz, mod.c_mps)
        lng_p, dlng_p, _ = table.lookup_log32(th, derivative, ddiv)
        return lng_p, dlng_p
    q, capped = _gauss_log_factor32(th, mod)
    if not derivative:
        return q, None
    dlng = th
    dlng *= _gauss_scales32(mod.sigma_deg, ddiv)[1]           # inv_s2 / ddiv
    if capped:
        dlng[q >= np.float32(_LN_G_MAX)] = 0.0
    return q, dlng


@dataclass
class _Moving32:
    """What a moving batch's float32 pass needs of its readings' geometry (B, N): ln g
    and d ln g / d theta / ``ddiv`` (float32); for echoes the range R (float64: the
    residuals are formed from it before rounding) and tau times its derivatives by
    (r, phi) (float32; None for the no-echo readings); the derivatives of theta by
    (r, phi) (float32). None where constant: a wall's dR/dr = 1 (``tdR_dr``), dtheta/dr
    = 0 and dtheta/dphi = 1."""

    lng: NDArray[np.float32]
    dlng: NDArray[np.float32] | None
    R: Array | None
    tdR_dr: NDArray[np.float32] | None
    tdR_dphi: NDArray[np.float32] | None
    dth_dr: NDArray[np.float32] | None
    dth_dphi: NDArray[np.float32] | None


def _moving_geometry32(kind: str, tier: str, mod: ModuleParams, r: Array, phi: Array,
                       px: Array, py: Array, yaw: Array, yaw32: NDArray[np.float32],
                       bounds: tuple[float, float], derivative: bool, ddiv: float = 1.0,
                       tau: float | None = None) -> _Moving32:
    """:class:`_Moving32` of readings at (px, py) (relative to the reference) with axes
    ``yaw``, for a local landmark (r, phi) (B, 1) (:func:`sonarloc.fit.model.geometry`);
    ``tau`` (us per m): the range and its derivatives too (echoes).

    Along the landmark's direction u(phi) a reading sits at ``l = p . u`` and beside it
    at ``m = p x u = px sin phi - py cos phi``; a wall is at range ``r - l`` (dR/dphi =
    m), a point at ``R = |(r - l, m)|`` and bearing ``phi + atan2(m, r - l)`` (so
    dR/dr = (r - l) / R, dR/dphi = r m / R, dtheta/dr = -m / R^2, dtheta/dphi =
    r (r - l) / R^2). l, m and R in float64 (R feeds the residuals: tens of thousands
    of us, formed before rounding), the rest in float32; the piston beam's theta in
    float64 (see :func:`_off_axis32`)."""
    f32 = np.float32
    c, s = np.cos(phi), np.sin(phi)
    u = px * c
    u += py * s                                          # l
    m = px * s
    m -= py * c
    if kind == "line":
        lng, dlng = _off_axis32(tier, mod, phi, yaw32, yaw, bounds, derivative, ddiv)
        if tau is None:
            return _Moving32(lng, dlng, None, None, None, None, None)
        tdR_dphi = (m * tau).astype(f32) if derivative else None
        np.subtract(r, u, out=u)
        return _Moving32(lng, dlng, u, None, tdR_dphi, None, None)
    np.subtract(r, u, out=u)                             # r - l
    u32, m32 = u.astype(f32), m.astype(f32)
    if M.BEAMS[tier] == "piston":
        th: FloatArray = _angle_diff(phi, yaw, bounds) + np.arctan2(m, u)
    else:
        th = phi.astype(f32) - yaw32
        th += np.arctan2(m32, u32)
    # (the wrap keeps float32 angles float32)
    lng, dlng = _log_beam32(tier, mod, M._wrap_fast(cast(Array, th)), derivative, ddiv)
    R = None
    if tau is not None or derivative:
        R = u * u
        R += m * m
        np.sqrt(R, out=R)
    if not derivative:
        return _Moving32(lng, None, R, None, None, None, None)
    assert R is not None
    r32 = r.astype(f32)
    iR = np.maximum(R, 1e-9).astype(f32)
    np.reciprocal(iR, out=iR)                            # 1 / R
    tdR_dr = tdR_dphi = None
    if tau is not None:
        tiR = iR * f32(tau)
        tdR_dr = u32 * tiR
        tdR_dphi = m32 * tiR
        tdR_dphi *= r32
    iR *= iR                                             # 1 / R^2
    iR *= f32(-1.0)
    m32 *= iR                                            # dtheta / dr
    u32 *= iR
    u32 *= -r32                                          # dtheta / dphi
    return _Moving32(lng, dlng, R if tau is not None else None, tdR_dr, tdR_dphi, m32, u32)


def _moving_columns32(out: NDArray[np.float32], geo: _Moving32, tau: float,
                      dth: FloatArray, dk: FloatArray) -> None:
    """Write into ``out`` (B, 3, N) the derivatives by (r, phi, kappa) of a moving
    batch's per-reading terms: ``tau`` R (``tau`` 0: none; else ``geo`` has R's
    derivatives) plus a term with derivative ``dth`` by theta (B, N) and ``dk`` by kappa
    ((B, N) or (B, 1))."""
    if geo.dth_dr is None:                              # a wall: dtheta/dr = 0, /dphi = 1
        out[:, 0] = tau
        np.copyto(out[:, 1], dth)
    else:
        assert geo.dth_dphi is not None
        np.multiply(dth, geo.dth_dr, out=out[:, 0])
        np.multiply(dth, geo.dth_dphi, out=out[:, 1])
        if tau:
            assert geo.tdR_dr is not None
            out[:, 0] += geo.tdR_dr
    if tau:
        assert geo.tdR_dphi is not None
        out[:, 1] += geo.tdR_dphi
    out[:, 2] = dk


def _evaluate32(kind: str, p: Array, batch: SegmentBatch, y: Array, use: NDArray,
                s2: Array | None, cfg: FitConfig, want_derivs: bool = True,
                s2_other: Array | None = None, tier: str = "gauss"
                ) -> tuple[Array, Array, Array, Array, Array, Array]:
    """:func:`_evaluate_core` with the detection model in float32 (``FitConfig.float32``).

    The readings enter relative to the model range (``y - tau R`` formed in float64,
    then rounded: tens of us, not ten thousands; a moving batch's R and the positions'
    projections on the landmark's direction in float64 too,
    :func:`_moving_geometry32`), the normal tail
    probabilities come from :func:`sonarloc.fit.model.log_sf32` (branch-free), the
    objective is summed in float64, the rest of the sums in float32 (relative error
    ~1e-6); returns float64 ``F``, gradient and Fisher matrix, float32 residuals and
    variances. Same model and return values as :func:`_evaluate_core` otherwise:
    ``gauss`` and ``piston`` with the truncated mean delay (:func:`_truncation_ratio32`),
    ``waveform`` with the delay table's moments at ``ln u = ln kappa + ln g``
    (:meth:`sonarloc.fit.model._DelayTable.lookup_log32`).
    """
    f32 = np.float32
    mod = cfg.module
    tau = M.us_per_m(mod)
    sa = M.sigma_a(mod)
    r, phi, K = p[:, 0:1], p[:, 1:2], p[:, 2:3]
    B = p.shape[0]
    lnk = np.log(np.maximum(K, 1e-300))
    zc = ((lnk - np.log(mod.detection_limit_us)) / sa).astype(f32)      # (B, 1)
    waveform = tier == "waveform"

    # detection margins z of the echoes and of the no-echo readings
    phi_bounds = (float(phi.min()), float(phi.max())) if B else None
    moving = batch.moving
    geo = gn = None
    if moving:
        geo = _moving_geometry32(kind, tier, mod, r, phi, batch.px, batch.py, batch.yaw,
                                 batch.yaw32, batch.yaw_bounds[:2], want_derivs, tau=tau)
        lng, dlng = geo.lng, geo.dlng
    else:
        lng, dlng = _off_axis32(tier, mod, phi, batch.yaw32, batch.yaw,
                                batch.yaw_bounds[:2], want_derivs, phi_bounds=phi_bounds)
    z = lng * (1.0 / sa)             # (Python float constants: float32 ops, NEP 50)
    z += zc
    nv = batch.ne_valid
    noecho = bool(nv.shape[1] and nv.any())
    zz = z.reshape(-1)
    if noecho:
        if moving:
            gn = _moving_geometry32(kind, tier, mod, r, phi, batch.ne_px, batch.ne_py,
                                    batch.ne_yaw, batch.ne_yaw32, batch.yaw_bounds[2:],
                                    want_derivs, sa)
            lgn, dzn = gn.lng, gn.dlng                  # dzn: d zn / d theta
        else:
            lgn, dzn = _off_axis32(tier, mod, phi, batch.ne_yaw32, batch.ne_yaw,
                                   batch.yaw_bounds[2:], want_derivs, sa,   # d zn / d theta
                                   phi_bounds)
        zn = lgn * (1.0 / sa)
        zn += zc
        # the normal tails of both in one pass (elementwise: the same numbers as two),
        # end to end flat: every part below a contiguous array of its own shape (columns
        # side by side were copied and then swept row by row)
        zz = np.concatenate([zz, (-zn).reshape(-1)])
    # log P(echo) = log Phi(-z), log P(no echo) = log Phi(zn); phi / Phi of each
    lp = M.log_sf32(zz)
    mills, excess = M.mills_ratio32(zz, lp)
    ne = z.size
    l0, m0, h0 = (t[:ne].reshape(z.shape) for t in (lp, mills, excess))
    curv = m0 * h0                                      # d m0 / dz = m0 (m0 - z)
    if waveform:
        # the module's delay moments at x = ln u (u = kappa g, the eq. 3 delay)
        x = lng + lnk.astype(f32)
        delay, dm_dx, var = M.waveform_delay_table(mod).lookup_log32(x, want_derivs)
        if s2 is None:
            var += float(mod.jitter_sd_us ** 2 + mod.count_period_us ** 2 / 12.0)
            s2 = var   # type: ignore[assignment]   # float32 (see Returns)
    else:
        g = np.exp(lng)
        ratio = _truncation_ratio32(h0, m0, curv, sa)    # Phi(-z-s) / Phi(-z)
        scale = float(np.exp(0.5 * sa * sa))
        delay = g * ratio
        delay *= (K * scale).astype(f32)
        if s2 is None:
            v = delay * delay
            v *= float(mod.amplitude_fluctuation ** 2)
            v += float(mod.jitter_sd_us ** 2 + mod.count_period_us ** 2 / 12.0)
            s2 = v     # type: ignore[assignment]   # float32 (see Returns)
    assert s2 is not None
    usef = use.astype(f32)
    w = usef / np.sqrt(s2)                              # 1/s, 0 where unused
    res = (y - tau * (r if geo is None or geo.R is None else geo.R)).astype(f32)
    res -= delay
    e = res * w
    F = _dot64(e, e)
    dF = 2.0 * _dot64(l0, usef)
    F -= dF
    F_other = F
    if s2_other is not None:
        F_other = _dot64(res * res, usef / s2_other) - dF
    grad = np.zeros((B, 3))
    H = np.zeros((B, 3, 3))
    ik = 1.0 / (K[:, 0] * sa)                           # d z / d kappa
    # a moving batch's terms: (geometry, tau, d / d theta, d / d kappa, Gram weights of
    # H and of the gradient), summed at the end (:func:`_gram_moving32`)
    blocks: list[tuple[_Moving32, float, FloatArray, FloatArray, FloatArray,
                       FloatArray]] = []
    if want_derivs:
        assert dlng is not None
        if waveform:
            assert dm_dx is not None
            # d mean / d kappa = (d mean / d ln u) / kappa, d mean / d theta = (d mean /
            # d ln u) d ln g / d theta
            jk = dm_dx * (1.0 / K).astype(f32)
            a = dm_dx * dlng
        else:
            # d mean / d kappa: scale (ratio + (ratio m0 - m1) / s) g
            m1 = np.exp(z * -sa - 0.5 * sa * sa)                # phi(z+s) / Phi(-z)
            m1 *= m0
            jk = ratio * m0
            jk -= m1
            jk *= 1.0 / sa
            jk += ratio
            jk *= g
            jk *= scale
            _truncated_slope_far32(jk, z, h0, ratio, g, scale, sa)
            a = jk * dlng
            a *= K.astype(f32)                          # d mean / d theta
        dz = dlng * (1.0 / sa)          # detection: d z / d theta = dlng / sa, d / dK = ik
        if geo is not None:     # moving: summed with the no-echo terms at the end
            blocks += [(geo, tau, a, jk, w * w, w * e),
                       (geo, 0.0, dz, ik[:, None], curv * usef, -(m0 * usef))]
        else:
            # the weighted columns of the Fisher matrix and the gradient in one array, so
            # that their row sums and dot products take four einsum calls, not fourteen (the
            # same sums: each row's own, in its order); the float64 additions as before
            S = np.empty((7, *e.shape), dtype=np.result_type(w, e, a, jk, curv, usef, dz))
            W, Wd, Wa, Gw, Wj, Wdz, Gd = S
            np.multiply(w, w, out=W)
            np.multiply(curv, usef, out=Wd)                 # curvature of -log Phi(-z)
            np.multiply(W, a, out=Wa)
            np.multiply(w, e, out=Gw)
            np.multiply(W, jk, out=Wj)
            np.multiply(Wd, dz, out=Wdz)
            np.multiply(m0, usef, out=Gd)                   # -d log P / dz
            sums = _sum_rows(S)
            dot_a, dot_jk = _dot_rows(S[2:4], a), _dot_rows(S[2:5], jk)
            dot_dz = _dot_rows(S[5:], dz)
            H[:, 0, 0] = tau * tau * sums[0]
            H[:, 0, 1] = tau * sums[2]
            H[:, 0, 2] = tau * sums[4]
            H[:, 1, 1] = dot_a[0]
            H[:, 1, 2] = dot_jk[0]
            H[:, 2, 2] = dot_jk[2]
            grad[:, 0] = -tau * sums[3]
            grad[:, 1] = -dot_a[1]
            grad[:, 2] = -dot_jk[1]
            H[:, 1, 1] += dot_dz[0]
            H[:, 1, 2] += ik * sums[5]
            H[:, 2, 2] += ik * ik * sums[1]
            grad[:, 1] += dot_dz[1]
            grad[:, 2] += ik * sums[6]
    prior = _kappa_prior(K[:, 0], grad, H, cfg, want_derivs)
    F = F + prior
    F_other = F_other + prior if s2_other is not None else F
    if noecho:
        lpn = lp[ne:].reshape(zn.shape)                 # log P(no echo) = log Phi(zn)
        nvf = nv.astype(f32)
        dFn = 2.0 * _dot64(lpn, nvf)
        F = F - dFn
        F_other = F_other - dFn if s2_other is not None else F
        if want_derivs:
            assert dzn is not None
            mn = mills[ne:].reshape(zn.shape)           # phi(zn) / Phi(zn)
            hn = excess[ne:].reshape(zn.shape)          # mn + zn
            if gn is not None:
                blocks.append((gn, 0.0, dzn, ik[:, None], hn * mn * nvf, mn * nvf))
            else:
                Sn = np.empty((3, *mn.shape), dtype=np.result_type(zn, mn, nvf, dzn))
                Wn, Wndz, Gn = Sn                       # (stacked as the echoes' S)
                np.multiply(hn, mn, out=Wn)
                Wn *= nvf                               # curvature of -log Phi(z)
                np.multiply(Wn, dzn, out=Wndz)
                np.multiply(mn, nvf, out=Gn)            # d log P / dz
                sums_n, dot_n = _sum_rows(Sn), _dot_rows(Sn[1:], dzn)
                H[:, 1, 1] += dot_n[0]
                H[:, 1, 2] += ik * sums_n[1]
                H[:, 2, 2] += ik * ik * sums_n[0]
                grad[:, 1] -= dot_n[1]
                grad[:, 2] -= ik * sums_n[2]
    if blocks:
        _gram_moving32(H, grad, blocks)
    H[:, 1, 0], H[:, 2, 0], H[:, 2, 1] = H[:, 0, 1], H[:, 0, 2], H[:, 1, 2]
    return F_other, F, grad, H, e, s2


def _gram_moving32(H: Array, grad: Array, blocks: Sequence[tuple[
        _Moving32, float, FloatArray, FloatArray, FloatArray, FloatArray]]) -> None:
    """:func:`_gram` of a moving batch's float32 terms: ``H += sum_n wH c c^T`` and
    ``grad -= sum_n wg c`` over the readings of all ``blocks`` (each ``(geometry, tau,
    dth, dk, wH, wg)``, its derivatives c by (r, phi, kappa) as
    :func:`_moving_columns32` writes them), as one stacked Jacobian (B, 3, N) and one
    batched matrix product: a moving fit's passes hold ~10 segments, where the numpy
    calls of separate row sums (~80 a pass) cost more than the sums."""
    f32 = np.float32
    widths = [blk[4].shape[1] for blk in blocks]
    J = np.empty((H.shape[0], 3, sum(widths)), dtype=f32)
    wH = np.empty((H.shape[0], sum(widths)), dtype=f32)
    wg = np.empty_like(wH)
    o = 0
    for (geo, tau, dth, dk, h, g), k in zip(blocks, widths, strict=True):
        _moving_columns32(J[:, :, o:o + k], geo, tau, dth, dk)
        wH[:, o:o + k], wg[:, o:o + k] = h, g
        o += k
    H += np.matmul(J * wH[:, None, :], J.transpose(0, 2, 1))
    grad -= _einsum("bkn,bn->bk", J, wg)


def _gram(H: Array, grad: Array, cols: Sequence[Array | None], wH: Array, wg: Array) -> None:
    """``H[k, l] += sum_n wH c_k c_l`` and ``grad[k] -= sum_n wg c_k`` over readings n.

    ``cols``: three columns, each (B, N), (B, 1) (the same for all readings) or None
    (zero); ``wH``, ``wg``: (B, N) weights.
    """
    sw: Array | None = None
    sg: Array | None = None
    dense: list[Array | None] = []          # wH * c of the columns that vary by reading
    for c in cols:
        if c is not None and c.shape[1] == 1:
            if sw is None:
                sw, sg = wH.sum(1), wg.sum(1)
            dense.append(None)
        else:
            dense.append(None if c is None else wH * c)
    for k in range(3):
        ck, dk = cols[k], dense[k]
        if ck is None:
            continue
        grad[:, k] -= (ck[:, 0] * sg if dk is None and sg is not None
                       else np.einsum("bn,bn->b", wg, ck))
        for m in range(k, 3):
            cm, dm = cols[m], dense[m]
            if cm is None:
                continue
            if dk is None and dm is None and sw is not None:
                v = ck[:, 0] * cm[:, 0] * sw
            elif dk is None and dm is not None:
                v = ck[:, 0] * dm.sum(1)
            elif dm is None and dk is not None:
                v = cm[:, 0] * dk.sum(1)
            else:
                v = np.einsum("bn,bn->b", dk if dk is not None else wH * ck, cm)
            H[:, k, m] += v
            if m != k:
                H[:, m, k] += v


def _angle_diff(a: FloatArray, b: FloatArray, b_bounds: tuple[float, float] | None = None,
                a_bounds: tuple[float, float] | None = None) -> Array:
    """``a - b`` wrapped to [-pi, pi] (broadcast); the bounds of the (small) inputs tell
    when no wrapping is needed, which saves passes over the (large) result.
    ``b_bounds``, ``a_bounds``: (min, max) of ``b`` (see :attr:`SegmentBatch.yaw_bounds`)
    and of ``a`` if known."""
    if a.size and b.size:
        bmin, bmax = b_bounds if b_bounds is not None else (b.min(), b.max())
        amin, amax = a_bounds if a_bounds is not None else (a.min(), a.max())
        if amax - bmin <= np.pi and amin - bmax >= -np.pi:
            return a - b
    return M._wrap_fast(a - b)


def _is_moving(batch: SegmentBatch) -> bool:
    """Whether any reading was taken away from its segment's reference position."""
    return batch.moving


def tof_jacobian(kind: str, tier: str, p: Array, batch: SegmentBatch, cfg: FitConfig
                 ) -> tuple[Array, Array, Array]:
    """Whitened TOF Jacobian (B, 3, Nd), mean delays (B, Nd) and SDs (B, Nd) at ``p``."""
    mod = cfg.module
    r, phi, K = p[:, 0:1], p[:, 1:2], p[:, 2:3]
    geo = M.geometry(kind, r, phi, batch.px, batch.py, batch.yaw)
    g, dg, lng = M.beam_delay_factor(geo.theta, tier, mod)
    z = M.detection_z(K, lng, mod) if cfg.detection else None
    J, et, sd = tof_jacobian_at(geo, K, g, dg, z, tier, mod)
    return J, et.delay, sd


def tof_jacobian_at(geo: M.Geometry, K: Array, g: Array, dg: Array, z: Array | None,
                    tier: str, mod: ModuleParams) -> tuple[Array, M.EchoTerms, Array]:
    """:func:`tof_jacobian` from the readings' geometry, kappa (B, 1), the beam's delay
    factor and its derivative and the detection margins (None: no detection model) at
    the fits: the whitened Jacobian (B, 3, Nd), the echo terms and the TOF SDs."""
    tau = M.us_per_m(mod)
    et = M.echo_terms(K, g, z, mod, want_info=False, tier=tier)
    sd = np.sqrt(M.tof_variance_us2(et.delay, mod, et.delay_var if tier == "waveform"
                                    else None))
    a = et.ddelay_du * K * dg
    J = np.stack([tau * geo.dR_dr + a * geo.dtheta_dr, tau * geo.dR_dphi + a * geo.dtheta_dphi,
                  np.broadcast_to(et.ddelay_du * g, g.shape)], axis=1) / sd[:, None, :]
    return J, et, sd


def _kappa_penalty(K: Array, cfg: FitConfig) -> tuple[Array, Array, Array]:
    """Soft box prior: (-2 log prior, its derivative by K, its curvature by K)."""
    if (math.isfinite(cfg.kappa_soft_log_sd)
            and not (K.size and K.min() >= cfg.kappa_lo_us and K.max() <= cfg.kappa_hi_us)):
        # (inside the box in kappa is inside it in log kappa: the log is monotonic)
        lk = np.log(K)
        lo, hi = np.log(cfg.kappa_lo_us), np.log(cfg.kappa_hi_us)
        if not (lk.size and lk.min() >= lo and lk.max() <= hi):    # some outside the box
            v = cfg.kappa_soft_log_sd ** 2
            d = np.maximum(lk - hi, 0.0) + np.minimum(lk - lo, 0.0)   # ln-distance outside
            out = d != 0.0
            return (d * d / v, 2.0 * d / (v * K),
                    np.where(out, 2.0 * (1.0 - d) / (v * K * K), 0.0))
    z = np.zeros(np.shape(K))     # no prior, or every kappa inside the box
    return z, z, z


def _kappa_prior(K: Array, grad: Array, H: Array, cfg: FitConfig, want_derivs: bool
                 ) -> Array:
    """-2 log of the kappa prior (B,); adds its share to the gradient of F/2 and to H."""
    pen, d1, d2 = _kappa_penalty(K, cfg)
    if want_derivs and d1.any():
        grad[:, 2] += 0.5 * d1
        H[:, 2, 2] += 0.5 * np.maximum(d2, 0.0)
    return pen


def _variances(kind: str, tier: str, p: Array, batch: SegmentBatch, cfg: FitConfig) -> Array:
    """TOF variances (B, Nd) [us^2] of the echoes at parameters ``p``."""
    mod = cfg.module
    geo = M.geometry(kind, p[:, 0:1], p[:, 1:2], batch.px, batch.py, batch.yaw)
    g, _, lng = M.beam_delay_factor(geo.theta, tier, mod, derivative=False)
    z = M.detection_z(p[:, 2:3], lng, mod) if cfg.detection else None
    et = M.echo_terms(p[:, 2:3], g, z, mod, want_info=False, tier=tier)
    return M.tof_variance_us2(et.delay, mod, et.delay_var if tier == "waveform" else None)


def _decimate(batch: SegmentBatch, y: Array, use: NDArray, max_echoes: int
              ) -> tuple[SegmentBatch, Array, NDArray, Array]:
    """``max_echoes`` used echoes, evenly spread from the first to the last, of segments
    with more, each weighted by (used echoes / kept ones) (the rest: all, weight 1): the
    grid bracket's readings. Columns: the kept echoes, in order."""
    n_use = use.sum(1)
    if int(n_use.max(initial=0)) <= max_echoes:
        return batch, y, use, use.astype(float)
    width = max(int(n_use.max()), 1)
    # column of the j-th used echo of each segment (used echoes first, in order)
    if use[:, 1:].shape[1] and np.any(use[:, 1:] & ~use[:, :-1]):
        order = np.argsort(~use, axis=1, kind="stable")[:, :width]
    else:       # no gaps: the used echoes are the first columns
        order = np.broadcast_to(np.arange(width), use[:, :width].shape)
    m = np.minimum(n_use, max_echoes)                                  # (B,) kept
    j = np.arange(max_echoes)[None, :]
    ok = j < m[:, None]
    pick = np.rint(j * ((n_use - 1) / np.maximum(m - 1, 1))[:, None]).astype(np.int64)
    cols = np.take_along_axis(order, np.clip(pick, 0, width - 1), axis=1)

    def g(a: Array) -> Array:
        return np.take_along_axis(a, cols, axis=1)

    if batch.moving:
        px, py = g(batch.px), g(batch.py)
    else:                   # all at the reference: zeros (no gathers)
        px = py = np.zeros(cols.shape)
    sub = SegmentBatch(px, py, g(batch.yaw), g(batch.tof_us), ok, batch.ne_px, batch.ne_py,
                       batch.ne_yaw, batch.ne_valid, batch.ref_xy, batch.ref_yaw,
                       batch.ref_t_s)
    # the no-echo readings are the batch's own: so are their cached forms
    for name in ("moving", "ne_yaw32"):
        if name in batch.__dict__:
            sub.__dict__[name] = batch.__dict__[name]
    wt = np.where(ok, (n_use / np.maximum(m, 1))[:, None], 0.0)
    return sub, np.where(ok, g(y), 0.0), ok, wt


def _node_profile(kind: str, tier: str, batch: SegmentBatch, phis: Array, r0: Array,
                  yc: Array, use: NDArray, wt: Array, moving: bool, cfg: FitConfig,
                  detection_cost: bool = True) -> tuple[Array, Array, Array]:
    """Profile over (To, kappa) at bearing nodes ``phis`` (B, G): To - y0 (B, G), kappa
    (B, G) and the approximate -2 log-likelihood (B, G).

    ``yc`` (B, Nd): readings less y0 (0 where unused); ``wt`` (B, Nd): reading weights
    (0 where unused; >1 for a decimated segment's kept echoes); ``r0`` (B,): the range of
    the geometry of a moving sensor. Bearing-independent TOF weights (the on-axis
    variance), so that the nodes' costs compare and weigh against the detection terms
    as a likelihood does; the detection terms in a cheap form good to ~10% (a bracket
    needs only the shape): 0.35 max(z + 1.4, 0)^2 per echo, 0.35 max(1.4 - z, 0)^2 per
    no-echo reading.
    """
    mod = cfg.module
    tau = M.us_per_m(mod)
    # float32 (FitConfig.float32): the (B, G, Nd) arrays of a stationary batch
    single = cfg.float32 and not moving
    dt: type[np.floating[Any]] = np.float32 if single else np.float64
    g: FloatArray
    lg: FloatArray
    if moving:
        R, theta = M.range_angle(kind, r0[:, None, None], phis[:, :, None],
                                 batch.px[:, None, :], batch.py[:, None, :],
                                 batch.yaw[:, None, :])
    elif single:
        theta = _angle_diff(phis.astype(dt)[:, :, None], batch.yaw32[:, None, :],
                            batch.yaw_bounds[:2])
    else:
        theta = _angle_diff(phis[:, :, None], batch.yaw[:, None, :], batch.yaw_bounds[:2])
    if single:
        lg = _log_factor32(theta, tier, mod)
        g = np.exp(lg)
    else:
        g, _, lg = M.beam_log_factor(theta, tier, mod, derivative=False)
    sa = M.sigma_a(mod)
    scale = np.exp(0.5 * sa * sa)
    wt_d = wt.astype(dt)
    w = wt_d[:, None, :]
    gw = g * w                                     # (B, G, Nd); the profile's g is scale g
    S0 = wt.sum(1)[:, None]
    S1 = gw.sum(-1).astype(float) * scale
    S2 = np.einsum("bgn,bgn->bg", gw, g).astype(float) * (scale * scale)
    if moving:   # the range offsets of the readings depend on the node
        ycg = (yc[:, None, :] - tau * (R - r0[:, None, None])) * (use[:, None, :])
        Sy = np.einsum("bgn,bgn->bg", ycg, w)
        Syy = np.einsum("bgn,bgn->bg", ycg * w, ycg)
        Sgy = np.einsum("bgn,bgn->bg", gw, ycg) * scale
    else:
        Sy = np.einsum("bn,bn->b", yc, wt)[:, None]
        Syy = np.einsum("bn,bn->b", yc * wt, yc)[:, None]
        Sgy = np.matmul(gw, yc.astype(dt)[:, :, None])[..., 0].astype(float) * scale
    if cfg.detection:
        # echoes were detected: the one nearest the axis must be detectable (z < 2)
        # (a large number added to the unused: a plain min is 3x faster than a masked one)
        big = np.where(use, 0.0, np.inf if single else 1e300).astype(dt)
        lg_min = np.min(lg + big[:, None, :], axis=-1).astype(float)
        lg_min = np.where(lg_min < 1e299, lg_min, np.inf)
        kmax = (mod.detection_limit_us * np.exp(2.0 * sa) * scale
                * np.exp(-np.where(np.isfinite(lg_min), lg_min, 0.0)))
    else:
        kmax = np.full(phis.shape, np.inf)
    T, Keff, sse = _profile_2x2(S0, S1, S2, Sy, Sgy, Syy, cfg.kappa_min_us * scale, kmax)
    K = Keff / scale
    if not detection_cost:
        return T, K, np.zeros(phis.shape)
    w0 = 1.0 / float(M.tof_variance_us2(0.0, mod))
    cost = w0 * sse + _kappa_penalty(K, cfg)[0]
    if cfg.detection:
        # z + 1.4 = (ln g + ln kappa - ln L + 1.4 sa) / sa, formed in place (B, G, Nd)
        lk = np.log(np.maximum(K, 1e-300))
        zd = lg + (lk - np.log(mod.detection_limit_us) + 1.4 * sa).astype(dt)[..., None]
        np.maximum(zd, 0.0, out=zd)
        cost = cost + (0.7 / (sa * sa)) * np.einsum("bgn,bgn->bg", zd * w, zd).astype(float)
        if batch.ne_valid.shape[1] and batch.ne_valid.any():
            if moving:
                thn = M.range_angle(kind, r0[:, None, None], phis[:, :, None],
                                    batch.ne_px[:, None, :], batch.ne_py[:, None, :],
                                    batch.ne_yaw[:, None, :])[1]
            elif single:
                thn = _angle_diff(phis.astype(dt)[:, :, None], batch.ne_yaw32[:, None, :],
                                  batch.yaw_bounds[2:])
            else:
                thn = _angle_diff(phis[:, :, None], batch.ne_yaw[:, None, :],
                                  batch.yaw_bounds[2:])
            if single:
                lgn = _log_factor32(thn, tier, mod)
            else:
                lgn = M.beam_log_factor(thn, tier, mod, derivative=False, want_g=False)[2]
            # (1.4 - z) sa = (ln L + 1.4 sa - ln kappa) - ln g, formed in place
            zn = np.subtract((np.log(mod.detection_limit_us) + 1.4 * sa - lk).astype(dt)[
                ..., None], lgn)
            np.maximum(zn, 0.0, out=zn)
            zn *= batch.ne_valid[:, None, :]
            cost = cost + (0.7 / (sa * sa)) * np.einsum("bgn,bgn->bg", zn, zn).astype(float)
    return T, K, cost


def _log_factor32(theta: FloatArray, tier: str, mod: ModuleParams) -> FloatArray:
    """ln g of the tier's beam in float32: the gauss beam's theta^2 / 2 sigma^2 capped as
    in :func:`sonarloc.fit.model.beam_log_factor`, the piston table's cubic
    (:meth:`sonarloc.fit.model._HermiteTable.lookup_log32`)."""
    if M.BEAMS[tier] == "piston":
        table = M._piston_table(mod.diameter_m, mod.carrier_hz, mod.c_mps)
        return table.lookup_log32(theta, derivative=False)[0]
    return _gauss_log_factor32(theta, mod)[0]


_LN_G_MAX = np.log(M._G_MAX)


@functools.lru_cache(maxsize=64)
def _gauss_scales32(sigma_deg: float, ddiv: float) -> tuple[np.float32, np.float32]:
    """The gauss beam's float32 factors of a pass: 1 / 2 sigma^2 (ln g = theta^2 times
    it) and 1 / sigma^2 / ``ddiv`` (d ln g / d theta over theta, scaled); worked out
    once (a model pass needs them twice)."""
    inv_s2 = 1.0 / np.deg2rad(sigma_deg) ** 2
    return np.float32(0.5 / np.deg2rad(sigma_deg) ** 2), np.float32(inv_s2 / ddiv)


def _gauss_log_factor32(theta: FloatArray, mod: ModuleParams) -> tuple[FloatArray, bool]:
    """ln g = theta^2 / 2 sigma^2 of the gauss beam in float32, capped as in
    :func:`sonarloc.fit.model.beam_log_factor`, and whether any entry is capped."""
    cap = _LN_G_MAX
    q = theta * theta
    q *= _gauss_scales32(mod.sigma_deg, 1.0)[0]
    capped = bool(q.size) and float(q.max()) >= cap
    if capped:
        np.minimum(q, np.float32(cap), out=q)
    return q, capped


def _grid_start(kind: str, tier: str, batch: SegmentBatch, y: Array, use: NDArray,
                cfg: FitConfig) -> tuple[Array, Array, NDArray[np.bool_], Array]:
    """Global bracket on a bearing grid: the best (r, phi, kappa) node, the best other
    local minimum and whether it is close enough to be refined too; the arc (lo, hi).

    Each start's bearing is refined by a parabola through its node and the neighbours,
    and its (To, kappa) profiled again there (with all echoes, the grid may use every
    k-th of a long segment's: ``cfg.grid_max_echoes``)."""
    mod = cfg.module
    tau = M.us_per_m(mod)
    B = batch.size
    with np.errstate(invalid="ignore"):
        y0 = np.nanmin(np.where(use, y, np.inf), axis=1)
    y0 = np.where(np.isfinite(y0), y0, 0.0)
    bear, centre = _axis_bearings(kind, batch, np.where(use, y, y0[:, None]), tau)
    rel = M._wrap_fast(bear - centre[:, None])
    lo = np.min(np.where(use, rel, np.inf), axis=1)
    hi = np.max(np.where(use, rel, -np.inf), axis=1)
    lo = np.where(np.isfinite(lo), lo, 0.0)
    hi = np.where(np.isfinite(hi), hi, 0.0)
    # nodes: uniform over the covered arc, coarser over the margins (partial U's); each
    # segment has its own count (the rest padded at the end), so that a segment's fit
    # does not depend on the other segments of the batch
    step = np.deg2rad(cfg.grid_step_deg)
    n_in = np.clip(np.ceil((hi - lo) / step).astype(np.int64) + 1, 3, 721)     # (B,)
    n_out = int(np.ceil(cfg.margin_deg / (2.0 * cfg.grid_step_deg)))
    margin = np.deg2rad(cfg.margin_deg)
    n_grid = int(n_in.max(initial=3)) + 2 * n_out
    j = np.arange(n_grid)[None, :]
    n_in_c = n_in[:, None]
    inner = lo[:, None] + (hi - lo)[:, None] * (j - n_out) / np.maximum(n_in_c - 1, 1)
    left = lo[:, None] - margin * (n_out - j) / max(n_out, 1)
    right = hi[:, None] + margin * (j - n_out - n_in_c + 1) / max(n_out, 1)
    pad = j >= n_in_c + 2 * n_out
    offs = np.where(j < n_out, left, np.where(j < n_out + n_in_c, inner, right))
    offs = np.where(pad, hi[:, None] + margin, offs)                          # (B, G)
    phis = centre[:, None] + offs
    r0 = y0 / tau
    moving = _is_moving(batch)
    yc = np.where(use, y - y0[:, None], 0.0)                                 # (B, Nd)
    usef = use.astype(float)
    if cfg.grid_max_echoes is not None:
        gb, gy, guse, gw = _decimate(batch, yc, use, cfg.grid_max_echoes)
    else:
        gb, gy, guse, gw = batch, yc, use, usef
    # nodes in blocks: temporaries of at most ~_GRID_BLOCK elements (large fresh arrays
    # cost page faults)
    per = max(_GRID_BLOCK // max(B * (gb.px.shape[1] + gb.ne_px.shape[1]), 1), 1)
    cost = np.empty((B, n_grid))
    for a in range(0, n_grid, per):
        cost[:, a:a + per] = _node_profile(kind, tier, gb, phis[:, a:a + per], r0, gy, guse,
                                           gw, moving, cfg)[2]
    cost = np.where(np.isfinite(cost) & ~pad, cost, np.inf)
    rows = np.arange(B)
    arc = np.stack([centre + lo, centre + hi], axis=-1)
    k1 = np.argmin(cost, axis=1)
    # the best other local minimum (at least two nodes away) for a second start
    left = np.concatenate([np.full((B, 1), np.inf), cost[:, :-1]], axis=1)
    right = np.concatenate([cost[:, 1:], np.full((B, 1), np.inf)], axis=1)
    local_min = (cost <= left) & (cost <= right) & np.isfinite(cost)
    far = np.abs(np.arange(n_grid)[None, :] - k1[:, None]) >= 2
    c2 = np.where(local_min & far, cost, np.inf)
    k2 = np.argmin(c2, axis=1)
    second = np.isfinite(c2[rows, k2]) & (c2[rows, k2] - cost[rows, k1] < cfg.second_start_dcost)
    best = []
    for k in (k1, k2):
        # parabolic refinement through the node and its neighbours
        kl = np.clip(k - 1, 0, n_grid - 1)
        kr = np.clip(k + 1, 0, n_grid - 1)
        cl, c0, cr = cost[rows, kl], cost[rows, k], cost[rows, kr]
        interior = (k > 0) & (k < n_grid - 1) & np.isfinite(cl) & np.isfinite(cr)
        denom = cl - 2 * c0 + cr
        with np.errstate(invalid="ignore", divide="ignore"):
            shift = np.where(interior & (denom > 0), 0.5 * (cl - cr) / denom, 0.0)
        shift = np.clip(shift, -0.5, 0.5)
        dphi = np.where(shift > 0, phis[rows, kr] - phis[rows, k],
                        phis[rows, k] - phis[rows, kl])
        best.append(phis[rows, k] + shift * dphi)
    # (To, kappa) at the refined bearings, from all echoes (the second start only where
    # it is to be refined)
    bp = np.stack(best, axis=1)                                              # (B, 2)
    T, K = np.zeros((B, 2)), np.zeros((B, 2))
    T[:, :1], K[:, :1], _ = _node_profile(kind, tier, batch, bp[:, :1], r0, yc, use, usef,
                                          moving, cfg, detection_cost=False)
    idx = np.flatnonzero(second)
    if idx.size:
        T[idx, 1:], K[idx, 1:], _ = _node_profile(
            kind, tier, _take(batch, idx), bp[idx, 1:], r0[idx], yc[idx], use[idx],
            usef[idx], moving, cfg, detection_cost=False)
    starts = [np.stack([(T[:, i] + y0) / tau, bp[:, i], np.maximum(K[:, i], cfg.kappa_min_us)],
                       axis=-1) for i in (0, 1)]
    return starts[0], starts[1], second, arc


def _trilaterate(batch: SegmentBatch, y: Array, use: NDArray, cfg: FitConfig,
                 steps: int = 5) -> tuple[Array, NDArray[np.bool_]]:
    """A point landmark's position (B, 2) relative to the reference from the echoes'
    ranges alone (the delays neglected: a few mm), and where the directions from it to
    the transducers spread enough to fix it (:data:`_TRILATERATION_SPREAD`).

    Gauss-Newton steps on the ranges from the mean of the echoes' axis points (each
    echo's range along its transducer's axis): the beams tell the side of the path the
    point is on, which the ranges of a straight path cannot (a mirror image).
    """
    tau = M.us_per_m(cfg.module)
    u = use.astype(float)
    n = np.maximum(u.sum(1), 1.0)
    R = y / tau
    q = np.stack([(u * (batch.px + R * np.cos(batch.yaw))).sum(1) / n,
                  (u * (batch.py + R * np.sin(batch.yaw))).sum(1) / n], axis=1)
    for _ in range(steps):
        dx, dz = q[:, :1] - batch.px, q[:, 1:] - batch.py
        d = np.maximum(np.hypot(dx, dz), 1e-6)
        jx, jz, f = dx / d * u, dz / d * u, (d - R) * u
        a, b, c = (jx * jx).sum(1), (jx * jz).sum(1), (jz * jz).sum(1)
        gx, gz = (jx * f).sum(1), (jz * f).sum(1)
        det = np.maximum(a * c - b * b, 1e-12)
        q[:, 0] -= (c * gx - b * gz) / det
        q[:, 1] -= (a * gz - b * gx) / det
    # the directions' spread: the smaller eigenvalue of their mean outer product (from
    # the last step's Jacobian: the point moved by millimetres there)
    tr, det = (a + c) / n, (a * c - b * b) / (n * n)
    spread = 0.5 * tr - np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    ok = np.isfinite(q).all(1) & (spread > _TRILATERATION_SPREAD) & (use.sum(1) >= 3)
    return q, ok


_TRILATERATION_SPREAD = 2.5e-3
"""Smallest eigenvalue of the mean outer product of the unit directions from a
trilaterated point to the transducers (about spread^2 / 12 for directions spread
evenly over ``spread`` rad: 10 deg) for it to start a moving point fit. A long pass
spreads them by tens of degrees; a short one gives a poorly placed point (the
neglected delays, a few mm of range, move it by cm) whose refinement may end in
another minimum: at 2 deg, a corner seen for 0.9 s (0.2 m of travel at 3.3 m) came
out a wall, and the no-prior relocalization of that room drive waited 2 s more."""


def _path_start(tier: str, batch: SegmentBatch, y: Array, use: NDArray, cfg: FitConfig,
                start: Array) -> tuple[Array, NDArray[np.bool_]]:
    """A moving point fit's start from its path: the trilaterated point
    (:func:`_trilaterate`, its (To, kappa) profiled at its bearing) (B, 3), and where its
    -2 log-likelihood is below that of the bracket's ``start`` (B,); :func:`_solve`
    refines it there beside the bracket's start, the better converged fit winning.

    The bracket's nodes place the point at one range along each bearing (the segment's
    nearest echo's) and profile To as an offset, which holds while the path's ranges
    move together (a short or radial path). On a long pass they do not: a room corner
    seen for 20 s by seven ring transducers (nearest 1.3 m, last reading 3.5 m) was
    bracketed to the wrong place, fitted as a wall and a fifth of its echoes dropped as
    spikes, where the trilaterated point fits them all (the simulator's truth). Refined
    beside the bracket's start rather than instead of it: a start that looks better
    need not converge to the better fit."""
    B = batch.size
    tri = np.zeros((B, 3))
    better = np.zeros(B, dtype=bool)
    q, ok = _trilaterate(batch, y, use, cfg)
    idx = np.flatnonzero(ok)
    if idx.size == 0:
        return tri, better
    tau = M.us_per_m(cfg.module)
    sub, ys, us = _take(batch, idx), y[idx], use[idx]
    r = np.hypot(q[idx, 0], q[idx, 1])
    phi = np.arctan2(q[idx, 1], q[idx, 0])
    y0 = np.min(np.where(us, ys, np.inf), axis=1)
    yc = np.where(us, ys - y0[:, None], 0.0)
    T, K, _ = _node_profile("point", tier, sub, phi[:, None], r, yc, us, us.astype(float),
                            True, cfg, detection_cost=False)
    tri[idx] = np.stack([(T[:, 0] + y0) / tau, phi, np.maximum(K[:, 0], cfg.kappa_min_us)],
                        axis=-1)
    both = np.concatenate([start[idx], tri[idx]])
    F, _, _, _, s2 = _evaluate_s2("point", tier, both, _take(sub, np.tile(
        np.arange(idx.size), 2)), np.tile(ys, (2, 1)), np.tile(us, (2, 1)), None, cfg,
        want_derivs=False)
    full = F + _log_det(s2, np.tile(us, (2, 1)))
    better[idx] = full[idx.size:] < full[:idx.size]
    return tri, better


def _arc_start(kind: str, tier: str, batch: SegmentBatch, y: Array, use: NDArray,
               cfg: FitConfig
               ) -> tuple[Array, Array, NDArray[np.bool_], Array, NDArray[np.bool_]]:
    """:func:`_grid_start`'s outputs from the arc's edges where the arc is whole, and
    where it is (B,).

    A pan's echo arc ends where the delay ``kappa g(theta)`` reaches the detection limit
    L, at the same off-axis angle on both sides of the reflector: the start's bearing is
    the midpoint of the two edges, each halfway between the outermost echo and the next
    no-echo reading; kappa is ``L / g`` at the half-width (z = 0 there); To the
    readings' mean less the model's delays at that bearing. Whole: a stationary point
    segment with at least 3 used echoes, a no-echo reading within ``_ARC_EDGE_GAP``
    beyond each end and at most ``_ARC_DROPOUTS`` no-echo readings per echo among the
    echoes (missed detections near the edges are common; echoes scattered over the pan
    are not a whole arc). The other segments (moving, partial arcs at a scan's edge,
    occluded ends, coarse pans) get the grid bracket, as fitted alone.
    """
    B = batch.size
    none = np.zeros(B, dtype=bool)
    if kind != "point" or _is_moving(batch) or batch.ne_valid.shape[1] == 0:
        return (*_grid_start(kind, tier, batch, y, use, cfg), none)
    mod = cfg.module
    tau = M.us_per_m(mod)
    # angles relative to the beam axis of the (first) minimum-TOF echo, as the grid's
    k_min = np.argmin(np.where(use, y, np.inf), axis=1)
    centre = M._wrap_fast(batch.yaw[np.arange(B), k_min])
    rel = M._wrap_fast(batch.yaw - centre[:, None])
    lo = np.min(np.where(use, rel, np.inf), axis=1)
    hi = np.max(np.where(use, rel, -np.inf), axis=1)
    nrel = M._wrap_fast(batch.ne_yaw - centre[:, None])
    nv = batch.ne_valid
    n_lo = np.max(np.where(nv & (nrel < lo[:, None]), nrel, -np.inf), axis=1)
    n_hi = np.min(np.where(nv & (nrel > hi[:, None]), nrel, np.inf), axis=1)
    inside = np.sum(nv & (nrel >= lo[:, None]) & (nrel <= hi[:, None]), axis=1)
    n_use = use.sum(1)
    whole = ((inside <= _ARC_DROPOUTS * n_use) & (lo - n_lo <= _ARC_EDGE_GAP)
             & (n_hi - hi <= _ARC_EDGE_GAP) & (n_use >= 3))
    if not whole.any():
        return (*_grid_start(kind, tier, batch, y, use, cfg), none)
    iw = np.flatnonzero(whole)
    edge_lo, edge_hi = 0.5 * (lo[iw] + n_lo[iw]), 0.5 * (hi[iw] + n_hi[iw])
    bp = centre[iw] + 0.5 * (edge_lo + edge_hi)
    # kappa from the arc's half-width: detected while kappa g(theta) is below the
    # detection limit (z = 0 at the edges)
    lg_edge = M.beam_log_factor(0.5 * (edge_hi - edge_lo), tier, mod, derivative=False)[2]
    k_edge = mod.detection_limit_us * np.exp(-lg_edge)
    # To: the readings' mean less the model's delays there (stationary: the range
    # offsets are zero)
    all_ = iw.size == B
    yaw_w, y_w, use_w = (batch.yaw, y, use) if all_ else (batch.yaw[iw], y[iw], use[iw])
    g = M.beam_log_factor(_angle_diff(bp[:, None], yaw_w), tier, mod, derivative=False)[0]
    g *= (k_edge * np.exp(0.5 * M.sigma_a(mod) ** 2))[:, None]             # the delays
    T0 = np.einsum("bn,bn->b", use_w.astype(float), y_w - g) / n_use[iw]
    start = np.zeros((B, 3))
    start2 = np.zeros((B, 3))
    second = np.zeros(B, dtype=bool)
    arc = np.stack([centre + lo, centre + hi], axis=-1)
    start[iw] = np.stack([T0 / tau, bp, np.maximum(k_edge, cfg.kappa_min_us)], axis=-1)
    ig = np.flatnonzero(~whole)
    if ig.size:
        s1, s2, sec, a = _grid_start(kind, tier, _take(batch, ig), y[ig], use[ig], cfg)
        start[ig], start2[ig], second[ig], arc[ig] = s1, s2, sec, a
    return start, start2, second, arc, whole


_ARC_DROPOUTS = 0.5
"""Most no-echo readings among a whole arc's echoes (a fraction of its echoes)."""

_ARC_EDGE_GAP = np.deg2rad(5.0)
"""Largest gap between an arc's outermost echo and the no-echo reading bounding it for
:func:`_arc_start` to take the edge between them (coarser pans: the grid)."""


_EARLY_TOLERANCE = 100.0

STOP_CHECK_ITER = 4
"""Steps of a refinement from another tier's fit before it may be given up as hopeless
(``stop_above`` of :func:`fit_batch`). Measured on the 200,000-reading rotation of
benchmarks/bench_fit.py section 4: from the 4th step on, refinements still more than
200 above their bar came down by at most 158 more (all ended 186 or more above it)."""

_LAMBDA0 = 1e-1
"""Initial Levenberg-Marquardt damping (a fraction of the Fisher matrix's diagonal)."""

_GRID_BLOCK = 1 << 16
"""Largest temporary array of the grid bracket (elements)."""


_STATE_FIELDS = ("p", "converged", "F", "H", "e", "s2", "pending")


@dataclass
class _State:
    """A fit's state at its parameters: objective F (B,) (without the variances'
    log-determinant), Fisher matrix H (B, 3, 3), standardised residuals e (B, Nd) and
    the TOF variances s2 (B, Nd) they were computed with; ``pending`` (B, 3): the
    Newton step still to go where the steps ran out before convergence (zero where
    not known: ``FitConfig.final_derivatives`` off)."""

    p: Array
    converged: NDArray[np.bool_]
    F: Array
    H: Array
    e: Array
    s2: Array
    pending: Array

    def full_cost(self, use: NDArray) -> Array:
        """-2 log-likelihood (B,) with the TOF variances' log-determinant."""
        return self.F + _log_det(self.s2, use)

    def take(self, idx: NDArray[np.int64]) -> _State:
        """The state of segments ``idx``."""
        return _State(*(getattr(self, f).take(idx, axis=0) for f in _STATE_FIELDS))

    def put(self, idx: NDArray[np.int64], other: _State) -> None:
        """Replace segments ``idx`` by ``other``'s (same width)."""
        for name in _STATE_FIELDS:
            getattr(self, name)[idx] = getattr(other, name)


def _log_det(s2: Array, use: NDArray) -> Array:
    """The TOF variances' share of the -2 log-likelihood (B,): the sum of ln(2 pi s2)
    over the used echoes (what the objective F leaves out)."""
    return np.where(use, np.log(2.0 * np.pi * s2), 0.0).sum(1)


_STEP_MAX = np.array([0.17, 3.0])
"""Largest step of (phi [rad], log kappa) in one Fisher-scoring step (10 deg, x20)."""
_STEP_MIN = -_STEP_MAX


def _refine(kind: str, tier: str, p: Array, batch: SegmentBatch, y: Array, use: NDArray,
            cfg: FitConfig, rounds: int, stop_above: Array | None = None) -> _State:
    """Damped Fisher scoring from ``p``; a step is taken only if it lowers the objective.

    A segment stops when its Newton decrement g^T H^-1 g (the expected decrease of the
    objective) falls below ``cfg.tolerance``; stopped segments are frozen for the rest
    of the round and left out of the remaining iterations, their damping kept (were it
    grown at the other segments' steps, a segment's next round would depend on the
    batch it shares; only the float32 passes' rounding does). ``stop_above`` (B,): a segment
    whose -2 log-likelihood (with the round's variances) still exceeds this after
    :data:`STOP_CHECK_ITER` steps (or at any later step) is given up (frozen for good,
    not converged; see :func:`fit_batch`). Returns the state at the result (variances
    of the last round's start: the weights a round's steps were taken with).
    """
    B = p.shape[0]
    p = p.copy()
    lam = np.full(B, _LAMBDA0)
    done = np.zeros(B, dtype=bool)
    given_up = np.zeros(B, dtype=bool)
    for rnd in range(rounds):
        # variances from the current delays, fixed for this round
        F, grad, H, E, s2 = _evaluate_s2(kind, tier, p, batch, y, use, None, cfg)
        # rounds before the last stop early: the next round moves the weights anyway
        tol = cfg.tolerance * (1.0 if rnd == rounds - 1 else _EARLY_TOLERANCE)
        done = given_up.copy()
        if stop_above is not None:      # the objective less the full cost
            stop_F = stop_above - _log_det(s2, use)
        act = np.arange(B)
        sub, ys, us, s2s = batch, y, use, s2
        for it in range(cfg.iterations):
            # the last step of all: its point's objective, not its derivatives (nothing
            # steps from there; the covariance keeps the Fisher matrix of the step's start)
            last = rnd == rounds - 1 and it == cfg.iterations - 1 and not cfg.final_derivatives
            # steps in (r, phi, log kappa): the delays scale with kappa and the detection
            # margin with log kappa, so this is where the objective is nearly quadratic
            # (row gathers by ndarray.take: a third of the indexing's cost)
            kap = p[:, 2].take(act)
            ga = grad.take(act, axis=0)
            ga[:, 2] *= kap
            Ha = H.take(act, axis=0)
            Ha[:, 2, :] *= kap[:, None]
            Ha[:, :, 2] *= kap[:, None]
            dg = _einsum("bkk->bk", Ha)                   # a view: damp in place
            dg += lam[act, None] * np.maximum(dg, 1e-12)
            delta = _solve3(Ha, -ga) if cfg.float32 else _solve_pivoted(Ha, -ga)
            delta = np.where(np.isfinite(delta), delta, 0.0)
            # converged where the expected decrease (Newton decrement) is negligible
            done[act[-_einsum("bk,bk->b", ga, delta) < tol]] = True
            if stop_above is not None and (rnd > 0 or it >= STOP_CHECK_ITER):
                hopeless = act[F[act] > stop_F[act]]
                done[hopeless] = True
                given_up[hopeless] = True
            keep = np.flatnonzero(~done[act])
            if keep.size == 0:
                break
            if keep.size < 0.7 * act.size:      # compact to the active segments
                act, delta = act[keep], delta.take(keep, axis=0)
                sub, ys, us = _take(sub, keep), ys.take(keep, axis=0), us.take(keep, axis=0)
                s2s = s2s.take(keep, axis=0)
            # keep steps physical: bearing moves at most 10 deg per step, kappa x20
            step = delta[:, 1:]
            np.minimum(np.maximum(step, _STEP_MIN, out=step), _STEP_MAX, out=step)
            q = p.take(act, axis=0)
            q[:, :2] += delta[:, :2]
            q[:, 0] = np.maximum(q[:, 0], 1e-3)
            q[:, 2] = np.maximum(q[:, 2] * np.exp(delta[:, 2]), cfg.kappa_min_us)
            if cfg.follow_variances:
                # the step is judged with the current variances; the state at the new
                # point carries its own (iteratively reweighted), from the same pass
                Fa, Fq, gq, Hq, eq, s2q = _evaluate_core(kind, tier, q, sub, ys, us, None,
                                                         cfg, not last, s2_other=s2s)
            else:
                Fq, gq, Hq, eq = _evaluate(kind, tier, q, sub, ys, us, s2s, cfg, not last)
                Fa, s2q = Fq, s2s
            ok = np.isfinite(Fa) & (Fa <= F[act]) & ~done[act]
            if act.size == B and ok.all():
                # every segment's step taken: the new state as it is (no copies)
                p, F, E = q, Fq.copy(), eq
                if not last:
                    grad, H = gq, Hq
                if cfg.follow_variances:
                    s2 = s2s = s2q
            else:
                # (every step taken: the rows as they are, no masks)
                ia, tk = (act, slice(None)) if ok.all() else (act[ok], ok)
                p[ia], F[ia], E[ia] = q[tk], Fq[tk], eq[tk]
                if not last:
                    grad[ia], H[ia] = gq[tk], Hq[tk]
                if cfg.follow_variances:
                    s2[ia] = s2q[tk]
                    s2s = s2s.copy() if s2s is s2 else s2s
                    s2s[tk] = s2q[tk]
            # (a segment stopped at this step, or before and not yet compacted out, keeps
            # its damping: grown at the others' steps it made its next round depend on
            # the batch it shares)
            stopped = done[act]
            lam[act] = np.where(stopped, lam[act],
                                np.where(ok, np.maximum(lam[act] / 4.0, 1e-9),
                                         np.minimum(lam[act] * 8.0, 1e9)))
            done[act[~ok & (lam[act] >= 1e9)]] = True
    pending = np.zeros((B, 3))
    if cfg.final_derivatives:
        # the Newton step from the result (derivatives evaluated there): how far the
        # converged fit still is, where the steps ran out before convergence
        open_ = np.flatnonzero(~done)
        if open_.size:
            step = -np.einsum("bij,bj->bi", _covariance(H[open_]), grad[open_])
            step = np.where(np.isfinite(step), step, 0.0)
            small = -np.einsum("bk,bk->b", grad[open_], step) < cfg.tolerance
            done[open_[small]] = True
            pending[open_[~small]] = step[~small]
    return _State(p, done & ~given_up, F, H, E, s2, pending)


def _solve(kind: str, tier: str, batch: SegmentBatch, y: Array, use: NDArray, cfg: FitConfig,
           start_fit: BatchFit | None = None, stop_above: Array | None = None
           ) -> tuple[_State, Array]:
    """Grid bracket + refinement (from a second start where the grid is ambiguous), or
    refinement from another model's fit of the same segments (``start_fit``); given up
    above ``stop_above`` (see :func:`_refine`)."""
    if start_fit is not None:
        st = _refine_any(kind, tier, start_fit.local.copy(), batch, y, use, cfg, stop_above)
        return st, start_fit.arc.copy()
    if cfg.start == "arc":
        start, start2, second, arc, whole = _arc_start(kind, tier, batch, y, use, cfg)
    else:
        start, start2, second, arc = _grid_start(kind, tier, batch, y, use, cfg)
        whole = np.zeros(batch.size, dtype=bool)
    if kind == "point" and _is_moving(batch):
        # the path's start, where it looks better, is refined as the second start (it
        # takes the place of the bracket's own second start there)
        tri, looks = _path_start(tier, batch, y, use, cfg, start)
        if looks.any():
            start2 = start2.copy()
            start2[looks] = tri[looks]
            second = second | looks
    cfg_arc = cfg if cfg.arc_iterations is None else replace(cfg,
                                                              iterations=cfg.arc_iterations)
    sa = stop_above
    idx = np.flatnonzero(second)
    st2: _State | None = None
    plain = cfg_arc is cfg or not whole.any()
    if plain and idx.size:
        # the second starts refined with the first ones, in the same passes: their
        # lockstep tails no longer run after the first's (a row's steps are its own but
        # for the float32 passes' rounding, see :func:`_refine`)
        both = np.concatenate([np.arange(batch.size), idx])
        st_all = _refine_any(kind, tier, np.concatenate([start, start2[idx]]),
                             _take(batch, both), y[both], use[both], cfg,
                             None if sa is None else sa[both])
        st = st_all.take(both[:batch.size])
        st2 = st_all.take(batch.size + np.arange(idx.size))
    elif plain:
        st = _refine_any(kind, tier, start, batch, y, use, cfg, sa)
    elif whole.all():
        st = _refine_any(kind, tier, start, batch, y, use, cfg_arc, sa)
    else:       # the arc's starts and the grid's take their own numbers of steps
        iw, ig = np.flatnonzero(whole), np.flatnonzero(~whole)
        st_w = _refine_any(kind, tier, start[iw], _take(batch, iw), y[iw], use[iw], cfg_arc,
                           None if sa is None else sa[iw])
        st_g = _refine_any(kind, tier, start[ig], _take(batch, ig), y[ig], use[ig], cfg,
                           None if sa is None else sa[ig])
        st = _State(*(np.empty((batch.size, *getattr(st_w, f).shape[1:]),
                               dtype=getattr(st_w, f).dtype) for f in _STATE_FIELDS))
        st.put(iw, st_w)
        st.put(ig, st_g)
    if idx.size:
        if st2 is None:
            st2 = _refine_any(kind, tier, start2[idx], _take(batch, idx), y[idx], use[idx],
                              cfg, None if sa is None else sa[idx])
        f1 = st.take(idx).full_cost(use[idx])
        f2 = st2.full_cost(use[idx])
        better = np.flatnonzero(f2 < f1)
        if better.size:
            st.put(idx[better], st2.take(better))
    return st, arc


def _refine_any(kind: str, tier: str, p: Array, batch: SegmentBatch, y: Array, use: NDArray,
                cfg: FitConfig, stop_above: Array | None = None) -> _State:
    """The refinement ``cfg.method`` asks for (see :class:`FitConfig`); ``stop_above``:
    see :func:`_refine` (the full method only)."""
    if cfg.method == "full":
        return _refine(kind, tier, p, batch, y, use, cfg, cfg.rounds, stop_above)
    nodet = replace(cfg, detection=False)
    if tier == "waveform":          # not linear in kappa: the full method, echoes only
        return _refine(kind, tier, p, batch, y, use, nodet, nodet.rounds)
    return _profile_refine(kind, tier, p, batch, y, use, nodet)


def _profile_refine(kind: str, tier: str, p: Array, batch: SegmentBatch, y: Array,
                    use: NDArray, cfg: FitConfig) -> _State:
    """Bearing refined on the profile (over To, kappa) of the echoes' weighted LS cost.

    Weights from the jitter model at the start ``p`` (held fixed); ``cfg.profile_evals``
    parabolas through 3-point stencils around the current bearing (half-width
    ``cfg.profile_step_deg``, then a quarter of the last unless the minimum lay at the
    stencil's edge; a step moves at most one half-width, to the lower side where the
    stencil is not convex); (To, kappa) solved at the result; then one model pass
    (no detection terms: ``cfg.detection`` is off) for the residuals, the objective and
    the Gauss-Newton matrix. ``converged``: the last parabola's minimum lay inside its
    stencil. Every stencil's best node is kept if the parabola's vertex is not lower,
    so the objective cannot rise along the way.
    """
    mod = cfg.module
    tau = M.us_per_m(mod)
    B = p.shape[0]
    moving = _is_moving(batch)
    with np.errstate(invalid="ignore"):
        y0 = np.nanmin(np.where(use, y, np.inf), axis=1)
    y0 = np.where(np.isfinite(y0), y0, 0.0)
    yc = np.where(use, y - y0[:, None], 0.0)
    # TOF weights relative to the on-axis variance (what _node_profile's cost scales by)
    s2 = _variances(kind, tier, p, batch, cfg)
    wt = np.where(use, float(M.tof_variance_us2(0.0, mod)) / s2, 0.0)
    phi = p[:, 1].copy()
    r0 = p[:, 0].copy()
    h = np.full(B, np.deg2rad(cfg.profile_step_deg))
    unit = np.array([-1.0, 0.0, 1.0])
    inside = np.zeros(B, dtype=bool)
    best_phi = phi.copy()
    best_c = np.full(B, np.inf)
    for _ in range(cfg.profile_evals):
        phis = phi[:, None] + h[:, None] * unit[None, :]
        T, K, c = _node_profile(kind, tier, batch, phis, r0, yc, use, wt, moving, cfg)
        c = np.where(np.isfinite(c), c, np.inf)
        cl, c0, cr = c[:, 0], c[:, 1], c[:, 2]
        kb = np.argmin(c, axis=1)
        cb = c[np.arange(B), kb]
        better = cb < best_c
        best_phi = np.where(better, phis[np.arange(B), kb], best_phi)
        best_c = np.where(better, cb, best_c)
        denom = cl - 2.0 * c0 + cr
        with np.errstate(invalid="ignore", divide="ignore"):
            shift = np.where(denom > 0, 0.5 * (cl - cr) / denom,
                             np.where(cl < cr, -1.0, 1.0))
        shift = np.where(np.isfinite(shift), np.clip(shift, -1.0, 1.0), 0.0)
        inside = np.abs(shift) < 1.0
        phi = phi + shift * h
        if moving:     # the geometry's range follows (a fixed-point iteration)
            r0 = np.maximum((T[np.arange(B), kb] + y0) / tau, 1e-3)
        h = np.where(inside, 0.25 * h, h)
    # (To, kappa) at the last vertex; the best stencil node where that is lower
    T, K, c = _node_profile(kind, tier, batch, phi[:, None], r0, yc, use, wt, moving, cfg)
    worse = ~(c[:, 0] <= best_c)
    if worse.any():
        phi = np.where(worse, best_phi, phi)
        T, K, _ = _node_profile(kind, tier, batch, phi[:, None], r0, yc, use, wt, moving,
                                cfg)
    q = np.stack([np.maximum((T[:, 0] + y0) / tau, 1e-3), phi,
                  np.maximum(K[:, 0], cfg.kappa_min_us)], axis=-1)
    q = np.where(np.isfinite(q), q, p)
    F, _, H, e, s2q = _evaluate_s2(kind, tier, q, batch, y, use, None, cfg)
    return _State(q, inside, F, H, e, s2q, np.zeros((B, 3)))


def _cofactors3(A: Array) -> tuple[tuple[Array, ...], Array, Array]:
    """Cofactors (c00, c01, c02, c11, c12, c22), determinants and traces (B,) of
    symmetric 3x3 matrices A (B, 3, 3) (its upper triangle is read)."""
    a00, a01, a02 = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    a11, a12, a22 = A[:, 1, 1], A[:, 1, 2], A[:, 2, 2]
    c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * c00 + a01 * c01 + a02 * c02
    return (c00, c01, c02, c11, c12, c22), det, a00 + a11 + a22


def _solve3(A: Array, b: Array) -> Array:
    """Solutions x (B, 3) of symmetric 3x3 systems A x = b by cofactors (vectorised;
    LAPACK's batched solve costs ~1 us per system); the ill-conditioned ones (smallest
    eigenvalue below 1e-10 of the largest, from det / trace^3) with pivoting
    (:func:`_solve_pivoted`). Each row's solution depends on its own system only."""
    (c00, c01, c02, c11, c12, c22), det, tr = _cofactors3(A)
    good = (det > 1e-10 * tr ** 3) & (tr > 0)
    b0, b1, b2 = b[:, 0], b[:, 1], b[:, 2]
    x = np.stack([c00 * b0 + c01 * b1 + c02 * b2, c01 * b0 + c11 * b1 + c12 * b2,
                  c02 * b0 + c12 * b1 + c22 * b2], axis=-1)
    x /= np.where(good, det, 1.0)[:, None]
    bad = np.flatnonzero(~good)
    if bad.size:
        x[bad] = _solve_pivoted(A[bad], b[bad])
    return x


def _solve_pivoted(A: Array, b: Array) -> Array:
    """Solutions x (B, k) of systems A (B, k, k) x = b (B, k) by LAPACK's pivoted LU;
    the singular ones by least squares, row by row, so a singular system leaves the
    others' solutions as they are."""
    try:
        return np.asarray(np.linalg.solve(A, b[..., None])[..., 0], dtype=float)
    except np.linalg.LinAlgError:
        pass
    x = np.empty(b.shape)
    for i in range(b.shape[0]):
        try:
            x[i] = np.linalg.solve(A[i], b[i])
        except np.linalg.LinAlgError:
            x[i] = np.linalg.lstsq(A[i], b[i], rcond=None)[0]
    return x


def _covariance(H: Array) -> Array:
    """Inverse of Fisher matrices (B, 3, 3), finite even when singular (huge variance).

    Well-conditioned ones (smallest eigenvalue above 1e-12 of the largest, from
    det / trace^3) by cofactors; the rest by eigendecomposition with a floor.
    """
    Hs = 0.5 * (H + np.swapaxes(H, -1, -2))
    Hs = np.where(np.isfinite(Hs), Hs, 0.0)
    (c00, c01, c02, c11, c12, c22), det, tr = _cofactors3(Hs)
    good = (det > 1e-12 * tr ** 3) & (tr > 0)
    inv_det = 1.0 / np.where(good, det, 1.0)
    out = np.stack([c00, c01, c02, c01, c11, c12, c02, c12, c22], axis=-1).reshape(-1, 3, 3)
    out *= inv_det[:, None, None]
    bad = np.flatnonzero(~good)
    if bad.size:
        w, V = np.linalg.eigh(Hs[bad])
        floor = np.maximum(w.max(axis=-1, keepdims=True) * 1e-14, 1e-30)
        inv = np.minimum(1.0 / np.maximum(w, floor), 1e30)
        out[bad] = np.einsum("bij,bj,bkj->bik", V, inv, V)
    return out


def fit_batch(batch: SegmentBatch, kind: str = "point", tier: str = "gauss",
              config: FitConfig | None = None, offsets_us: Array | None = None,
              use: NDArray[np.bool_] | None = None, start: BatchFit | None = None,
              rows: NDArray[np.int64] | None = None, stop_above: Array | None = None
              ) -> BatchFit:
    """Fit one landmark model to each of ``B`` segments.

    Parameters
    ----------
    batch : padded readings (see :func:`pack_segments`).
    kind : ``"point"`` (x, y, kappa) or ``"line"`` (rho, alpha, kappa).
    tier : model tier, one of :data:`sonarloc.fit.model.TIERS`.
    config : fitter settings (speed of sound, detection model, ...).
    offsets_us : (B, Nd) known additive offsets of readings, subtracted.
    use : (B, Nd) echoes to use (default: all valid).
    start : another model's fit of the same segments (same kind): refine from it instead
        of bracketing on the grid (for a second tier, whose optimum is near the first's).
    rows : fit only these segments of ``batch`` (the result has one row per entry, as
        ``fit_batch(_take(batch, rows), ...)``, without copying them out first; the
        other arguments then refer to the selected segments).
    stop_above : (B,) -2 log-likelihood above which a segment's refinement is given up
        after :data:`STOP_CHECK_ITER` steps: another tier that far above the bar it is
        to beat is hopeless (:func:`sonarloc.fit.select.choose_tier`); its result is
        where it stopped, ``converged`` False. Spikes found there are dropped and the
        segment refitted (then to the end) as usual.

    Returns
    -------
    BatchFit with local parameters and covariance; segments with fewer than 3 echoes
    are returned as fitted on what they have (their status is decided by the caller).
    """
    if kind not in M.KINDS:
        raise ValueError(f"`kind` must be 'point' or 'line', got {kind!r}")
    if tier not in M.TIERS:
        raise ValueError(f"`tier` must be one of {', '.join(M.TIERS)}; got {tier!r}")
    cfg = config or FitConfig()
    if start is not None and start.kind != kind:
        raise ValueError(f"`start` is a {start.kind} fit, expected {kind}")
    pick = np.arange(batch.size) if rows is None else np.asarray(rows, dtype=np.int64)
    B = pick.size
    n_d = batch.valid[pick].sum(1)
    n_n = batch.ne_valid[pick].sum(1)
    # float32 passes cost about half per reading: the fixed per-chunk cost weighs twice
    chunks = _plan_chunks(n_d, n_n, cfg.chunk_readings,
                          _CALL_OVERHEAD_READINGS * (2 if cfg.float32 else 1))
    # chunks of segments of similar size, each trimmed to its own widest segment: little
    # work on padding, arrays of a bounded size
    out_local = np.zeros((B, 3))
    out_cov = np.zeros((B, 3, 3))
    out_vec = {name: np.zeros(B) for name in ("cost", "chi2", "robust_cost")}
    out_n = np.zeros(B, dtype=np.int64)
    out_conv = np.zeros(B, dtype=bool)
    out_arc = np.zeros((B, 2))
    Nd = batch.px.shape[1]
    out_used = np.zeros((B, Nd), dtype=bool)
    out_resid = np.zeros((B, Nd))
    for idx in chunks:
        wd = max(int(n_d[idx].max()), 1)
        wn = max(int(n_n[idx].max()), 1)
        sub = _take(batch, pick[idx], wd, wn)
        part = _fit_direct(
            sub, kind, tier, cfg,
            None if offsets_us is None else offsets_us[idx][:, :wd],
            None if use is None else use[idx][:, :wd],
            None if start is None else _trim_fit(start.take(idx), wd),
            None if stop_above is None else stop_above[idx])
        out_local[idx], out_cov[idx] = part.local, part.cov
        for name in out_vec:
            out_vec[name][idx] = getattr(part, name)
        out_n[idx], out_conv[idx], out_arc[idx] = part.n_used, part.converged, part.arc
        out_used[idx, :wd], out_resid[idx, :wd] = part.used, part.resid
    return BatchFit(kind, tier, out_local, out_cov, out_vec["cost"], out_vec["chi2"], out_n,
                    out_used, out_resid, out_arc, out_conv, out_vec["robust_cost"])


_CALL_OVERHEAD_READINGS = 2000
"""Fixed cost of fitting one chunk (Python and numpy call overhead), in padded readings."""


def _plan_chunks(n_d: NDArray[np.int64], n_n: NDArray[np.int64], chunk_readings: int,
                 overhead: int = _CALL_OVERHEAD_READINGS
                 ) -> list[NDArray[np.int64]]:
    """Split segments into chunks of similar size (indices), minimising the padded work.

    Segments are sorted by (echoes, no-echo readings); a chunk is a run of the sorted
    order of padded size ``count * (max echoes + max no-echo)`` (cut further to stay
    below ``chunk_readings``) and costs that plus a fixed per-call overhead. The best
    split into runs is found by dynamic programming over the distinct echo counts.
    """
    B = n_d.size
    if B == 0:
        return [np.arange(0)]
    order = np.lexsort((n_n, n_d))
    nd_s, nn_s = n_d[order], n_n[order]
    # groups of equal echo count (boundaries in the sorted order)
    starts = np.flatnonzero(np.r_[True, nd_s[1:] != nd_s[:-1]])
    ends = np.r_[starts[1:], B]
    G = starts.size
    w_d = np.maximum(nd_s[ends - 1], 1).astype(float)                   # group widths
    w_n = np.maximum(np.maximum.reduceat(nn_s, starts), 1).astype(float)
    cum = np.r_[0, ends].astype(float)                                  # segments before
    best = np.zeros(G + 1)
    prev = np.zeros(G + 1, dtype=np.int64)
    if G <= 256:
        # cost of every run of groups i..j (i <= j) at once: (G, G), upper triangle
        i_, j_ = np.arange(G)[:, None], np.arange(G)[None, :]
        mn_all = np.maximum.accumulate(np.where(j_ >= i_, w_n[None, :], 0.0), axis=1)
        padded = (cum[1:][None, :] - cum[:-1][:, None]) * (w_d[None, :] + mn_all)
        pieces = np.maximum(np.ceil(padded / chunk_readings), 1.0)
        run_cost = padded + pieces * overhead
        for j in range(1, G + 1):
            cost = best[:j] + run_cost[:j, j - 1]
            i = int(np.argmin(cost))
            best[j], prev[j] = cost[i], i
    else:
        for j in range(1, G + 1):
            # runs of groups i..j-1 (i = 0..j-1)
            mn = np.maximum.accumulate(w_n[:j][::-1])[::-1]
            count = cum[j] - cum[:j]
            padded_j = count * (w_d[j - 1] + mn)
            pieces_j = np.maximum(np.ceil(padded_j / chunk_readings), 1.0)
            cost = best[:j] + padded_j + pieces_j * overhead
            i = int(np.argmin(cost))
            best[j], prev[j] = cost[i], i
    runs = []
    j = G
    while j > 0:
        i = int(prev[j])
        runs.append((int(starts[i]), int(ends[j - 1])))
        j = i
    chunks = []
    for a, b in reversed(runs):
        width = int(max(nd_s[b - 1], 1) + max(nn_s[a:b].max(), 1)) + 2
        per = max(chunk_readings // width, 1)
        for c in range(a, b, per):
            chunks.append(order[c:min(c + per, b)])
    return chunks


def _trim_fit(fit: BatchFit, wd: int) -> BatchFit:
    return BatchFit(fit.kind, fit.tier, fit.local, fit.cov, fit.cost, fit.chi2, fit.n_used,
                    fit.used[:, :wd], fit.resid[:, :wd], fit.arc, fit.converged,
                    fit.robust_cost)


def _fit_direct(batch: SegmentBatch, kind: str, tier: str, cfg: FitConfig,
                offsets_us: Array | None, use: NDArray[np.bool_] | None,
                start: BatchFit | None, stop_above: Array | None = None) -> BatchFit:
    """:func:`fit_batch` on one chunk."""
    mod = cfg.module
    y = batch.tof_us - 0.5 * mod.count_period_us
    if offsets_us is not None:
        y = y - np.where(batch.valid, offsets_us, 0.0)
    use0 = batch.valid & np.isfinite(y)
    if use is not None:
        use0 = use0 & use
    n_avail = use0.sum(1)
    y = np.where(use0, y, 0.0)
    st, arc = _solve(kind, tier, batch, y, use0, cfg, start, stop_above)
    # spikes: drop the worst echoes beyond outlier_sigma, then fit those segments again
    bad = use0 & (np.abs(st.e) > cfg.outlier_sigma)
    if bad.any():
        max_drop = np.floor(cfg.max_outlier_fraction * use0.sum(1)).astype(int)
        order = np.argsort(-np.abs(np.where(bad, st.e, 0.0)), axis=1)
        rank = np.empty_like(order)
        np.put_along_axis(rank, order, np.arange(order.shape[1])[None, :].repeat(
            order.shape[0], 0), axis=1)
        drop = bad & (rank < max_drop[:, None])
        if drop.any():
            use0 = use0 & ~drop
            idx = np.flatnonzero(drop.any(1))
            sub = _take(batch, idx)
            st2, _ = _solve(kind, tier, sub, y[idx], use0[idx], cfg)
            st2, use0[idx] = _readmit(kind, tier, st2, sub, y[idx], use0[idx], drop[idx], cfg)
            st.put(idx, st2)
    p, conv, F, H = st.p, st.converged, st.F, st.H
    e = np.asarray(st.e, dtype=float)
    chi2 = (e * e).sum(1)
    # full -2 log-likelihood (with the variances' log-determinant) to compare models
    F = st.full_cost(use0)
    n_used = use0.sum(1)
    dof = np.maximum(n_used - 3, 1)
    inflate = np.maximum(chi2 / dof, 1.0)
    cov = _covariance(H) * inflate[:, None, None]
    # not converged: the mean squared error adds the (expected) distance to the optimum
    cov += st.pending[:, :, None] * st.pending[:, None, :]
    robust = F + cfg.outlier_sigma ** 2 * (n_avail - n_used)
    return BatchFit(kind, tier, p, cov, F, chi2, n_used, use0, e, arc, conv, robust)


def _readmit(kind: str, tier: str, st: _State, batch: SegmentBatch, y: Array, use: NDArray,
             dropped: NDArray, cfg: FitConfig) -> tuple[_State, NDArray]:
    """The echoes ``dropped`` as spikes by a first fit that the refit without them
    (``st``, on echoes ``use``) explains (within ``cfg.outlier_sigma``) taken back, the
    fit refined from there; kept where the robust cost (-2 log-likelihood plus
    ``outlier_sigma**2`` per dropped echo, as :func:`fit_batch` reports it) falls.

    A first fit gone to a wrong optimum drops the echoes it misfits worst, and those
    need not be spikes: on a moving ring's 300 s drive (the simulator's truth, true
    poses) 1781 of the 1836 echoes dropped in single-reflector segments were the
    segment's own reflector's, often the first or last of a segment whose refit then
    explained them to a few us. Returns the state and the echoes used.
    """
    e = _evaluate_s2(kind, tier, st.p, batch, y, dropped, None, cfg, want_derivs=False)[3]
    back = dropped & (np.abs(e) <= cfg.outlier_sigma)
    rows = np.flatnonzero(back.any(1))
    if rows.size == 0:
        return st, use
    use_new = use[rows] | back[rows]
    new = _refine_any(kind, tier, st.p[rows], _take(batch, rows), y[rows], use_new, cfg)
    # the robust costs differ by the echoes' terms and the penalty of those taken back
    gain = (st.take(rows).full_cost(use[rows]) - new.full_cost(use_new)
            + cfg.outlier_sigma ** 2 * back[rows].sum(1))
    keep = np.flatnonzero(np.isfinite(gain) & (gain > 0.0))
    if keep.size:
        st = st.take(np.arange(st.p.shape[0]))
        st.put(rows[keep], new.take(keep))
        use = use.copy()
        use[rows[keep]] = use_new[keep]
    return st, use


def _take(batch: SegmentBatch, idx: NDArray[np.int64], wd: int | None = None,
          wn: int | None = None) -> SegmentBatch:
    """The segments ``idx`` of ``batch``; with ``wd`` / ``wn``, only the first ``wd``
    echo and ``wn`` no-echo columns (copied, not the whole rows)."""
    d, n = slice(wd), slice(wn)

    def rows(a: NDArray[Any], cols: slice) -> NDArray[Any]:
        # whole rows: np.take's gather (a third faster than the indexing's)
        return a.take(idx, axis=0) if cols.stop is None else a[idx, cols]

    sub = SegmentBatch(rows(batch.px, d), rows(batch.py, d), rows(batch.yaw, d),
                       rows(batch.tof_us, d), rows(batch.valid, d), rows(batch.ne_px, n),
                       rows(batch.ne_py, n), rows(batch.ne_yaw, n), rows(batch.ne_valid, n),
                       batch.ref_xy.take(idx, axis=0), batch.ref_yaw.take(idx, axis=0),
                       batch.ref_t_s.take(idx, axis=0))
    # what the batch has worked out holds for its segments: a stationary batch's are
    # stationary, float32 angles are the rows of its own (the fitter's steps take
    # subsets of the active segments every few iterations)
    known = batch.__dict__
    if known.get("moving") is False:
        sub.__dict__["moving"] = False
    for name, cols in (("yaw32", d), ("ne_yaw32", n)):
        if name in known:
            sub.__dict__[name] = rows(known[name], cols)
    return sub

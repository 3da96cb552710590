"""Reading-level fusion of many closed segments at once: the batch replay's fast path.

The Localizer fuses a segment's readings one segment at a time
(:meth:`~sonarloc.localize.localizer.Localizer.add_landmark`): the transducer poses'
odometry chain, the candidates among the map features, each candidate's readings
linearised through the forward model, screened and gated, the winner's stacked update
iterated. Almost all of that depends on the belief only through the point it is
linearised at, and in a replay the belief at a segment's reference time is known in
advance to within millimetres: the latest belief moved by the odometry since
(``map→odom ⊕ odom pose``). :class:`BatchFuser` does that work in two levels:
:meth:`~BatchFuser.linearize` for many segments in one pass of numpy calls (chains,
candidates and rivals, the forward model and measurement covariances at those
predicted beliefs), then :meth:`~BatchFuser.decide` for a few at a time at the beliefs
the latest one predicts (screening, rivals, the stacked gate, the winner), which leaves
each segment as its association and a reduced update of at most three rows
(:class:`Prepared`, :class:`~sonarloc.localize.echoes.Compressed`). The caller
(:class:`~sonarloc.localize.offline.OfflinePipeline`) applies the reduced updates in
time order to the true belief (:func:`reduced_update`), which moves the prediction by
``H (x - x0)`` exactly (linear in the offset), after re-checking the winner's screening
there (:meth:`Prepared.screen_holds`); where the offset is too large to trust the
linearisation (:data:`FAST_DXY_M`, :data:`FAST_DYAW_RAD`: the updates decided before it
moved the belief) it decides the segment anew at the belief now, and where the update
step is too large (:data:`FAST_STEP_M`, :data:`FAST_STEP_RAD`: the first updates after a
poor prior) it falls back to the Localizer's own per-segment path.

Association is decided at predicted beliefs: the latest belief moved by the odometry,
without the updates of the segments decided with it (at most ``chunk_s`` of them, a
slightly wider gate than the one-at-a-time path's). The rules are those of
:meth:`~sonarloc.localize.localizer.Localizer._associate_echoes` and ``_echo_for``:
candidates that can echo towards the transducers and whose ranges are near the
readings', each candidate's readings screened one by one (chi-square(1)), readings a
detected, nearer rival explains as well dropped (:func:`~sonarloc.localize.echoes.
ambiguous`), the stacked squared Mahalanobis distance gated (chi-square(n)), the
candidate keeping the most readings wins if no other comes close in likelihood.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc import se2
from sonarloc.localize import echoes, ekf
from sonarloc.localize.echoes import Compressed
from sonarloc.localize.ekf import Feature, Gaussian, OdomNoise
from sonarloc.localize.features import FeatureMap
from sonarloc.physics.reflectors import ReflectorKind, kappa_at_range_us

Array = NDArray[np.float64]

#: Largest offset of the true belief from the one a segment was linearised at (position
#: [m], yaw [rad]) for which its reduced update is used as it is; beyond, the segment is
#: decided anew at the true belief (the first of a decision: the Localizer's per-segment
#: path).
FAST_DXY_M = 0.02
FAST_DYAW_RAD = 0.02
#: Largest update step (position [m], yaw [rad]) accepted from a reduced update; a
#: larger one is redone by the iterated per-segment path (relinearised at the result).
FAST_STEP_M = 0.02
FAST_STEP_RAD = 0.02

#: Largest change of a reading's off-axis angle [rad] (0.1 deg) over which
#: :meth:`BatchFuser.decide` extrapolates the delay model along its slope (the
#: curvature term stays below a few hundredths of a microsecond out to 15 deg off axis;
#: the per-segment path re-evaluates it beyond 0.03 deg, ``echoes.RELINEARIZE_RAD``).
RELINEARIZE_DELAY_RAD = 2e-3

#: A rival feature claims a reading only where it is detected with at least this
#: probability (``echoes.ambiguous``'s ``min_detect``, as the Localizer calls it).
RIVAL_MIN_DETECT = 0.5

Outcome = Literal["matched", "unmatched", "none"]


@dataclass(frozen=True)
class SegmentEchoes:
    """A closed segment's echoes, in time order: ``data`` (5, n) rows time [s],
    transducer pose in ``odom`` (x [m], y [m], yaw [rad]) and time of flight [us];
    ``t_ref`` its reference time (the last echo)."""

    t_ref: float
    data: Array

    @classmethod
    def from_segments(cls, segs: Sequence[object]) -> list[SegmentEchoes]:
        """The echoes of :class:`~sonarloc.fit.segment.Segment` s, in their order (those
        without any left out); each segment's readings in time order (a stable sort
        where they are not), ``data`` views into one array for all."""
        if not segs:
            return []
        rs = [s.readings for s in segs]  # type: ignore[attr-defined]
        data = np.array([np.concatenate([getattr(r, f) for r in rs]) for f in
                         ("t_s", "x_m", "y_m", "yaw_rad", "tof_us")], dtype=float)
        seg = np.repeat(np.arange(len(rs)), [len(r.t_s) for r in rs])
        echo = np.isfinite(data[4])
        data, seg = data[:, echo], seg[echo]
        if np.any((data[0, 1:] < data[0, :-1]) & (seg[1:] == seg[:-1])):
            data = data[:, np.lexsort((data[0], seg))]     # stable: by segment, then time
        ends = np.cumsum(np.bincount(seg, minlength=len(rs))).tolist()
        return [cls(data[0, b - 1].item(), data[:, a:b])
                for a, b in zip([0, *ends[:-1]], ends, strict=True) if b > a]


@dataclass
class Prepared:
    """One segment associated at a predicted belief (:meth:`BatchFuser.decide`).

    ``outcome``: ``matched`` (``kind``/``index``/``feature`` say which map feature;
    ``reduced`` its readings' update), ``unmatched`` (no feature explains the readings)
    or ``none`` (no reading inside the history). ``x0``: the predicted belief's mean,
    ``odom_ref`` the odometry pose at ``t_ref``; ``chain`` ``(t, z, rel, p_fac,
    v_fac)`` of the per-segment path (:meth:`Localizer._associate_echoes`).
    """

    t_ref: float
    outcome: Outcome
    odom_ref: Array
    x0: Array
    #: (t, z, rel, p_fac, v_fac) of the whole batch (padded), this segment's row and
    #: first column there
    batch: tuple[Array, Array, Array, Array, Array] | None = None
    row: int = 0
    col0: int = 0
    kind: str = ""
    index: int = -1
    feature: Feature | None = None
    n_kept: int = 0
    d2: float = math.nan
    n_candidates: int = 0
    share: float = math.nan
    reduced: Compressed | None = None
    #: the winner's usable readings at ``x0``: (Jacobian row (3,), innovation, variance
    #: of the reading, kept by the screening)
    screen_rows: list[tuple[list[float], float, float, bool]] | None = None

    @property
    def chain(self) -> tuple[Array, Array, Array, Array, Array] | None:
        """``(t, z, rel, p_fac, v_fac)`` of this segment's readings (None without any)."""
        if self.batch is None:
            return None
        k, c = self.row, self.col0
        t, z, rel, p_fac, v_fac = self.batch
        return t[k, c:], z[k, c:], rel[k, c:], p_fac[k, c:], v_fac[k, c:]

    def screen_holds(self, state: Gaussian, gate: float) -> bool:
        """Whether the one-reading screening at ``state`` keeps the same readings as at
        ``x0`` (the innovations moved by ``H (x - x0)``; scalar arithmetic)."""
        return self.screen_holds_lists(state.mean.tolist(), state.cov.tolist(), gate)

    def screen_holds_lists(self, mean: list[float], cov: list[list[float]], gate: float
                           ) -> bool:
        """:meth:`screen_holds` of a belief given as floats (mean (3,), cov (3, 3))."""
        if self.screen_rows is None:
            return False
        m0, m1, m2 = mean
        x0 = self.x0.tolist()
        d0, d1 = m0 - x0[0], m1 - x0[1]
        d2 = (m2 - x0[2] + math.pi) % (2.0 * math.pi) - math.pi
        (p00, p01, p02), (_, p11, p12), (_, _, p22) = cov
        for (h0, h1, h2), nu0, r_ii, kept in self.screen_rows:
            nu = nu0 - (h0 * d0 + h1 * d1 + h2 * d2)
            var = (h0 * (p00 * h0 + p01 * h1 + p02 * h2) + h1 * (p01 * h0 + p11 * h1 + p12 * h2)
                   + h2 * (p02 * h0 + p12 * h1 + p22 * h2) + r_ii)
            if (var > 0.0 and nu * nu <= gate * var) != kept:
                return False
        return True


Mat3 = list[list[float]]
Rows3 = tuple[tuple[float, float, float], tuple[float, float, float],
              tuple[float, float, float]]


def _mul3(a: Sequence[Sequence[float]], b: Sequence[Sequence[float]]) -> Rows3:
    """The product of 3x3 matrices given as nested sequences of floats, written out
    (:func:`reduced_update_lists` runs once per fused segment: no numpy calls)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = b
    return ((a00 * b00 + a01 * b10 + a02 * b20, a00 * b01 + a01 * b11 + a02 * b21,
             a00 * b02 + a01 * b12 + a02 * b22),
            (a10 * b00 + a11 * b10 + a12 * b20, a10 * b01 + a11 * b11 + a12 * b21,
             a10 * b02 + a11 * b12 + a12 * b22),
            (a20 * b00 + a21 * b10 + a22 * b20, a20 * b01 + a21 * b11 + a22 * b21,
             a20 * b02 + a21 * b12 + a22 * b22))


def reduced_update(state: Gaussian, c: Compressed) -> tuple[Gaussian, float] | None:
    """:func:`~sonarloc.localize.echoes.update` with a linearisation ``c`` already made:
    the update with ``(c.q_nu - c.rq (x - c.x0), c.rq, I)`` in Joseph form, for one
    filter, in scalar arithmetic (Cholesky solve of the 3x3 innovation covariance).
    Returns the updated belief and the reduced squared Mahalanobis distance (add
    ``c.resid2`` for the n-row one); None when the innovation covariance is not
    positive definite or not finite."""
    res = reduced_update_lists(state.mean.tolist(), state.cov.tolist(), c)
    if res is None:
        return None
    mean, cov, d2 = res
    return Gaussian.of_lists(mean, cov), d2


def reduced_update_lists(mean: list[float], cov: list[list[float]], c: Compressed
                         ) -> tuple[list[float], list[list[float]], float] | None:
    """:func:`reduced_update` of a belief given as floats (mean (3,), cov (3, 3) nested):
    the updated mean and covariance as lists, and the reduced squared Mahalanobis
    distance; None as there."""
    m0, m1, m2 = mean
    x0 = c.x0.tolist()
    d0, d1 = m0 - x0[0], m1 - x0[1]
    d2_ = (m2 - x0[2] + math.pi) % (2.0 * math.pi) - math.pi
    h: Mat3 = c.rq.tolist()
    qn = c.q_nu.tolist()
    if len(h) < 3:                          # fewer than 3 rows: pad with zero rows
        h = h + [[0.0, 0.0, 0.0]] * (3 - len(h))
        qn = qn + [0.0] * (3 - len(qn))
    (h00, h01, h02), (h10, h11, h12), (h20, h21, h22) = h
    n0 = qn[0] - (h00 * d0 + h01 * d1 + h02 * d2_)
    n1 = qn[1] - (h10 * d0 + h11 * d1 + h12 * d2_)
    n2 = qn[2] - (h20 * d0 + h21 * d1 + h22 * d2_)
    # written out (this runs once per fused segment): H P, S = H P Hᵀ + I, S = L Lᵀ, K,
    # the mean, the Joseph form and its symmetrised result
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = _mul3(h, cov)      # H P
    s00 = a00 * h00 + a01 * h01 + a02 * h02 + 1.0
    if not (s00 > 0.0 and math.isfinite(s00)):
        return None
    l00 = math.sqrt(s00)
    l10 = (a10 * h00 + a11 * h01 + a12 * h02) / l00
    l20 = (a20 * h00 + a21 * h01 + a22 * h02) / l00
    s11 = a10 * h10 + a11 * h11 + a12 * h12 + 1.0 - l10 * l10
    if not s11 > 0.0:
        return None
    l11 = math.sqrt(s11)
    l21 = ((a20 * h10 + a21 * h11 + a22 * h12) - l20 * l10) / l11
    s22 = a20 * h20 + a21 * h21 + a22 * h22 + 1.0 - l20 * l20 - l21 * l21
    if not s22 > 0.0:
        return None
    l22 = math.sqrt(s22)

    def solve(b0: float, b1: float, b2: float) -> tuple[float, float, float]:
        y0 = b0 / l00                           # S⁻¹ b: forward and back substitution
        y1 = (b1 - l10 * y0) / l11
        y2 = (b2 - l20 * y0 - l21 * y1) / l22
        z2 = y2 / l22
        z1 = (y1 - l21 * z2) / l11
        return (y0 - l10 * z1 - l20 * z2) / l00, z1, z2

    # K = P Hᵀ S⁻¹ = (S⁻¹ H P)ᵀ: row j of K is S⁻¹ times column j of H P
    k00, k01, k02 = solve(a00, a10, a20)
    k10, k11, k12 = solve(a01, a11, a21)
    k20, k21, k22 = solve(a02, a12, a22)
    sn0, sn1, sn2 = solve(n0, n1, n2)
    d2 = n0 * sn0 + n1 * sn1 + n2 * sn2
    if not (math.isfinite(d2) and d2 >= 0.0):
        return None
    new = [m0 + k00 * n0 + k01 * n1 + k02 * n2, m1 + k10 * n0 + k11 * n1 + k12 * n2,
           (m2 + k20 * n0 + k21 * n1 + k22 * n2 + math.pi) % (2.0 * math.pi) - math.pi]
    # I - K H
    i00, i01, i02 = (1.0 - (k00 * h00 + k01 * h10 + k02 * h20), 0.0 - (k00 * h01 + k01 * h11
                     + k02 * h21), 0.0 - (k00 * h02 + k01 * h12 + k02 * h22))
    i10, i11, i12 = (0.0 - (k10 * h00 + k11 * h10 + k12 * h20), 1.0 - (k10 * h01 + k11 * h11
                     + k12 * h21), 0.0 - (k10 * h02 + k11 * h12 + k12 * h22))
    i20, i21, i22 = (0.0 - (k20 * h00 + k21 * h10 + k22 * h20), 0.0 - (k20 * h01 + k21 * h11
                     + k22 * h21), 1.0 - (k20 * h02 + k21 * h12 + k22 * h22))
    # B = (I - K H) P
    (b00, b01, b02), (b10, b11, b12), (b20, b21, b22) = _mul3(
        ((i00, i01, i02), (i10, i11, i12), (i20, i21, i22)), cov)
    # B (I - K H)ᵀ + K Kᵀ, symmetrised
    o00 = b00 * i00 + b01 * i01 + b02 * i02 + (k00 * k00 + k01 * k01 + k02 * k02)
    o11 = b10 * i10 + b11 * i11 + b12 * i12 + (k10 * k10 + k11 * k11 + k12 * k12)
    o22 = b20 * i20 + b21 * i21 + b22 * i22 + (k20 * k20 + k21 * k21 + k22 * k22)
    o01 = b00 * i10 + b01 * i11 + b02 * i12 + (k00 * k10 + k01 * k11 + k02 * k12)
    o10 = b10 * i00 + b11 * i01 + b12 * i02 + (k10 * k00 + k11 * k01 + k12 * k02)
    o02 = b00 * i20 + b01 * i21 + b02 * i22 + (k00 * k20 + k01 * k21 + k02 * k22)
    o20 = b20 * i00 + b21 * i01 + b22 * i02 + (k20 * k00 + k21 * k01 + k22 * k02)
    o12 = b10 * i20 + b11 * i21 + b12 * i22 + (k10 * k20 + k11 * k21 + k12 * k22)
    o21 = b20 * i10 + b21 * i11 + b22 * i12 + (k20 * k10 + k21 * k11 + k22 * k12)
    s01, s02, s12 = 0.5 * (o01 + o10), 0.5 * (o02 + o20), 0.5 * (o12 + o21)
    return new, [[o00, s01, s02], [s01, o11, s12], [s02, s12, o22]], d2


def _median_valid(a: Array, n: NDArray[np.intp]) -> Array:
    """Median over the last axis of ``a`` (..., N) of its ``n`` (...) finite entries (NaN
    elsewhere; NaN where n is 0)."""
    srt = np.sort(a, axis=-1)                       # NaN last
    nn = np.broadcast_to(n, a.shape[:-1])
    lo = np.clip((nn - 1) // 2, 0, a.shape[-1] - 1)[..., None]
    hi = np.clip(nn // 2, 0, a.shape[-1] - 1)[..., None]
    med = 0.5 * (np.take_along_axis(srt, lo, -1) + np.take_along_axis(srt, hi, -1))[..., 0]
    return np.where(nn > 0, med, np.nan)


def interpolate_track(track_t: Array, track: Array, t: Array) -> Array:
    """Odometry poses (n, 3) at times ``t`` (n,): linear between the records of the
    track (``track_t`` (m,) sorted, ``track`` (m, 3)), yaw the short way round, held
    at the ends."""
    i = np.searchsorted(track_t, t, side="right")
    a = np.clip(i - 1, 0, len(track_t) - 1)
    b = np.minimum(a + 1, len(track_t) - 1)
    span = track_t[b] - track_t[a]
    f = np.where((b > a) & (span > 0) & (t > track_t[a]),
                 (t - track_t[a]) / np.where(span > 0, span, 1.0), 0.0)
    return se2.interpolate(track[a], track[b], f)


@dataclass
class Linearized:
    """Segments made ready by :meth:`BatchFuser.linearize` for :meth:`BatchFuser.decide`.

    Per segment (S): reference times and odometry poses, readings kept and the first
    column in the padded (S, N) layout, its usable entries; ``batch`` (t, z, rel, p_fac,
    v_fac) padded; ``xh``, ``ph`` the beliefs linearised at. ``pairs``: (segment,
    feature) candidates in segment order with the gap between their median range and
    the readings' and the smallest gap of one reading, the delay model linearised at
    ``xh`` (off-axis angle, mean [us] and slope [us/rad], (C, N) each), measurement
    covariances (C, N, N), usable readings (C, N), the strengths the delay model was
    evaluated with, the readings' own variances [m²] and detection probabilities
    (C, N); None when no segment has a candidate. :meth:`BatchFuser.decide`
    re-evaluates the delay model in place where a belief turns a reading's off-axis
    angle by more than :data:`RELINEARIZE_DELAY_RAD`.
    """

    t_ref: Array
    odom_ref: Array
    n_s: NDArray[np.intp]
    col0: NDArray[np.intp]
    valid: NDArray[np.bool_]
    batch: tuple[Array, Array, Array, Array, Array]
    xh: Array
    ph: Array
    pairs: tuple[NDArray[np.intp], NDArray[np.intp], Array, Array, Array, Array, Array,
                 Array, NDArray[np.bool_], Array, Array, Array] | None = None


class BatchFuser:
    """Vectorised linearisation and association of segments (see the module docstring).

    Parameters
    ----------
    fmap : the map's features.
    noise : odometry increment noise model.
    c_mps : speed of sound.
    screen_probability, gate_probability : the Localizer's ``echo_screen_probability``
        and ``echo_gate_probability``.
    max_range_m, wall_margin_m, min_match_probability : association settings.
    min_fraction : a winner must keep this share of a segment's readings (at least one).
    map_var_m2 : (P + W,) variance [m²] of each feature's position (points, then walls),
        shared by a segment's readings (``EchoObservation.map_var_m2``); None: 0.
    """

    def __init__(self, fmap: FeatureMap, noise: OdomNoise, c_mps: float,
                 screen_probability: float, gate_probability: float, max_range_m: float,
                 wall_margin_m: float, min_match_probability: float,
                 min_fraction: float, map_var_m2: ArrayLike | None = None) -> None:
        self.fmap = fmap
        self.noise = noise
        self.c_mps = float(c_mps)
        self.screen_gate = ekf.chi2_gate(1, screen_probability)
        self.gate_probability = gate_probability
        self.max_range_m = max_range_m
        self.wall_margin_m = wall_margin_m
        self.min_match_probability = min_match_probability
        self.min_fraction = min_fraction
        self.table = echoes.delay_table(self.c_mps)
        self._gates = np.array([np.inf])
        n_p = fmap.n_points
        # per feature (points first, then walls): centre / line, radius, strength, kind
        self._is_point = np.concatenate([np.ones(n_p, bool), np.zeros(fmap.n_walls, bool)])
        self._par = np.concatenate([fmap.point_xy, fmap.wall_line]).reshape(-1, 2)
        self._radius = np.concatenate([fmap.point_radius_m, np.zeros(fmap.n_walls)])
        kap = np.concatenate([fmap.point_kappa_us, fmap.wall_kappa_us])
        ok = np.isfinite(kap) & (kap > 0)
        self._kappa = np.where(ok, kap, 1.0)  # Localizer._kappa_fallback without a fit
        kinds = tuple(fmap.point_kind) + tuple(fmap.wall_kind)
        self._map_var = np.zeros(len(kinds)) if map_var_m2 is None else \
            np.asarray(map_var_m2, dtype=float).reshape(len(kinds))
        # feature groups: the same point (within 1 mm) or the same line (1 mm, 1 mrad) is
        # not a rival of itself (Localizer._rivals)
        n_f = len(kinds)
        group = np.arange(n_f)
        for i in range(n_f):
            for j in range(i):
                if self._is_point[i] != self._is_point[j]:
                    continue
                if self._is_point[i]:
                    same = math.hypot(*(self._par[i] - self._par[j])) <= 1e-3
                else:
                    d_alpha = (self._par[i, 1] - self._par[j, 1] + math.pi) % (2 * math.pi) \
                        - math.pi
                    same = abs(self._par[i, 0] - self._par[j, 0]) <= 1e-3 and \
                        abs(d_alpha) <= 1e-3
                if same:
                    group[i] = group[j]
                    break
        _, self._group = np.unique(group, return_inverse=True)
        self._n_groups = int(self._group.max(initial=-1)) + 1
        grow = [ReflectorKind.parse(k).is_cylinder for k in kinds]
        self._grow_kinds = sorted({k for k, g in zip(kinds, grow, strict=True) if g})
        self._grow_code = np.array([self._grow_kinds.index(k) if g else -1
                                    for k, g in zip(kinds, grow, strict=True)], dtype=int)
        self._features = [fmap.point(i) for i in range(n_p)] + \
            [fmap.wall(i) for i in range(fmap.n_walls)]
        us_to_m = 0.5e-6 * self.c_mps
        self._us_to_m = us_to_m
        self._bias_m = us_to_m * 0.5 * self.table.params.count_period_us

    def gate(self, dof: int) -> float:
        """chi-square gate of the stacked update with ``dof`` readings."""
        if dof >= len(self._gates):
            self._gates = np.array([np.inf] + [ekf.chi2_gate(k, self.gate_probability)
                                               for k in range(1, max(2 * dof, 16))])
        return float(self._gates[dof])

    def linearize(self, segs: list[SegmentEchoes], track_t: Array, track: Array,
                  t_min: float, last_odom: Array, last_state: Gaussian) -> Linearized | None:
        """The first level, for many segments: readings padded, transducer chains,
        candidate features and rivals, every candidate's readings through the forward
        model at the beliefs predicted from ``last_state`` (the latest belief, at
        odometry pose ``last_odom``) by the odometry ``track`` (times ``track_t``; it
        must cover the readings and reference times). Readings before ``t_min`` (the
        history's start) are left out. None without segments."""
        if not segs:
            return None
        S = len(segs)
        t_ref = np.array([s.t_ref for s in segs])
        lens = np.array([s.data.shape[1] for s in segs])
        allv = np.concatenate([s.data for s in segs], axis=1)          # (5, total)
        seg_id = np.repeat(np.arange(S), lens)
        keep_r = (allv[0] >= t_min) & (allv[0] <= t_ref[seg_id] + 1e-9)
        flat = allv[:, keep_r]
        rows = seg_id[keep_r]
        n_s = np.bincount(rows, minlength=S)
        N = max(int(n_s.max()), 3)
        # (S, N) padded at the start with the first reading (a zero odometry increment)
        col0 = N - n_s
        starts = np.cumsum(n_s) - n_s
        cols = col0[rows] + np.arange(len(rows)) - starts[rows]
        has = n_s > 0
        first = np.zeros((S, 5))
        first[has] = flat[:, starts[has]].T
        pad = np.repeat(first[:, None, :], N, axis=1)
        pad[rows, cols] = flat.T
        valid = np.zeros((S, N), dtype=bool)
        valid[rows, cols] = True
        t_r = pad[..., 0]
        sens = pad[..., 1:4]
        z = 0.5e-6 * self.c_mps * pad[..., 4]
        # odometry at the readings and at the reference times
        base_at = interpolate_track(track_t, track, t_r.reshape(-1)).reshape(S, N, 3)
        odom_ref = interpolate_track(track_t, track, t_ref)
        rel, p_fac, v_fac = echoes.relative_sensor_chain(odom_ref, base_at, sens, self.noise)
        # predicted beliefs at the reference times: the last belief moved by the odometry
        pred = ekf.predict(Gaussian(np.broadcast_to(last_state.mean, (S, 3)).copy(),
                                    np.broadcast_to(last_state.cov, (S, 3, 3)).copy()),
                           se2.between(last_odom, odom_ref), self.noise)
        xh, ph = pred.mean, pred.cov
        lin = Linearized(t_ref, odom_ref, n_s, col0, valid, (t_r, z, rel, p_fac, v_fac), xh, ph)
        if not has.any():
            return lin
        # --- candidates: features that can echo towards the last transducer position,
        # their ranges near the readings' (median; the delay adds at most ~2 mm); rivals:
        # those near any one reading (they may explain it as well: echoes.ambiguous).
        # Selected with this covariance (:meth:`decide` applies its own tolerance).
        tpose = se2.compose(xh[:, None, :], rel)                       # (S, N, 3) in map
        last_xy = tpose[:, -1, :2]
        base = np.concatenate([self.fmap.points_visible_from(last_xy, self.max_range_m),
                               self.fmap.walls_facing(last_xy, self.wall_margin_m,
                                                      self.max_range_m)], axis=1)
        base &= has[:, None]
        tol = 0.05 + 4.0 * np.sqrt(np.maximum(ph[:, 0, 0] + ph[:, 1, 1], 0.0))
        bs, bf = np.nonzero(base)                    # the features each segment may see
        rng_b = np.where(valid[bs], self._ranges(tpose, bs, bf), np.nan)   # (B, N)
        zmed = _median_valid(np.where(valid, z, np.nan), n_s)
        gap_med = np.abs(_median_valid(rng_b, n_s[bs]) - zmed[bs])
        gap_one = np.min(np.where(valid[bs], np.abs(rng_b - z[bs]), np.inf), axis=1)
        near = (gap_med <= tol[bs]) | (gap_one <= tol[bs])
        ps, fs = bs[near], bf[near]
        if ps.size == 0:
            return lin
        # --- each pair's readings through the forward model at the predicted belief
        rng, theta, _, _ = self._geometry(tpose[ps], fs)
        kap = np.broadcast_to(self._kappa[fs][:, None], rng.shape).copy()
        code = self._grow_code[fs]                 # cylinders grow with range, by kind
        for kc in np.unique(code[code >= 0]).tolist():
            m = code == kc
            kap[m] = kappa_at_range_us(kap[m], self._grow_kinds[kc], np.maximum(rng[m], 1e-3),
                                       self._radius[fs[m]][:, None])
        vp = valid[ps]                      # padding: not evaluated (zero delay)
        mean, slope, sd, p_det = (np.zeros(rng.shape) for _ in range(4))
        mean[vp], slope[vp], sd[vp], p_det[vp] = self.table.lookup(theta[vp], kap[vp])
        _, _, g = self._measure(xh[ps], rel[ps], fs, theta, mean, slope, z[ps])
        sd_m = self._us_to_m * echoes.reading_sd_us(sd, self.c_mps)
        gp = np.einsum("cni,cnij->cnj", g, p_fac[ps])
        gv = np.einsum("cnij,cnj->cni", v_fac[ps], g)
        mm = gp @ np.swapaxes(gv, -1, -2)           # g_i P_i V_j g_j, valid for i <= j
        r = np.triu(mm) + np.swapaxes(np.triu(mm, 1), -1, -2)
        r = 0.5 * (r + np.swapaxes(r, -1, -2))
        idx = np.arange(N)
        r[:, idx, idx] += sd_m**2
        r += self._map_var[fs][:, None, None]     # the feature's map error, shared
        with np.errstate(invalid="ignore"):
            ok = vp & np.isfinite(mean) & np.isfinite(slope) & np.isfinite(r[:, idx, idx])
        lin.pairs = (ps, fs, gap_med[near], gap_one[near], theta,
                     np.where(ok, mean, 0.0), np.where(ok, slope, 0.0), r, ok, kap,
                     np.where(ok, sd_m**2, 0.0), np.where(ok, p_det, 0.0))
        return lin

    def _geometry(self, tp: Array, fs: NDArray[np.intp]) -> tuple[Array, Array, Array, Array]:
        """Range, off-axis angle and their derivatives wrt the transducer pose (C, N, 3)
        of transducers ``tp`` (C, N, 3) in map seeing features ``fs`` (C,) (points or
        walls; :func:`~sonarloc.localize.echoes.geometry`)."""
        px, py, psi = tp[..., 0], tp[..., 1], tp[..., 2]
        is_pt = self._is_point[fs][:, None]
        par = self._par[fs]
        cx, cy = par[:, 0:1], par[:, 1:2]
        dx, dy = cx - px, cy - py
        dist2 = np.maximum(dx * dx + dy * dy, 1e-18)
        dist = np.sqrt(dist2)
        ca, sa = np.cos(cy), np.sin(cy)                                # walls: (rho, alpha)
        signed = cx - px * ca - py * sa
        sign = np.where(signed < 0, -1.0, 1.0)
        rng = np.where(is_pt, dist - self._radius[fs][:, None], np.abs(signed))
        direction = np.where(is_pt, np.arctan2(dy, dx), cy + np.where(signed < 0, math.pi, 0.0))
        theta = (direction - psi + math.pi) % (2.0 * math.pi) - math.pi
        zero = np.zeros_like(rng)
        dr = np.stack([np.where(is_pt, -dx / dist, -sign * ca),
                       np.where(is_pt, -dy / dist, -sign * sa), zero], axis=-1)
        dth = np.stack([np.where(is_pt, dy / dist2, 0.0), np.where(is_pt, -dx / dist2, 0.0),
                        zero - 1.0], axis=-1)
        return rng, theta, dr, dth

    def _measure(self, x: Array, rel: Array, fs: NDArray[np.intp], theta_lin: Array,
                 mean: Array, slope: Array, z: Array,
                 geom: tuple[Array, Array, Array, Array] | None = None
                 ) -> tuple[Array, Array, Array]:
        """Innovations (C, N), Jacobians wrt the pose (C, N, 3) and wrt the transducer
        poses in ``base_link`` (C, N, 3) of the readings ``z`` (C, N) of features ``fs``
        seen from beliefs ``x`` (C, 3), transducers ``rel`` (C, N, 3), the delay model
        linearised at ``theta_lin`` (mean, slope) and extrapolated along its slope
        (:meth:`~sonarloc.localize.echoes.EchoObservation.measure`)."""
        c0, s0 = np.cos(x[:, 2])[:, None], np.sin(x[:, 2])[:, None]
        rng, theta, dr, dth = geom if geom is not None else \
            self._geometry(se2.compose(x[:, None, :], rel), fs)
        us_to_m = self._us_to_m
        dtheta = (theta - theta_lin + math.pi) % (2.0 * math.pi) - math.pi
        nu = z - (rng + us_to_m * (mean + slope * dtheta) + self._bias_m)
        dh = dr + (us_to_m * slope)[..., None] * dth        # wrt the transducer pose in map
        # transducer pose T = x ⊕ rel: dT/dx and dT/drel
        hx = np.stack([dh[..., 0], dh[..., 1],
                       dh[..., 0] * (-s0 * rel[..., 0] - c0 * rel[..., 1])
                       + dh[..., 1] * (c0 * rel[..., 0] - s0 * rel[..., 1]) + dh[..., 2]],
                      axis=-1)
        g = np.stack([dh[..., 0] * c0 + dh[..., 1] * s0, -dh[..., 0] * s0 + dh[..., 1] * c0,
                      dh[..., 2]], axis=-1)
        return nu, hx, g

    def decide(self, lin: Linearized, a: int, b: int, x: Array, p: Array,
               map_var_extra_m2: Array | None = None) -> list[Prepared]:
        """Screen, gate and associate segments ``a..b-1`` of ``lin`` at beliefs with means
        ``x`` (b-a, 3) and covariances ``p`` (b-a, 3, 3) (geometry at ``x``, the delay
        model as linearised); the winners' reduced updates. ``map_var_extra_m2``: (P + W,)
        variance [m²] added to each feature's ``map_var_m2`` (shared by a segment's
        readings; the Localizer's :meth:`~sonarloc.localize.localizer.Localizer.map_uses`);
        given, a winner's update also takes the feature's ``map_var_m2`` once more for
        each earlier winner of the same feature among these segments (they will have
        been fused before it, as the live Localizer counts them)."""
        out: list[Prepared] = []
        t_r, z, rel, p_fac, v_fac = lin.batch
        for k in range(a, b):
            tk, nk, ck = float(lin.t_ref[k]), int(lin.n_s[k]), int(lin.col0[k])
            out.append(Prepared(tk, "unmatched", lin.odom_ref[k], x[k - a], lin.batch, k, ck)
                       if nk else Prepared(tk, "none", lin.odom_ref[k], x[k - a]))
        if lin.pairs is None:
            return out
        ps_all = lin.pairs[0]
        lo, hi = np.searchsorted(ps_all, [a, b])
        if hi <= lo:
            return out
        ps = ps_all[lo:hi] - a
        _, fs_a, med_a, one_a, th_a, mean_a, slope_a, r_a, ok_a, kap_a, sd2_a, pd_a = \
            lin.pairs
        fs, med_gap, one_gap, r, ok = fs_a[lo:hi], med_a[lo:hi], one_a[lo:hi], r_a[lo:hi], \
            ok_a[lo:hi]
        th_lin, mean, slope = th_a[lo:hi], mean_a[lo:hi], slope_a[lo:hi]
        N = r.shape[1]
        idx = np.arange(N)
        tol = 0.05 + 4.0 * np.sqrt(np.maximum(p[:, 0, 0] + p[:, 1, 1], 0.0))
        is_cand = med_gap <= tol[ps]
        is_rival = one_gap <= tol[ps]
        # the readings through the forward model at these beliefs (the delay model as
        # linearised)
        geom = self._geometry(se2.compose(x[ps][:, None, :], rel[ps + a]), fs)
        with np.errstate(invalid="ignore"):
            redo = ok & (np.abs((geom[1] - th_lin + math.pi) % (2.0 * math.pi) - math.pi)
                         > RELINEARIZE_DELAY_RAD)
        if redo.any():
            # the delay model again where the angle moved too far to extrapolate it (in
            # place: later decisions start from here); the readings' own variances too
            th = geom[1][redo]
            m2, s2, sd2, pd2 = self.table.lookup(th, kap_a[lo:hi][redo])
            sdm2 = (self._us_to_m * echoes.reading_sd_us(sd2, self.c_mps)) ** 2
            fine = np.isfinite(m2) & np.isfinite(s2) & np.isfinite(sdm2)
            rows_c, cols_c = np.nonzero(redo)
            rows_c, cols_c = rows_c + lo, cols_c
            th_a[rows_c, cols_c] = th
            mean_a[rows_c, cols_c] = np.where(fine, m2, 0.0)
            slope_a[rows_c, cols_c] = np.where(fine, s2, 0.0)
            r_a[rows_c, cols_c, cols_c] += np.where(fine, sdm2, 0.0) - sd2_a[rows_c, cols_c]
            sd2_a[rows_c, cols_c] = np.where(fine, sdm2, 0.0)
            pd_a[rows_c, cols_c] = np.where(fine, pd2, 0.0)
            ok_a[rows_c, cols_c] &= fine
            r, ok = r_a[lo:hi], ok_a[lo:hi]
            th_lin, mean, slope = th_a[lo:hi], mean_a[lo:hi], slope_a[lo:hi]
        if map_var_extra_m2 is not None:
            r = r + map_var_extra_m2[fs][:, None, None]
        nu, hx, _ = self._measure(x[ps], rel[ps + a], fs, th_lin, mean, slope, z[ps + a], geom)
        nu = np.where(ok, nu, 0.0)
        # --- screening, one reading at a time
        hph = np.einsum("cni,cij,cmj->cnm", hx, p[ps], hx)
        s_ii = hph[:, idx, idx] + r[:, idx, idx]
        with np.errstate(invalid="ignore", divide="ignore"):
            # (a reading past the edge of the detection arc is not the feature's:
            # echoes.screen)
            usable = ok & np.isfinite(s_ii) & (s_ii > 0) \
                & ((pd_a[lo:hi] >= echoes.SCREEN_MIN_DETECT)
                   | ~echoes.belief_is_tight(p[ps])[:, None])
            passed = usable & (nu**2 <= self.screen_gate * np.where(usable, s_ii, 1.0))
        # a candidate's reading is not kept where a rival (another point, another line
        # of the same segment) also passes it, is detected there and predicts the
        # earlier crossing (echoes.ambiguous: the first crossing wins)
        h = z[ps + a] - nu                                   # predicted ranges
        detected = pd_a[lo:hi] >= RIVAL_MIN_DETECT
        claim = passed & is_rival[:, None] & detected
        pc, pq = self._rival_pairs(ps, fs)
        beaten = np.zeros(passed.shape, dtype=bool)
        wins = claim[pq] & (h[pq] < h[pc])                   # (pairs, N)
        rows_w, cols_w = np.nonzero(wins)
        beaten[pc[rows_w], cols_w] = True
        keep = passed & ~beaten & is_cand[:, None]
        n_keep = keep.sum(axis=1)
        need = np.maximum(1, np.ceil(self.min_fraction * lin.n_s[ps + a] - 1e-9)).astype(int)
        live = is_cand & (n_keep >= need) & (n_keep >= 1)
        if not live.any():
            return out
        # --- stacked squared Mahalanobis distance of each candidate's kept readings
        both = keep[:, :, None] & keep[:, None, :]
        eye = np.broadcast_to(np.eye(N), both.shape)
        s_full = np.where(both, hph + r, eye)
        nu_k = np.where(keep, nu, 0.0)
        d2 = np.full(len(ps), np.inf)
        logdet = np.zeros(len(ps))
        li = np.flatnonzero(live)
        try:
            sol = np.linalg.solve(s_full[li], nu_k[li][..., None])[..., 0]
            d2[li] = np.einsum("cn,cn->c", nu_k[li], sol)
            logdet[li] = np.linalg.slogdet(s_full[li])[1]
        except np.linalg.LinAlgError:
            for c in li.tolist():
                try:
                    d2[c] = float(nu_k[c] @ np.linalg.solve(s_full[c], nu_k[c]))
                    logdet[c] = float(np.linalg.slogdet(s_full[c])[1])
                except np.linalg.LinAlgError:
                    d2[c] = np.inf
        self.gate(int(n_keep.max()))
        gated = live & (d2 <= self._gates[n_keep])
        # --- the winner of each segment: most readings kept, clearly the likeliest
        g = np.flatnonzero(gated)                 # pairs in segment order
        if g.size == 0:
            return out
        sg = ps[g]
        first_of = np.flatnonzero(np.concatenate([[True], sg[1:] != sg[:-1]]))
        gi = np.cumsum(np.concatenate([[0], (sg[1:] != sg[:-1]).astype(int)]))
        nk = n_keep[g]
        top = nk == np.maximum.reduceat(nk, first_of)[gi]
        ll = np.where(top, -0.5 * d2[g] - 0.5 * logdet[g], -np.inf)
        llmax = np.maximum.reduceat(ll, first_of)
        share = 1.0 / np.add.reduceat(np.where(top, np.exp(ll - llmax[gi]), 0.0), first_of)
        n_top = np.add.reduceat(top.astype(int), first_of)
        best = np.flatnonzero(top & (ll == llmax[gi]))
        best = best[np.concatenate([[True], gi[best[1:]] != gi[best[:-1]]])]  # the first
        sure = share >= self.min_match_probability
        if not sure.any():
            return out
        wp = g[best[sure]]
        # --- the winners' reduced updates: whitened by R = L Lᵀ and QR-factored
        kw = keep[wp]
        bw = kw[:, :, None] & kw[:, None, :]
        rw_full = r[wp]
        if map_var_extra_m2 is not None and len(wp) > 1:
            fw = fs[wp]                                  # in segment order
            earlier = np.triu(fw[:, None] == fw[None, :], 1).sum(axis=0)
            rw_full = rw_full + (earlier * self._map_var[fw])[:, None, None]
        rw = np.where(bw, rw_full, np.broadcast_to(np.eye(N), bw.shape))
        hw = np.where(kw[..., None], hx[wp], 0.0)
        nw = np.where(kw, nu[wp], 0.0)
        good = np.ones(len(wp), dtype=bool)
        try:
            chol = np.linalg.cholesky(rw)
        except np.linalg.LinAlgError:
            chol = np.broadcast_to(np.eye(N), rw.shape).copy()
            for j in range(len(wp)):
                try:
                    chol[j] = np.linalg.cholesky(rw[j])
                except np.linalg.LinAlgError:
                    good[j] = False
        sol = np.linalg.solve(chol, np.concatenate([hw, nw[..., None]], axis=-1))
        qm, rq = np.linalg.qr(sol[..., :3], mode="reduced")
        q_nu = np.einsum("cni,cn->ci", qm, sol[..., 3])
        resid2 = np.maximum(np.einsum("cn,cn->c", sol[..., 3], sol[..., 3])
                            - np.einsum("ci,ci->c", q_nu, q_nu), 0.0)
        r_ii = r[:, idx, idx]
        wp, j_ok = wp[good], np.flatnonzero(good)            # the rest: the per-segment path
        screen = self._screen_rows(wp, (pc, pq), (hx, nu, r_ii), (usable, passed),
                                   detected & usable & is_rival[:, None], h)
        for j, f, k, nk, d2c, sh, nt, rows in zip(
                j_ok.tolist(), fs[wp].tolist(), ps[wp].tolist(),
                n_keep[wp].tolist(), d2[wp].tolist(), share[sure][good].tolist(),
                n_top[sure][good].tolist(), screen, strict=True):
            pr = out[k]
            pr.n_candidates = nt
            pr.outcome = "matched"
            point = f < self.fmap.n_points
            pr.kind = "point" if point else "wall"
            pr.index = f if point else f - self.fmap.n_points
            pr.feature = self._features[f]
            pr.n_kept = nk
            pr.d2 = d2c
            pr.share = sh
            pr.reduced = Compressed(x[k].copy(), q_nu[j], rq[j], float(resid2[j]), nk)
            pr.screen_rows = rows
        return out

    def _rival_pairs(self, ps: NDArray[np.intp], fs: NDArray[np.intp]
                     ) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Pairs (c, q) of candidate pairs ``(ps, fs)`` (segment, feature; in segment
        order) of the same segment whose features are not the same point or line (a
        rival of each other: ``Localizer._rivals``), sorted by c, then q."""
        first = np.flatnonzero(np.concatenate([[True], ps[1:] != ps[:-1]]))
        size = np.diff(np.append(first, len(ps)))
        run_start = np.repeat(first, size)                 # (C,) first pair of c's run
        run_size = np.repeat(size, size)
        pc = np.repeat(np.arange(len(ps)), run_size)
        pq = np.repeat(run_start, run_size) + (np.arange(len(pc))
                                               - np.repeat(np.cumsum(run_size) - run_size,
                                                           run_size))
        other = self._group[fs[pc]] != self._group[fs[pq]]
        return pc[other], pq[other]

    @staticmethod
    def _screen_rows(wp: NDArray[np.intp], pairs: tuple[NDArray[np.intp], NDArray[np.intp]],
                     rows: tuple[Array, Array, Array],
                     screened: tuple[NDArray[np.bool_], NDArray[np.bool_]],
                     rival_usable: NDArray[np.bool_], h: Array
                     ) -> list[list[tuple[list[float], float, float, bool]]]:
        """:attr:`Prepared.screen_rows` of the winning pairs ``wp`` (W,): what decided
        their kept readings, each a (Jacobian row, innovation, reading variance, passed)
        of ``rows`` (hx (C, N, 3), nu (C, N), r_ii (C, N)): the winner's own screening
        of its usable readings (``screened`` = (usable, passed) (C, N)), then each of
        its rivals' (``pairs``, in q order) screening of the readings the winner passed
        that the rival (a rival, detected and usable there: ``rival_usable``) predicts
        nearer (ranges ``h`` (C, N))."""
        hx, nu, r_ii = rows
        usable, passed = screened
        pc, pq = pairs
        w_of = np.full(len(usable), -1)
        w_of[wp] = np.arange(len(wp))
        mine = w_of[pc] >= 0
        rc, rq = pc[mine], pq[mine]
        pi, ri = np.nonzero(passed[rc] & rival_usable[rq] & (h[rq] < h[rc]))
        wi, oi = np.nonzero(usable[wp])
        src = np.concatenate([wp[wi], rq[pi]])              # the screening's pair, reading
        col = np.concatenate([oi, ri])
        owner = np.concatenate([wi, w_of[rc[pi]]])
        order = np.argsort(owner, kind="stable")            # own rows first, then rivals'
        src, col = src[order], col[order]
        bounds = [0, *np.cumsum(np.bincount(owner, minlength=len(wp))).tolist()]
        flat = list(zip(hx[src, col].tolist(), nu[src, col].tolist(),
                        r_ii[src, col].tolist(), passed[src, col].tolist(), strict=True))
        return [flat[b0:b1] for b0, b1 in zip(bounds[:-1], bounds[1:], strict=True)]

    def _ranges(self, tpose: Array, seg: NDArray[np.intp], feat: NDArray[np.intp]) -> Array:
        """(B, N) ranges (geometry only) from the transducers ``tpose[seg]`` ((S, N, 3)
        indexed by ``seg`` (B,)) to the features ``feat`` (B,) (points then walls)."""
        px, py = tpose[seg, :, 0], tpose[seg, :, 1]
        is_pt = self._is_point[feat][:, None]
        par = self._par[feat]
        a, b = par[:, 0:1], par[:, 1:2]                   # point (x, y) or wall (rho, alpha)
        return np.where(is_pt, np.hypot(a - px, b - py) - self._radius[feat][:, None],
                        np.abs(a - px * np.cos(b) - py * np.sin(b)))

"""Two point reflectors in one segment: the min-of-two-U's model and when to believe it.

Two reflectors a few degrees apart at nearly the same range give one segment: the
module reports the *first* detected crossing, so the readings follow the lower of two
U-shaped curves. One landmark then explains the readings with a too-low kappa (a
wider, flatter U) or not at all. This module fits the two-reflector model

    reading i ~ first detected echo of {A, B}:
        p(y_i) = f_A P_A (1 - P_B (1 - w)) + f_B P_B (1 - P_A w)
        P(no echo at j) = (1 - P_A,j) (1 - P_B,j)

with ``f`` the detected echo's TOF density and ``P`` its detection probability under
the single-landmark model (:mod:`sonarloc.fit.model`, same tier) and
``w = Phi((m_B - m_A) / sqrt(s_A^2 + s_B^2))`` the probability that A's crossing comes
first when both are detected. With one component it is exactly the single-landmark
likelihood, so both are compared on equal terms.

Search: for fixed bearings (phi_A, phi_B) and an assignment of each echo to the
component nearer its beam axis, the model is linear in (To, kappa) of each component;
a grid over bearing *pairs* with these 2x2 solves brackets the optimum globally, the
best few nodes are refined on the full likelihood (quasi-Newton, BFGS).

Decision (documented in docs/FITTING.md): the pair replaces the single landmark when

* -2 log-likelihood drops by more than the BIC price of three more parameters
  (``3 ln n``, n readings including no-echo ones) and by more than ``MIN_GAIN``,
* each component is individually supported: removing it (the other kept as fitted)
  costs more than that price; it is the first echo for at least ``min_echoes``
  readings, mostly in one contiguous run of beam axes (``MIN_RUN_SHARE``),
* the bearings differ by more than ``MIN_SEPARATION_DEG``, and the weaker one is not
  where the stronger one's side lobe would be (``SIDE_LOBE_DEG``).

A candidate whose single fit leaves no room for that gain (each echo costs at least
what a zero-delay echo at its mean costs: :func:`_pair_cost_floor`) is not searched.
Otherwise the single landmark stands; a segment whose single fit was not trusted
keeps its status and its reason gets the pair test's numbers (the two could not be
told apart). Each echo is evaluated with a robust cap (``outlier_sigma^2`` plus the
log-variance at zero delay) so a spike cannot buy a component.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtrc, chdtri, ndtr

from sonarloc.fit import model as M
from sonarloc.fit.lsq import FitConfig, SegmentBatch, _kappa_penalty, pack_flat
from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.fit.segment import Segment
from sonarloc.physics.tof import ModuleParams

Array = NDArray[np.float64]

MIN_SEPARATION_DEG = 1.0
"""Bearings of the two components closer than this are one landmark."""

GRID_STEP_DEG = 1.0
"""Bearing grid step of the pair search."""

N_STARTS = 3
"""Grid nodes refined on the full likelihood."""

MIN_GAIN = 25.0
"""Least -2 log-likelihood gain of two reflectors over one, on top of the BIC price: the
models are not exact (spikes, a beam tier that misses side lobes), and single
reflectors with such misfits gain up to ~20 from a second component (measured:
benchmarks/results/fit_quality.md)."""

MIN_RUN_SHARE = 0.6
"""The readings where a component gives the first echo must mostly (this share) form one
contiguous run in beam-axis order: a reflector's U, not scattered spikes."""

SIDE_LOBE_DEG = (12.0, 26.0)
"""A weak component (kappa above ``SIDE_LOBE_KAPPA_US``) this far from a strong one
(kappa below ``SIDE_LOBE_STRONG_US``) may be the strong one's side lobe (PHYSICS.md:
side lobes near 17-20 deg reach the detection limit only for kappa below ~0.2 us)."""

SIDE_LOBE_KAPPA_US = 3.0
SIDE_LOBE_STRONG_US = 0.3

N_CANDIDATES = 48
"""Best grid nodes by the linear solves whose full likelihood is evaluated."""

_LNK_LO, _LNK_HI = math.log(1e-4), math.log(1e4)   # ln kappa [us] evaluated within these

_SCALE = np.array([1e-3, math.pi / 180.0, 1.0])   # mm, deg, ln kappa -> m, rad, ln kappa


@dataclass
class PairFit:
    """Result of the two-reflector fit (:func:`resolve_pair_groups`) for one segment.

    ``local``: (2, 3) ``(r [m], phi [rad], kappa [us])`` of the components seen from the
    reference pose (ordered by bearing); ``cov``: (2, 3, 3) their marginal covariances
    (NaN unless accepted);
    ``cost_single``/``cost_pair``: robust -2 log-likelihood of the best one- and two-
    reflector models; ``support``: (2,) cost increase when either component is removed;
    ``n_first``: (2,) readings at which each is the first echo (responsibilities);
    ``price``: the BIC price of the three extra parameters; ``accepted``: the decision;
    ``basis``: a sentence saying why; ``ambiguous``: components whose bearing another
    optimum fits as well; ``hidden``: (2,) 0 where a component's minimum is seen (it is
    the first echo at the reading nearest its bearing), NaN where the other reflector
    hides it, else how far [deg] it lies beyond the readings. A candidate whose pair
    cannot reach the bar is not searched (:func:`_bounded`): ``cost_single`` is then the
    cost of the single landmark as given, ``cost_pair`` a lower bound of every pair's
    (so ``gain`` is an upper bound) and the fitted quantities are NaN.
    """

    local: Array
    cov: Array
    cost_single: float
    cost_pair: float
    support: Array
    n_first: Array
    price: float
    accepted: bool
    basis: str
    chi2: Array
    ambiguous: dict[int, str] = field(default_factory=dict)
    hidden: Array = field(default_factory=lambda: np.zeros(2))

    @property
    def gain(self) -> float:
        return self.cost_single - self.cost_pair


class _Mixture(NamedTuple):
    """:meth:`_Segment._mixture`: per echo (S, n) each component's log-likelihood of
    being the first echo (``parts``) and the robust total ``ll``; with two components
    also the standardised mean difference ``t``, ``w = Phi(t)`` (A's crossing first)
    and the detection probabilities ``pa``, ``pb`` (None with one)."""

    parts: list[Array]
    ll: Array
    t: Array | None
    w: Array | None
    pa: Array | None
    pb: Array | None


@dataclass
class _CompGrad:
    """What :meth:`_Segment.cost_grad` needs of one component besides its terms: the
    derivatives of the echo mean, variance and log P(echo) by v = ln(kappa g) (S, n),
    d ln g / d theta at the echoes, the echo geometry; d log P(no echo) / d ln kappa
    (S, n_ne), d ln g / d theta there and the no-echo geometry (None: no such readings)."""

    m_v: Array
    s2_v: Array
    lp_v: Array
    dlng: Array
    geo: M.Geometry | None
    lqn_v: Array
    dlngn: Array
    ng: M.Geometry | None


class _Rd(NamedTuple):
    """The readings of the evaluated rows (:meth:`_Segment._readings`): echo (px, py,
    yaw, y) and no-echo (px, py, yaw) arrays, (n,) / (S, n) with parameters per row
    (``rows`` None), or flat (N,) over all rows' readings with ``rows`` (N,) / ``nrows``
    (N_ne,) the row of each entry (:class:`_Segments`: px, py empty where the
    transducer did not move, the geometry then needs no positions); ``S`` rows."""

    px: Array
    py: Array
    yaw: Array
    y: Array
    npx: Array
    npy: Array
    nyaw: Array
    rows: NDArray[np.intp] | None
    nrows: NDArray[np.intp] | None
    S: int
    blocks: tuple[tuple[str, _Rd], ...] | None = None
    """Rows of several tiers (:class:`_Segments`): each tier's entries, contiguous (the
    readings of that tier's rows, ``rows`` the same), in order; None: one tier."""


def _rowsum(v: Array, rows: NDArray[np.intp] | None, S: int) -> Array:
    """Per-row sums (S,) of per-reading values: (S, n) summed along the readings, or
    flat (N,) with the row of each entry."""
    if rows is None:
        return np.asarray(v.sum(1), dtype=float)
    return np.bincount(rows, weights=v, minlength=S).astype(float, copy=False)


class _Segment:
    """One segment's readings relative to its reference pose (row ``b`` of a batch).

    :meth:`cost` and :meth:`detail` evaluate several parameter rows at once; with
    :class:`_Segments` (several segments' readings end to end) each row names
    its segment (``owner``), so the pair search of a whole scan runs in one call per
    step instead of one per segment (the cost of a call is mostly per-call overhead).
    """

    def __init__(self, batch: SegmentBatch, b: int, cfg: FitConfig, tier: str) -> None:
        v = batch.valid[b]
        nv = batch.ne_valid[b]
        self.px, self.py, self.yaw = batch.px[b, v], batch.py[b, v], batch.yaw[b, v]
        self.y = batch.tof_us[b, v] - 0.5 * cfg.module.count_period_us
        self.npx, self.npy, self.nyaw = (batch.ne_px[b, nv], batch.ne_py[b, nv],
                                         batch.ne_yaw[b, nv])
        self.cfg = cfg
        self.tier = tier
        mod = cfg.module
        self.cap = cfg.outlier_sigma ** 2 + math.log(
            2.0 * math.pi * float(M.tof_variance_us2(0.0, mod)))
        # whether the transducer moved (the geometry's fast path for a pan otherwise)
        self.moving = bool(self.px.any() or self.py.any())
        self.ne_moving = bool(self.npx.any() or self.npy.any())

    @property
    def n(self) -> int:
        return int(self.y.size + self.npx.size)

    def _readings(self, owner: NDArray[np.intp] | None, S: int) -> _Rd:
        """The readings of ``S`` rows (of segments ``owner``, :class:`_Segments`)."""
        return _Rd(self.px, self.py, self.yaw, self.y, self.npx, self.npy, self.nyaw,
                   None, None, S)

    def _masks(self, owner: NDArray[np.intp] | None
               ) -> tuple[NDArray[np.bool_] | None, NDArray[np.bool_] | None]:
        """Which (echo, no-echo) entries of each row are real (None: all of them)."""
        return None, None

    def _pad_detail(self, terms: list[tuple[Array, ...]], parts: list[Array], ll: Array,
                    rd: _Rd) -> tuple[Array, Array]:
        """:meth:`detail` of flat readings (:class:`_Segments` only)."""
        raise NotImplementedError("flat readings: _Segments")

    def _component(self, q: Array, rd: _Rd, grad: bool = False, tier: str | None = None
                   ) -> tuple[tuple[Array, Array, Array, Array], _CompGrad | None]:
        """Per-reading terms of components q (S, 3) local (r, phi, ln kappa):
        echo mean (S, n), variance, log P(echo); no-echo log P(no echo) (S, n_ne); with
        ``grad``, also what the analytic gradient needs (every echo term but the range's
        depends on the parameters through v = ln(kappa g) only), else None."""
        mod = self.cfg.module
        tier = tier or self.tier
        px, py, yaw, npx, npy, nyaw = rd.px, rd.py, rd.yaw, rd.npx, rd.npy, rd.nyaw
        r_, phi_, K_ = q[:, 0:1], q[:, 1:2], np.exp(np.clip(q[:, 2:3], _LNK_LO, _LNK_HI))
        if rd.rows is None:
            r, phi, K = r_, phi_, K_
        else:                                        # flat: each reading its row's values
            r, phi, K = _per_reading((r_, phi_, K_), rd.rows)
        R, theta, geo = _geometry(r, phi, px, py, yaw, self.moving)
        g, dg, lg = M.beam_delay_factor(theta, tier, mod, derivative=grad)
        z = M.detection_z(K, lg, mod)
        et = M.echo_terms(K, g, z, mod, want_info=False, tier=tier)
        waveform = tier == "waveform"
        s2 = M.tof_variance_us2(et.delay, mod, et.delay_var if waveform else None)
        mean = M.us_per_m(mod) * R + et.delay
        ng = None
        has_ne = bool(nyaw.shape[-1])
        if has_ne:
            rn, phin, Kn = ((r, phi, K) if rd.nrows is None else
                            _per_reading((r_, phi_, K_), rd.nrows))
            _, theta_n, ng = _geometry(rn, phin, npx, npy, nyaw, self.ne_moving)
            gn, dgn, lgn = M.beam_delay_factor(theta_n, tier, mod, derivative=grad)
            ne = M.noecho_terms(M.detection_z(Kn, lgn, mod), want_info=False)
            lqn = ne[0]
        else:
            lqn = np.zeros((q.shape[0], 0) if rd.nrows is None else (0,))
        if not grad:
            return (mean, s2, et.log_p, lqn), None
        sa = M.sigma_a(mod)
        u = K * g
        m_v = et.ddelay_du * u                       # d mean / d v, v = ln(kappa g)
        if waveform:
            s2_v = _waveform_var_du(mod, u) * u
        else:
            a = mod.amplitude_fluctuation
            s2_v = 2.0 * a * a * et.delay * m_v
        lp_v = et.dlogp_dz * (1.0 / sa)              # z = (v - ln L) / sigma_a
        dlng = dg / g
        if has_ne:
            lqn_v = ne[1] * (1.0 / sa)
            dlngn = dgn / gn
        else:
            lqn_v = dlngn = lqn
        return (mean, s2, et.log_p, lqn), _CompGrad(m_v, s2_v, lp_v, dlng, geo, lqn_v, dlngn, ng)

    def _components(self, comps: list[Array], rd: _Rd, grad: bool = False
                    ) -> list[tuple[tuple[Array, Array, Array, Array], _CompGrad | None]]:
        """:meth:`_component` of each of ``comps``; two in one call, their rows stacked
        (a call's cost is mostly per-call overhead); rows of several tiers
        (``rd.blocks``) one call per tier, the entries joined."""
        if rd.blocks is None:
            return self._components_tier(comps, rd, grad, self.tier)
        if len(rd.blocks) == 1:
            return self._components_tier(comps, rd.blocks[0][1], grad, rd.blocks[0][0])
        each = [self._components_tier(comps, sub, grad, tier) for tier, sub in rd.blocks]
        return [_join_component([e[k] for e in each]) for k in range(len(comps))]

    def _components_tier(self, comps: list[Array], rd: _Rd, grad: bool, tier: str
                         ) -> list[tuple[tuple[Array, Array, Array, Array], _CompGrad | None]]:
        """:meth:`_components` of rows of one tier."""
        if len(comps) == 1:
            return [self._component(comps[0], rd, grad, tier)]
        S = comps[0].shape[0]
        terms, cg = self._component(np.concatenate(comps), self._doubled(rd), grad, tier)
        # echo and no-echo entries of the first component: its rows, or its flat readings
        ne, nn = (S, S) if rd.rows is None else (rd.y.size, rd.nyaw.size)

        def halves(a: Array, at: int) -> tuple[Array, Array]:
            return a[:at], a[at:]

        (m, s2, lp, lqn) = (halves(terms[0], ne), halves(terms[1], ne),
                            halves(terms[2], ne), halves(terms[3], nn))
        out: list[tuple[tuple[Array, Array, Array, Array], _CompGrad | None]] = [
            ((m[k], s2[k], lp[k], lqn[k]), None) for k in range(2)]
        if cg is None:
            return out

        def geo_halves(geo: M.Geometry | None, at: int) -> list[M.Geometry | None]:
            if geo is None:
                return [None, None]
            f = [halves(a, at) for a in (geo.R, geo.theta, geo.dR_dr, geo.dR_dphi,
                                         geo.dtheta_dr, geo.dtheta_dphi)]
            return [M.Geometry(f[0][k], f[1][k], f[2][k], f[3][k], f[4][k], f[5][k],
                               moving=geo.moving) for k in range(2)]

        e = [halves(a, ne) for a in (cg.m_v, cg.s2_v, cg.lp_v, cg.dlng)]
        n_ = [halves(a, nn) for a in (cg.lqn_v, cg.dlngn)]
        geo, ng = geo_halves(cg.geo, ne), geo_halves(cg.ng, nn)
        return [(out[k][0], _CompGrad(e[0][k], e[1][k], e[2][k], e[3][k], geo[k],
                                      n_[0][k], n_[1][k], ng[k])) for k in range(2)]

    def _doubled(self, rd: _Rd) -> _Rd:
        """The readings of ``rd`` for two components' rows stacked (the first's rows, then
        the second's): flat readings twice over (the last call's again)."""
        if rd.rows is None:
            return rd
        cache: dict[int, tuple[_Rd, _Rd]] = self.__dict__.setdefault("_doubled_rd", {})
        hit = cache.get(id(rd))
        if hit is not None and hit[0] is rd:
            return hit[1]
        assert rd.nrows is not None

        def twice(a: Array) -> Array:
            return np.concatenate([a, a])

        rd2 = _Rd(twice(rd.px), twice(rd.py), twice(rd.yaw), twice(rd.y), twice(rd.npx),
                  twice(rd.npy), twice(rd.nyaw), np.concatenate([rd.rows, rd.rows + rd.S]),
                  np.concatenate([rd.nrows, rd.nrows + rd.S]), 2 * rd.S)
        if len(cache) > 8:           # the readings of the last calls only
            cache.clear()
        cache[id(rd)] = (rd, rd2)
        return rd2

    def cost(self, comps: list[Array], owner: NDArray[np.intp] | None = None) -> Array:
        """Robust -2 log-likelihood (S,) of one or two components, each (S, 3)
        ``(r [m], phi [rad], ln kappa)``; ``owner`` (S,): the segment of each row
        (:class:`_Segments` only)."""
        return self._eval(comps, False, owner)[0]

    def detail(self, comps: list[Array], owner: NDArray[np.intp] | None = None
               ) -> tuple[Array, Array, Array]:
        """:meth:`cost`, the first-echo responsibilities (S, m, n) and the standardised
        residuals (S, n) of the component each echo is assigned to (padding entries of
        :class:`_Segments` rows are meaningless)."""
        return self._eval(comps, True, owner)

    def cost_grad(self, x: Array, owner: NDArray[np.intp] | None = None
                  ) -> tuple[Array, Array]:
        """:meth:`cost` (S,) at scaled points x (S, D) (mm, deg, ln kappa per component,
        as the optimiser sees them) and its analytic gradient by x (S, D).

        The cost is :meth:`cost`'s to the last bit (the same terms); the gradient is the
        chain rule through the per-component terms: every echo term of a component but
        the range's depends on its parameters through v = ln(kappa g(theta)) only, so per
        echo two derivatives (by the range R and by v) of the robust mixture cost carry
        it (tested against central differences). Zero where the cost is off the cliffs
        (replaced by 1e12) and, for ln kappa, outside the clip of :data:`_LNK_LO`..
        :data:`_LNK_HI`.
        """
        x = np.atleast_2d(np.asarray(x, dtype=float))
        comps = _unscale(x)
        rd = self._readings(owner, x.shape[0])
        mask, ne_mask = self._masks(owner)
        y = rd.y if rd.y.ndim == 2 or rd.rows is not None else rd.y[None, :]
        parts: list[_CompGrad] = []
        terms: list[tuple[Array, ...]] = []
        for (mean, s2, log_p, lqn), cg in self._components(comps, rd, grad=True):
            assert cg is not None
            lnorm = -0.5 * (y - mean) ** 2 / s2 - 0.5 * np.log(2.0 * np.pi * s2)
            if ne_mask is not None:
                lqn = np.where(ne_mask, lqn, 0.0)
            terms.append((mean, s2, log_p, lnorm, np.broadcast_to(y, mean.shape),
                          _rowsum(lqn, rd.nrows, rd.S)))
            parts.append(cg)
        mix = self._mixture(terms)
        Ks = [np.exp(np.clip(q[:, 2], _LNK_LO, _LNK_HI)) for q in comps]
        pens = [_kappa_penalty(K, self.cfg) for K in Ks]
        cost, _, _ = self._combine(terms, comps, mask, False, mix, rd, [p[0] for p in pens])
        # per echo: d(-2 ll)/d(mean, variance, log P) of each component
        if len(comps) == 1:
            mean, s2 = terms[0][0], terms[0][1]
            rho = np.exp(mix.parts[0] - mix.ll)
            res = (y - mean) / s2
            d_m = [rho * res]
            d_s2 = [rho * (0.5 * res * res - 0.5 / s2)]
            d_lp = [rho]
        else:
            (ma, sa2, _, _, _, _), (mb, sb2, _, _, _, _) = terms
            t, w, pa, pb = mix.t, mix.w, mix.pa, mix.pb
            assert t is not None and w is not None and pa is not None and pb is not None
            inv_sd = 1.0 / np.sqrt(sa2 + sb2)
            da, db = 1.0 - pb * (1.0 - w), 1.0 - pa * w
            ia = np.where(da > 1e-300, 1.0 / np.maximum(da, 1e-300), 0.0)
            ib = np.where(db > 1e-300, 1.0 / np.maximum(db, 1e-300), 0.0)
            ra, rb = np.exp(mix.parts[0] - mix.ll), np.exp(mix.parts[1] - mix.ll)
            dll_dw = ra * pb * ia - rb * pa * ib
            dw_dm = np.exp(-0.5 * t * t - _LOG_SQRT_2PI) * inv_sd    # d w / d mb
            dw_ds2 = -0.5 * t * dw_dm * inv_sd                      # d w / d sa2 (= sb2)
            res_a, res_b = (y - ma) / sa2, (y - mb) / sb2
            d_m = [ra * res_a - dll_dw * dw_dm, rb * res_b + dll_dw * dw_dm]
            d_s2 = [ra * (0.5 * res_a * res_a - 0.5 / sa2) + dll_dw * dw_ds2,
                    rb * (0.5 * res_b * res_b - 0.5 / sb2) + dll_dw * dw_ds2]
            d_lp = [ra - rb * pa * w * ib, rb - ra * pb * (1.0 - w) * ia]
        tau = M.us_per_m(self.cfg.module)
        S = x.shape[0]
        grad = np.zeros((S, x.shape[1]))
        for k, (q, cg) in enumerate(zip(comps, parts, strict=True)):
            geo, ng = cg.geo, cg.ng
            g_r = -2.0 * tau * d_m[k]                               # d(-2 ll) / d R
            g_v = -2.0 * (d_m[k] * cg.m_v + d_s2[k] * cg.s2_v + d_lp[k] * cg.lp_v)  # / d v
            if mask is not None:
                g_r, g_v = np.where(mask, g_r, 0.0), np.where(mask, g_v, 0.0)
            g_t = g_v * cg.dlng                                     # ... / d theta
            rows, nrows = rd.rows, rd.nrows
            if geo is not None:
                d_r = _rowsum(g_r * geo.dR_dr + g_t * geo.dtheta_dr, rows, S)
                d_phi = _rowsum(g_r * geo.dR_dphi + g_t * geo.dtheta_dphi, rows, S)
            else:                  # seen from the reference position: R = r, theta = phi - yaw
                d_r, d_phi = _rowsum(g_r, rows, S), _rowsum(g_t, rows, S)
            d_lk = _rowsum(g_v, rows, S)
            if cg.lqn_v.shape[-1]:
                gn_v = -2.0 * cg.lqn_v
                if ne_mask is not None:
                    gn_v = np.where(ne_mask, gn_v, 0.0)
                gn_t = gn_v * cg.dlngn
                if ng is not None:
                    d_phi = d_phi + _rowsum(gn_t * ng.dtheta_dphi, nrows, S)
                    d_r = d_r + _rowsum(gn_t * ng.dtheta_dr, nrows, S)
                else:
                    d_phi = d_phi + _rowsum(gn_t, nrows, S)
                d_lk = d_lk + _rowsum(gn_v, nrows, S)
            lk = q[:, 2]
            d_lk = (d_lk + pens[k][1] * Ks[k]) * ((lk > _LNK_LO) & (lk < _LNK_HI))
            for j, d in enumerate((d_r, d_phi, d_lk)):
                grad[:, 3 * k + j] = d * _SCALE[j]
        grad[cost >= 1e12] = 0.0
        return cost, grad

    def _terms(self, comp: tuple[Array, Array, Array, Array], owner: NDArray[np.intp] | None,
               rd: _Rd) -> tuple[Array, ...]:
        """Per-reading terms of a component for the likelihood from its
        :meth:`_component` terms ``comp``: echo mean (S, n), variance, log P(echo), log
        normal density of the reading; the readings (S, n); and the sum of log P(no
        echo) over the no-echo readings (S,)."""
        mean, s2, log_p, lqn = comp
        y = rd.y if rd.y.ndim == 2 or rd.rows is not None else rd.y[None, :]
        lnorm = -0.5 * (y - mean) ** 2 / s2 - 0.5 * np.log(2.0 * np.pi * s2)
        ne_mask = self._masks(owner)[1]
        if ne_mask is not None:
            lqn = np.where(ne_mask, lqn, 0.0)
        return (mean, s2, log_p, lnorm, np.broadcast_to(y, mean.shape),
                _rowsum(lqn, rd.nrows, rd.S))

    def _eval(self, comps: list[Array], detail: bool, owner: NDArray[np.intp] | None
              ) -> tuple[Array, Array, Array]:
        rd = self._readings(owner, comps[0].shape[0])
        terms = [self._terms(comp, owner, rd) for comp, _ in self._components(comps, rd)]
        return self._combine(terms, comps, self._masks(owner)[0], detail, None, rd)

    def _mixture(self, terms: list[tuple[Array, ...]]) -> _Mixture:
        """Per echo (S, n): the log-likelihood of each component being the first echo
        and the robust total, from the components' terms (:meth:`_terms`)."""
        lnorm = [t[3] for t in terms]
        if len(terms) == 1:
            parts = [terms[0][2] + lnorm[0]]
            w = pa = pb = t = None
        else:
            (ma, sa2, lpa, _, _, _), (mb, sb2, lpb, _, _, _) = terms
            # w = P(A's crossing before B's) when both are detected
            t = (mb - ma) / np.sqrt(sa2 + sb2)
            w = ndtr(t)
            pa, pb = np.exp(lpa), np.exp(lpb)
            parts = [lpa + lnorm[0] + np.log(np.maximum(1.0 - pb * (1.0 - w), 1e-300)),
                     lpb + lnorm[1] + np.log(np.maximum(1.0 - pa * w, 1e-300))]
        # a uniform floor exp(-cap / 2) per echo: a spike costs at most about `cap`
        ll = np.logaddexp(parts[0] if len(parts) == 1 else np.logaddexp(parts[0], parts[1]),
                          -0.5 * self.cap)
        return _Mixture(parts, ll, t, w, pa, pb)

    def _combine(self, terms: list[tuple[Array, ...]], comps: list[Array],
                 mask: NDArray[np.bool_] | None, detail: bool, mix: _Mixture | None,
                 rd: _Rd, pens: list[Array] | None = None) -> tuple[Array, Array, Array]:
        """The likelihood from the components' terms (:meth:`_terms`); ``mix``: their
        :meth:`_mixture` if known; ``pens``: the components' kappa prior terms if known."""
        parts, ll = (mix or self._mixture(terms))[:2]
        per = -2.0 * ll
        if mask is not None:
            per = np.where(mask, per, 0.0)
        c = _rowsum(per, rd.rows, rd.S)
        for t in terms:
            c = c - 2.0 * t[5]
        for k, q in enumerate(comps):
            c = c + (pens[k] if pens is not None else
                     _kappa_penalty(np.exp(np.clip(q[:, 2], _LNK_LO, _LNK_HI)), self.cfg)[0])
        c = np.where(np.isfinite(c), c, 1e12)   # off the cliffs: the optimiser backs off
        if not detail:
            return c, np.zeros(0), np.zeros(0)
        if rd.rows is not None:
            # flat readings: responsibilities and residuals padded into (S, m, n) rows
            resp_p, resid_p = self._pad_detail(terms, parts, ll, rd)
            return c, resp_p, resid_p
        resp = np.exp(np.stack(parts, axis=1) - ll[:, None, :])
        pick = np.argmax(resp, axis=1)
        m_all = np.stack([t[0] for t in terms], axis=1)
        s_all = np.stack([t[1] for t in terms], axis=1)
        m_sel = np.take_along_axis(m_all, pick[:, None, :], axis=1)[:, 0]
        s_sel = np.take_along_axis(s_all, pick[:, None, :], axis=1)[:, 0]
        return c, resp, (terms[0][4] - m_sel) / np.sqrt(s_sel)


class _Segments(_Segment):
    """Several segments (of any tiers; all moving or all still, their no-echo readings
    too: segments without any go with either) with their readings end to end in flat
    arrays; every evaluated row says its segment (``owner``) and is
    evaluated on that segment's readings only (gathered per call: no padding, so
    segments of any sizes share every call). A row's cost is that of its segment alone
    (up to the order of the additions)."""

    def __init__(self, segs: Sequence[_Segment]) -> None:
        first = segs[0]
        self.cfg, self.cap = first.cfg, first.cap
        self.tiers = sorted({s.tier for s in segs})
        self.tier = first.tier if len(self.tiers) == 1 else "+".join(self.tiers)
        self.seg_tier = np.array([self.tiers.index(s.tier) for s in segs], dtype=np.intp)
        # segments without no-echo readings go with either kind of no-echo motion
        self.moving = first.moving
        self.ne_moving = any(s.ne_moving for s in segs)
        if any((s.moving, s.cfg) != (self.moving, self.cfg)
               or (s.npx.size and s.ne_moving != self.ne_moving) for s in segs):
            raise ValueError("`segs` must share motion and config")
        self.px, self.py, self.yaw, self.y = (np.concatenate([getattr(s, f) for s in segs])
                                              for f in ("px", "py", "yaw", "y"))
        self.npx, self.npy, self.nyaw = (np.concatenate([getattr(s, f) for s in segs])
                                         for f in ("npx", "npy", "nyaw"))
        self.n_echo = np.array([s.y.size for s in segs])
        self.n_ne = np.array([s.npx.size for s in segs])
        self.off = np.concatenate([[0], np.cumsum(self.n_echo)[:-1]])
        self.ne_off = np.concatenate([[0], np.cumsum(self.n_ne)[:-1]])
        self.sizes = self.n_echo + self.n_ne
        self._last: tuple[NDArray[np.intp], _Rd] | None = None

    @property
    def n(self) -> int:
        raise AttributeError("_Segments: use `sizes` (readings per segment)")

    @staticmethod
    def _gather(off: NDArray[np.intp], size: NDArray[np.intp], owner: NDArray[np.intp]
                ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.intp]]:
        """Indices of the readings of rows ``owner`` (N,), the row of each and its
        position within the row."""
        length = size[owner]
        rows = np.repeat(np.arange(owner.size), length)
        ends = np.cumsum(length)
        pos = np.arange(int(ends[-1]) if ends.size else 0) - np.repeat(ends - length, length)
        return np.repeat(off[owner], length) + pos, rows, pos

    def _readings(self, owner: NDArray[np.intp] | None, S: int) -> _Rd:
        if owner is None:
            raise ValueError("_Segments needs the `owner` of every row")
        owner = np.asarray(owner, dtype=np.intp)
        # the last call's readings again (consecutive quasi-Newton steps mostly
        # evaluate the same rows)
        if self._last is not None and np.array_equal(self._last[0], owner):
            return self._last[1]
        T = len(self.tiers)
        rt = self.seg_tier[owner]
        # rows of several tiers: each tier's entries together (each row's in its order)
        perm = np.argsort(rt, kind="stable") if T > 1 else np.arange(owner.size)
        ie, rows, _ = self._gather(self.off, self.n_echo, owner[perm])
        inn, nrows, _ = self._gather(self.ne_off, self.n_ne, owner[perm])
        rows, nrows = perm[rows], perm[nrows]
        none = np.zeros(0)
        rd = _Rd(self.px[ie] if self.moving else none, self.py[ie] if self.moving else none,
                 self.yaw[ie], self.y[ie], self.npx[inn] if self.ne_moving else none,
                 self.npy[inn] if self.ne_moving else none, self.nyaw[inn], rows, nrows, S)
        if T > 1:
            n_rows = np.bincount(rt, minlength=T)
            ends_e = np.cumsum(np.bincount(rt, weights=self.n_echo[owner], minlength=T))
            ends_n = np.cumsum(np.bincount(rt, weights=self.n_ne[owner], minlength=T))
            blocks = []
            for t in np.flatnonzero(n_rows).tolist():
                e = slice(int(ends_e[t - 1]) if t else 0, int(ends_e[t]))
                n = slice(int(ends_n[t - 1]) if t else 0, int(ends_n[t]))
                blocks.append((self.tiers[t], _Rd(
                    rd.px[e] if self.moving else none, rd.py[e] if self.moving else none,
                    rd.yaw[e], rd.y[e], rd.npx[n] if self.ne_moving else none,
                    rd.npy[n] if self.ne_moving else none, rd.nyaw[n], rows[e], nrows[n],
                    S)))
            rd = rd._replace(blocks=tuple(blocks))
        self._last = (owner.copy(), rd)
        return rd

    def _pad_detail(self, terms: list[tuple[Array, ...]], parts: list[Array], ll: Array,
                    rd: _Rd) -> tuple[Array, Array]:
        """:meth:`detail`'s responsibilities (S, m, n) and residuals (S, n) of flat
        readings, padded (zeros) to the longest row."""
        assert rd.rows is not None
        rows = rd.rows
        count = np.bincount(rows, minlength=rd.S)
        pos = np.empty(rows.size, dtype=np.intp)   # each entry's place in its row
        pos[np.argsort(rows, kind="stable")] = (np.arange(rows.size)
                                                - np.repeat(np.cumsum(count) - count, count))
        width = int(pos.max()) + 1 if pos.size else 0
        resp_f = np.exp(np.stack(parts, axis=0) - ll[None, :])      # (m, N)
        pick = np.argmax(resp_f, axis=0)
        m_all = np.stack([t[0] for t in terms], axis=0)
        s_all = np.stack([t[1] for t in terms], axis=0)
        idx = np.arange(rows.size)
        resid_f = (terms[0][4] - m_all[pick, idx]) / np.sqrt(s_all[pick, idx])
        resp = np.zeros((rd.S, len(parts), width))
        resid = np.zeros((rd.S, width))
        for k in range(len(parts)):
            resp[rows, k, pos] = resp_f[k]
        resid[rows, pos] = resid_f
        return resp, resid

    def _masks(self, owner: NDArray[np.intp] | None
               ) -> tuple[NDArray[np.bool_] | None, NDArray[np.bool_] | None]:
        return None, None


_Terms = tuple[tuple[Array, Array, Array, Array], _CompGrad | None]


def _join_component(parts: list[_Terms]) -> _Terms:
    """One component's :meth:`_Segment._component` terms of flat readings from those of
    consecutive blocks of its entries (:attr:`_Rd.blocks`)."""
    terms = tuple(np.concatenate([p[0][j] for p in parts]) for j in range(4))
    cgs = [p[1] for p in parts]
    if any(cg is None for cg in cgs):
        return (terms[0], terms[1], terms[2], terms[3]), None
    cs = [cg for cg in cgs if cg is not None]

    def cat(name: str) -> Array:
        return np.concatenate([getattr(cg, name) for cg in cs])

    def geo(name: str) -> M.Geometry | None:
        gs = [getattr(cg, name) for cg in cs]
        real = [g for g in gs if g is not None]
        if not real:
            return None
        # a block without such readings has none (its arrays are empty)
        f = [np.concatenate([getattr(g, n) for g in real]) for n in (
            "R", "theta", "dR_dr", "dR_dphi", "dtheta_dr", "dtheta_dphi")]
        return M.Geometry(f[0], f[1], f[2], f[3], f[4], f[5])

    return ((terms[0], terms[1], terms[2], terms[3]),
            _CompGrad(cat("m_v"), cat("s2_v"), cat("lp_v"), cat("dlng"), geo("geo"),
                      cat("lqn_v"), cat("dlngn"), geo("ng")))


def _per_reading(cols: tuple[Array, ...], rows: NDArray[np.intp]) -> tuple[Array, ...]:
    """Each (S, 1) column's value at every flat reading (N,), ``rows`` the row of each
    (``np.take`` of the column: the same values as ``col[rows, 0]``, a third of its time
    on a pair call's ~10,000 readings)."""
    return tuple(np.take(c[:, 0], rows) for c in cols)


def _geometry(r: Array, phi: Array, px: Array, py: Array, yaw: Array, moving: bool
              ) -> tuple[Array, Array, M.Geometry | None]:
    """Range and off-axis angle of point components (r, phi) (S, 1) at readings (S, n)
    or (n,), and the full :func:`sonarloc.fit.model.geometry` (with derivatives) where
    the transducer moved; from the reference position R = r and theta = phi - yaw (the
    same numbers as the full geometry's, without building its derivative arrays)."""
    if moving:
        geo = M.geometry("point", r, phi, px, py, yaw, moving=True)
        return geo.R, geo.theta, geo
    return r, M._wrap_fast(phi - yaw), None


def _unscale(x: Array) -> list[Array]:
    """Scaled (S, 3m) optimiser variables -> components (S, 3) in (m, rad, ln kappa)."""
    x = np.atleast_2d(x)
    return [x[:, 3 * k:3 * k + 3] * _SCALE for k in range(x.shape[1] // 3)]


_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)


def _waveform_var_du(mod: ModuleParams, u: Array) -> Array:
    """d/du of the waveform tier's delay variance (the ``delay_var`` of
    :func:`sonarloc.fit.model.echo_terms`) at eq. 3 delays u: the table is linear in
    ln u per cell, (0.25 u)^2 below it, constant above."""
    tab = M.waveform_delay_table(mod)
    coef = tab.coef
    n = coef.shape[0]
    t = (np.log(np.maximum(u, 1e-300)) - tab.x0) * (1.0 / tab.dx)
    i = np.minimum(np.clip(t, 0.0, n).astype(np.intp), n - 1)
    d = np.take(coef[:, 5], i) * (1.0 / tab.dx) / np.maximum(u, 1e-300)
    return np.where(t < 0.0, 0.125 * u, np.where(t > n, 0.0, d))


def _minimise(seg: _Segment, x0: Array, fixed: int | None = None, maxiter: int = 60
              ) -> tuple[Array, float]:
    """Quasi-Newton (BFGS) on the scaled variables with the analytic gradient;
    ``fixed``: index of a variable held at its start value (for profiles)."""
    xs, cs = _minimise_batch(seg, x0[None, :], None if fixed is None else [fixed], maxiter)
    return xs[0], float(cs[0])


def _minimise_batch(seg: _Segment, x0: Array, fixed: Sequence[int | None] | None = None,
                    maxiter: int = 60, gtol: float = 1e-2,
                    owner: NDArray[np.intp] | None = None) -> tuple[Array, Array]:
    """BFGS from several starts in lockstep: every call of :meth:`_Segment.cost_grad`
    evaluates the next trial point of every unfinished start with its analytic gradient
    (the first of a new step, or a shorter one where its line search backtracks: each
    start's line search runs on its own, so backtracking starts cost no calls of their
    own). The cost of a call is mostly per-call overhead, so S starts cost about as
    much as one; each start's path is the one it would take alone.

    Parameters
    ----------
    x0 : (S, D) scaled starts (mm, deg, ln kappa per component).
    fixed : per start, an index held at its start value (profiles), or None.
    maxiter : BFGS iterations per start; ``gtol``: stop when the largest free gradient
        component is below this (-2 log-likelihood per scaled unit).
    owner : (S,) the segment of each start when ``seg`` is a :class:`_Segments` (the
        starts of many segments then share every call; each start's path is the one it
        would take alone).

    Returns
    -------
    (S, D) optima (ln kappa clipped into the prior's reach) and (S,) their costs.
    """
    x = np.array(x0, dtype=float, copy=True)
    S, D = x.shape
    free = np.ones((S, D), dtype=bool)
    for s, fix in enumerate(fixed or [None] * S):
        if fix is not None:
            free[s, fix] = False

    def evaluate(pts: Array, rows: NDArray[np.intp]) -> tuple[Array, Array]:
        c, g = seg.cost_grad(pts, None if owner is None else owner[rows])
        return c, np.where(free.take(rows, axis=0), g, 0.0)

    rows_all = np.arange(S)
    f, g = evaluate(x, rows_all)
    Hinv = np.tile(np.eye(D), (S, 1, 1)) * free[:, :, None] * free[:, None, :]
    first = np.ones(S, dtype=bool)
    active = np.abs(g).max(1) > gtol
    it = np.zeros(S, dtype=int)
    # each row's line search (backtracking, Armijo, at most 12 trials) runs on its own:
    # every call evaluates the next trial point of every active row, the first of a new
    # step or a shorter one, so a row that backtracks costs no call of its own
    p = np.zeros((S, D))
    slope, alpha = np.zeros(S), np.zeros(S)
    tries = np.zeros(S, dtype=int)               # trials of the row's current step
    while active.any():
        new = np.flatnonzero(active & (tries == 0))
        if new.size:
            # (row gathers by ndarray.take: a third of the fancy index's cost)
            gn = g.take(new, axis=0)
            pn = -np.einsum("sij,sj->si", Hinv.take(new, axis=0), gn)
            sl = np.einsum("si,si->s", pn, gn)
            bad = ~(sl < 0)                      # not a descent direction: steepest descent
            pn[bad] = -gn[bad]
            sl[bad] = -np.einsum("si,si->s", gn[bad], gn[bad])
            p[new], slope[new] = pn, sl
            alpha[new] = np.where(first[new], np.minimum(1.0, 1.0 / np.maximum(
                np.linalg.norm(pn, axis=1), 1e-300)), 1.0)
        k = np.flatnonzero(active)
        trial = x.take(k, axis=0) + alpha[k, None] * p.take(k, axis=0)
        ft, gt = evaluate(trial, k)
        ok = ft <= f[k] + 1e-4 * alpha[k] * slope[k]
        tries[k] += 1
        alpha[k[~ok]] *= 0.3
        end = ok | (tries[k] >= 12)              # the rows whose step ends here
        if not end.any():
            continue
        rows, moved = k[end], ok[end]
        tries[rows] = 0
        x_old, g_old = x.take(rows, axis=0), g.take(rows, axis=0)
        x_new, f_new, g_new = x_old.copy(), f[rows], g_old.copy()
        x_new[moved], f_new[moved], g_new[moved] = (trial[end][moved], ft[end][moved],
                                                    gt[end][moved])
        sv = x_new - x_old
        yv = g_new - g_old
        sy = np.einsum("si,si->s", sv, yv)
        upd = np.flatnonzero(moved & (sy > 1e-12))
        for j in upd[first[rows[upd]]].tolist():   # scale the initial inverse Hessian
            Hinv[rows[j]] *= sy[j] / float(yv[j] @ yv[j])
        if upd.size:                             # the BFGS update of all rows at once
            r, s_, y_ = rows[upd], sv[upd], yv[upd]
            rho = (1.0 / sy[upd])[:, None, None]
            V = np.eye(D) - rho * (s_[:, :, None] * y_[:, None, :])
            Hinv[r] = (V @ Hinv.take(r, axis=0) @ np.swapaxes(V, 1, 2)
                       + rho * (s_[:, :, None] * s_[:, None, :]))
        first[rows[moved]] = False
        f_old = f[rows]
        x[rows], f[rows], g[rows] = x_new, f_new, g_new
        it[rows] += 1
        # converged: small gradient, or a step that no longer lowers the cost by FTOL
        done = ((~moved) | (np.abs(g_new).max(1) <= gtol) | (it[rows] >= maxiter)
                | (f_old - f_new < FTOL))
        active[rows[done]] = False
    # ln kappa within the prior's reach (it is soft; keep the optimiser off the cliffs)
    lk = x[:, 2::3]
    clipped = np.clip(lk, math.log(seg.cfg.kappa_min_us), math.log(1e3))
    if np.any(clipped != lk):
        x[:, 2::3] = clipped
        f = np.asarray(seg.cost(_unscale(x), owner))
    return x, np.asarray(f, dtype=float)


FTOL = 1e-4
"""A quasi-Newton step lowering -2 log-likelihood by less than this ends the search."""

SCREEN_ITER = 8
"""Quasi-Newton iterations before the screen. The screen runs two starts of every
candidate: its best grid start and its single fit split in two; the other grid
starts run only for the candidates it passes, whose search is then the one from all
starts (half the screen's work of running them all). Measured on 354 candidates (the 243
of bench_fit section 4, close-pair pans of both tiers at 10-24 deg): the two passed
every candidate whose pair reached the bar (54 accepted; after the screen's
iterations the best grid start led in 34 of them, the other grid starts in 19)."""

SCREEN_MARGIN = 12.0
"""A candidate whose pair gains less than ``max(BIC price, MIN_GAIN) - SCREEN_MARGIN``
after ``SCREEN_ITER`` iterations is rejected there: the remaining iterations added at
most 4.3 (-2 log-likelihood; measured on 91 candidates, close pairs and a continuous-
rotation scan), so it could not reach the bar."""


PROFILE_STEPS = (-1.0, -0.4, 0.4, 1.0)
"""Steps in ln kappa of the profile that measures each bearing's real spread."""


def _profile_bearing_sds(seg: _Segment, x: Array, c: float) -> list[float]:
    """Bearing SD [rad] of each component along its kappa profile.

    Bearing and kappa of a reflector whose inner arm is hidden by the other trade off
    along a curved ridge the local (Hessian) covariance misses: hold ln kappa at a few
    steps away, refit the rest, and take the largest bearing shift per unit of
    sqrt(-2 log-likelihood rise) (exact for a Gaussian likelihood). All profile points
    of both components are refitted together (:func:`_minimise_batch`).
    """
    return _profile_bearing_sds_batch(seg, x[None, :], np.array([c]), None)[0]


def _profile_bearing_sds_batch(seg: _Segment, xs: Array, cs: Array,
                               owner: NDArray[np.intp] | None) -> list[list[float]]:
    """:func:`_profile_bearing_sds` of several optima xs (P, 6) with costs cs (P,) (of
    segments ``owner`` (P,) of a :class:`_Segments`), all profile points in one search."""
    starts, fixed, comp, row = [], [], [], []
    for p, x in enumerate(xs):
        for k in range(2):
            for step in PROFILE_STEPS:
                x0 = x.copy()
                x0[3 * k + 2] += step
                starts.append(x0)
                fixed.append(3 * k + 2)
                comp.append(k)
                row.append(p)
    own = None if owner is None else owner[np.array(row)]
    xp, cp = _minimise_batch(seg, np.array(starts), fixed, owner=own)
    sds = [[0.0, 0.0] for _ in range(len(xs))]
    for j, (k, p) in enumerate(zip(comp, row, strict=True)):
        dphi = math.radians(float(xp[j, 3 * k + 1] - xs[p, 3 * k + 1]))
        rise = max(float(cp[j]) - float(cs[p]), 1e-3)
        sds[p][k] = max(sds[p][k], abs(dphi) / math.sqrt(rise))
    return sds


def _hessian(seg: _Segment, x: Array, h: float = 1e-2) -> Array:
    """Central-difference Hessian of the cost in the scaled variables (one batch call)."""
    return _hessian_batch(seg, x[None, :], None, h)[0]


def _hessian_batch(seg: _Segment, xs: Array, owner: NDArray[np.intp] | None,
                   h: float = 1e-2) -> Array:
    """:func:`_hessian` at several points xs (P, d) (of segments ``owner`` (P,) of a
    :class:`_Segments`) in one cost call; (P, d, d)."""
    P_, d = xs.shape
    E = np.eye(d) * h
    offs = [np.zeros(d)]
    for i in range(d):
        offs += [E[i], -E[i]]
    for i in range(d):
        for j in range(i + 1, d):
            offs += [E[i] + E[j], E[i] - E[j], -E[i] + E[j], -E[i] - E[j]]
    O = np.array(offs)                                   # (m, d)
    pts = (xs[:, None, :] + O[None, :, :]).reshape(-1, d)
    own = None if owner is None else np.repeat(owner, O.shape[0])
    c_all = np.asarray(seg.cost(_unscale(pts), own)).reshape(P_, O.shape[0])
    out = np.zeros((P_, d, d))
    for p in range(P_):
        c = c_all[p]
        H = out[p]
        f0 = c[0]
        for i in range(d):
            H[i, i] = (c[1 + 2 * i] - 2.0 * f0 + c[2 + 2 * i]) / (h * h)
        k = 1 + 2 * d
        for i in range(d):
            for j in range(i + 1, d):
                pp, pm, mp, mm = c[k:k + 4]
                H[i, j] = H[j, i] = (pp - pm - mp + mm) / (4.0 * h * h)
                k += 4
    return out


_Grid = tuple[Array, NDArray[np.intp], NDArray[np.intp]]


def _starts(seg: _Segment, single: Array, n_starts: int) -> list[Array]:
    """Best bearing pairs of a grid, each with (To, kappa) of both components solved
    linearly (echoes assigned to the component nearer their beam axis)."""
    grid = _start_grid(seg, single)
    if grid is None:
        return []
    return _pick_starts(np.asarray(seg.cost(_unscale(grid[0]))), grid, n_starts)


def _start_grid(seg: _Segment, single: Array) -> _Grid | None:
    """The :data:`N_CANDIDATES` best nodes of :func:`_starts`'s grid by the linear solves:
    scaled points (k, 6) and their node indices (a, b); None if none is bracketed."""
    return _start_grids([seg], [single])[0]


GRID_CHUNK = 150_000
"""Elements (segments x bearing pairs x echoes) of one step of :func:`_start_grids`."""


def _start_grids(segs: Sequence[_Segment], singles: Sequence[Array]) -> list[_Grid | None]:
    """:func:`_start_grid` of several segments of one tier (all moving or all still),
    the linear solves of all of them at once: their bearing nodes (J per segment) and
    echoes padded into (C, J, n) arrays, in chunks of about :data:`GRID_CHUNK` (the
    work of one segment's grid is mostly per-call overhead). Each segment's result is
    the one it would get alone up to the rounding of the sums (padding adds zeros)."""
    C = len(segs)
    if C == 0:
        return []
    first = segs[0]
    mod = first.cfg.module
    tau = M.us_per_m(mod)
    step = math.radians(GRID_STEP_DEG)
    margin = math.radians(3.0)
    sizes = np.array([seg.yaw.size for seg in segs])
    if sizes.min() == 0:
        raise ValueError("every segment of _start_grids needs echoes")
    phi = np.array([float(sg[1]) for sg in singles])
    own = np.repeat(np.arange(C), sizes)
    rel = M.wrap_angle(np.concatenate([seg.yaw for seg in segs]) - phi[own])   # echo axes
    first_e = np.concatenate([[0], np.cumsum(sizes)[:-1]])                    # relative
    lo = np.minimum.reduceat(rel, first_e) - margin
    hi = np.maximum.reduceat(rel, first_e) + margin
    # np.arange(lo, hi + 1e-9, step) of every segment (its length and its values:
    # start, start + step, then start + i * ((start + step) - start))
    Jc = np.ceil((hi + 1e-9 - lo) / step).astype(np.intp)
    i = np.arange(int(Jc.max()), dtype=float)
    steps = lo[:, None] + i[None, :] * ((lo + step) - lo)[:, None]
    if steps.shape[1] > 1:
        steps[:, 1] = lo + step
    steps[:, 0] = lo
    nodes_all = phi[:, None] + steps
    nodes_l = [nodes_all[c, :Jc[c]] for c in range(C)]
    nc = np.array([seg.y.size for seg in segs])
    out: list[_Grid | None] = [None] * C
    # chunks of segments of similar size (sorted by J n) so the padding stays small
    order = np.argsort(Jc * Jc * nc, kind="stable")
    start = 0
    while start < C:
        stop = start + 1
        while (stop < C and (stop + 1 - start) * int(Jc[order[stop]]) ** 2 // 2
               * int(nc[order[start:stop + 1]].max()) <= GRID_CHUNK):
            stop += 1
        idx = order[start:stop].tolist()
        for c, grid in zip(idx, _grid_chunk([segs[c] for c in idx],
                                            [singles[c] for c in idx],
                                            [nodes_l[c] for c in idx], tau), strict=True):
            out[c] = grid
        start = stop
    return out


def _grid_chunk(segs: Sequence[_Segment], singles: Sequence[Array], nodes_l: list[Array],
                tau: float) -> list[_Grid | None]:
    """The linear solves of :func:`_start_grids` for one chunk of segments."""
    first = segs[0]
    mod = first.cfg.module
    C = len(segs)
    J = max(v.size for v in nodes_l)
    n = max(seg.y.size for seg in segs)
    Jc = np.array([v.size for v in nodes_l])
    nodes = np.zeros((C, J))
    px, py, yaw, y = (np.zeros((C, n)) for _ in range(4))
    ok_e = np.zeros((C, n), dtype=bool)
    for c, (seg, v) in enumerate(zip(segs, nodes_l, strict=True)):
        nodes[c, :v.size] = v
        nodes[c, v.size:] = v[-1]
        m = seg.y.size
        px[c, :m], py[c, :m], yaw[c, :m], y[c, :m] = seg.px, seg.py, seg.yaw, seg.y
        ok_e[c, :m] = True
    r0 = np.array([float(s[0]) for s in singles])
    R, theta, _ = _geometry(r0[:, None, None], nodes[:, :, None], px[:, None, :],
                            py[:, None, :], yaw[:, None, :], first.moving)
    g, _, _ = M.beam_delay_factor(theta, first.tier, mod, derivative=False)
    g_cap = 1e6 * math.exp(0.5 * M.sigma_a(mod) ** 2)
    g = np.minimum(g, 1e6) * math.exp(0.5 * M.sigma_a(mod) ** 2)      # (C, J, n)
    if first.moving:
        yy = y[:, None, :] - tau * (R - r0[:, None, None])            # (C, J, n): To + kappa g
    else:                                             # R = r0: the readings themselves
        yy = y[:, None, :]                            # (C, 1, n): the same at every node
    ja, jb = np.triu_indices(J, k=2)
    # centred readings: the sums of y are then small (the solves better conditioned)
    y0 = np.array([float(seg.y.mean()) for seg in segs])
    yy = yy - y0[:, None, None]
    sums = _grid_sums(g, yy, ok_e, Jc, ja, jb, g_cap)
    cost = np.zeros((C, ja.size))
    sols = np.zeros((C, ja.size, 4))
    for k, (S0, S1, S2, Sy, Sgy, Syy) in enumerate(sums):
        det = S0 * S2 - S1 * S1
        ok = (det > 1e-12 * np.maximum(S0 * S2, 1e-300)) & (S0 >= 3)
        det = np.where(ok, det, 1.0)
        to = (S2 * Sy - S1 * Sgy) / det
        kap = (S0 * Sgy - S1 * Sy) / det
        ssr = Syy - to * Sy - kap * Sgy
        cost = cost + np.where(ok & (kap > 0), ssr, np.inf)
        sols[:, :, 2 * k] = to + y0[:, None]
        sols[:, :, 2 * k + 1] = np.where(kap > 0, kap, 1.0)
    cost[jb[None, :] >= Jc[:, None]] = np.inf         # pairs beyond a segment's nodes
    kmin = first.cfg.kappa_min_us
    order = np.argsort(cost, axis=1)[:, :N_CANDIDATES]          # (C, k) best first
    n_fin = np.isfinite(np.take_along_axis(cost, order, axis=1)).sum(1)
    a, b = ja[order], jb[order]
    so = np.take_along_axis(sols, order[:, :, None], axis=1)    # (C, k, 4)
    cc = np.arange(C)[:, None]
    xs = np.stack([so[..., 0] / tau / _SCALE[0], nodes[cc, a] / _SCALE[1],
                   np.log(np.maximum(so[..., 1], kmin)),
                   so[..., 2] / tau / _SCALE[0], nodes[cc, b] / _SCALE[1],
                   np.log(np.maximum(so[..., 3], kmin))], axis=2)
    return [(xs[c, :k], a[c, :k], b[c, :k]) if k else None
            for c, k in enumerate(n_fin.tolist())]


_Sums = tuple[Array, Array, Array, Array, Array, Array]


def _grid_sums(g: Array, yy: Array, ok_e: NDArray[np.bool_], Jc: NDArray[np.intp],
               ja: NDArray[np.intp], jb: NDArray[np.intp], g_cap: float = math.inf
               ) -> tuple[_Sums, _Sums]:
    """Sums of the grid's 2x2 linear solves for bearing pairs (ja, jb) (P,) of C
    segments: each echo is assigned to the component with the smaller delay factor (A
    on a tie); per component (count, sum g, sum g^2, sum y, sum g y, sum y^2) over its
    echoes, each (C, P). ``g``, ``yy``: (C, J, n) delay factors and To + kappa g
    readings per bearing node ((C, 1, n) where they are the same at every node); ``ok_e``:
    (C, n) real echoes; ``Jc``: (C,) real nodes.

    Where every pair's assignment splits the echoes at one place of one order (A's
    echoes first: the order of g at the first node minus g at the last, e.g. a pan over
    a beam that falls off with the angle) the sums are cumulative sums, O(C J n)
    instead of O(C P n); the split is checked on the assignment itself, and segments
    where it fails get the direct masked sums, as do those where some delay factor
    reaches ``g_cap`` (the grid's cap: echoes far from both nodes tie there and go to
    A whichever side they are on, so that assignment is no split). Same sums up to
    the order of the additions."""
    C, J, n = g.shape
    P_ = ja.size
    A = [np.zeros((C, P_)) for _ in range(6)]
    B = [np.zeros((C, P_)) for _ in range(6)]
    # delay factors at the cap tie (A takes both): such assignments are no split
    capped = ((g >= g_cap) & ok_e[:, None, :]).any(axis=(1, 2))
    direct = np.flatnonzero(capped)
    tr = np.flatnonzero(~capped)
    if tr.size:
        Ct = tr.size
        gt, yt, okt = g[tr], yy[tr], ok_e[tr]
        cc = np.arange(Ct)
        key = np.where(okt, gt[:, 0, :] - gt[cc, Jc[tr] - 1, :], np.inf)  # padding last
        order = np.argsort(key, axis=1, kind="stable")
        gs = np.take_along_axis(gt, order[:, None, :], axis=2)
        ys = np.take_along_axis(yt, order[:, None, :], axis=2)
        oks = np.take_along_axis(okt, order, axis=1)
        gs = np.where(oks[:, None, :], gs, 0.0)
        ys = np.where(oks[:, None, :], ys, 0.0)
        to_a = gs[:, ja] <= gs[:, jb]                 # (Ct, P, n) the assignment
        to_a &= oks[:, None, :]
        real = jb[None, :] < Jc[tr][:, None]          # (Ct, P)
        split = (~(to_a[:, :, 1:] & ~to_a[:, :, :-1]).any(2) | ~real).all(1)
        n_a = to_a.sum(2)                             # A's echoes: the first n_a
        nc = oks.sum(1)
        A[0][tr] = n_a
        B[0][tr] = nc[:, None] - n_a
        for q, v in enumerate((gs, gs * gs, ys, gs * ys, ys * ys), start=1):
            head = np.zeros((Ct, J, n + 1))
            np.cumsum(v, axis=2, out=head[:, :, 1:])
            tail = np.zeros((Ct, J, n + 1))           # sums from k to the end
            np.cumsum(v[:, :, ::-1], axis=2, out=tail[:, :, 1:])
            tail = tail[:, :, ::-1]
            per_node = v.shape[1] > 1                 # else the readings alone (a pan)
            A[q][tr] = head[cc[:, None], ja[None, :] if per_node else 0, n_a]
            B[q][tr] = tail[cc[:, None], jb[None, :] if per_node else 0, n_a]
        direct = np.concatenate([direct, tr[~split]])
    if direct.size:                                   # not a split: the direct sums
        sa, sb = _direct_sums(g[direct], yy[direct], ok_e[direct])
        for q in range(6):
            A[q][direct] = sa[:, ja, jb, q]
            B[q][direct] = sb[:, jb, ja, q]
    return (A[0], A[1], A[2], A[3], A[4], A[5]), (B[0], B[1], B[2], B[3], B[4], B[5])


def _direct_sums(g: Array, yy: Array, ok_e: NDArray[np.bool_]) -> tuple[Array, Array]:
    """:func:`_grid_sums` of every ordered node pair written out, as matrix products:
    (C, J, J, 6) sums over the echoes A takes at node a paired with node b (``[:, a,
    b]``: g at a <= g at b) and over those B takes at node b paired with node a (``[:,
    b, a]``: g at b < g at a), each of (1, g, g^2, y, g y, y^2) at the taking node. A
    product per node evaluates all its pairs at once (the pairs' masked sums over
    (C, P, n) arrays cost about three times as much; a moving segment's delay factors
    reach the cap, so its assignments are no split). The assignments are formed for
    blocks of nodes of about :data:`GRID_CHUNK` elements (C, block, J, n)."""
    C, J, n = g.shape
    y = yy if yy.shape[1] > 1 else np.broadcast_to(yy, g.shape)
    w = ok_e[:, None, :].astype(float)
    gw, yw = g * w, y * w
    V = np.stack([np.broadcast_to(w, g.shape), gw, gw * g, yw, gw * y, yw * y], axis=3)
    sa, sb = np.zeros((C, J, J, 6)), np.zeros((C, J, J, 6))
    step = max(GRID_CHUNK // max(C * J * n, 1), 1)
    for lo in range(0, J, step):
        at = slice(lo, lo + step)
        takes_a = (g[:, at, None, :] <= g[:, None, :, :]).astype(float)  # (C, a, b, n)
        takes_b = (g[:, at, None, :] < g[:, None, :, :]).astype(float)   # (C, b, a, n)
        sa[:, at] = np.matmul(takes_a, V[:, at])
        sb[:, at] = np.matmul(takes_b, V[:, at])
    return sa, sb


def _pick_starts(full: Array, grid: _Grid, n_starts: int) -> list[Array]:
    """The ``n_starts`` best grid points by the full likelihood ``full`` (k,), no two
    on neighbouring nodes."""
    xs, a, b = grid
    best: list[Array] = []
    taken: list[tuple[int, int]] = []
    for k in np.argsort(full).tolist():
        ak, bk = int(a[k]), int(b[k])
        if any(abs(ak - a2) <= 1 and abs(bk - b2) <= 1 for a2, b2 in taken):
            continue
        taken.append((ak, bk))
        best.append(xs[k])
        if len(best) >= n_starts:
            break
    return best


COST_CHUNK = 1024
"""Rows of one cost call when ranking the grid starts (arrays that stay in cache)."""


def _fit_pairs(segs: Sequence[_Segment], singles: Sequence[Array],
               n_starts: int = N_STARTS) -> list[PairFit]:
    """Fit one and two point reflectors to each of several segments of any tiers (all
    moving or all still), every search step of all of them in one cost call
    (:class:`_Segments`); candidates whose pair provably cannot gain the bar over their
    single fit (:func:`_pair_cost_floor`) are not searched (:func:`_bounded`)."""
    C = len(segs)
    cfg = segs[0].cfg
    ev: _Segment = segs[0] if C == 1 else _Segments(segs)
    every = np.arange(C)
    s0 = np.array([[s[0] / _SCALE[0], s[1] / _SCALE[1],
                    math.log(max(float(s[2]), cfg.kappa_min_us))] for s in singles])
    c0 = np.asarray(ev.cost(_unscale(s0), None if C == 1 else every))
    price = np.array([3.0 * math.log(max(seg.n, 2)) for seg in segs])
    bar = np.maximum(price, MIN_GAIN)
    bound = c0 - _pair_cost_floor(segs)     # no pair gains more
    hopeless = bound <= bar
    out: list[PairFit | None] = [
        _bounded(c0[c], bound[c], price[c], bar[c]) if hopeless[c] else None
        for c in range(C)]
    keep = np.flatnonzero(~hopeless)
    if keep.size:
        kept = keep.tolist()
        for c, pf in zip(kept, _search_pairs(
                ev, None if C == 1 else keep, [segs[c] for c in kept],
                [singles[c] for c in kept], s0[keep], c0[keep], price[keep], bar[keep],
                n_starts), strict=True):
            out[c] = pf
    return [pf for pf in out if pf is not None]


def _pair_cost_floor(segs: Sequence[_Segment]) -> Array:
    """(C,) a lower bound of each segment's two-reflector cost (:meth:`_Segment.cost`)
    whatever the components' parameters: ``n_echo`` times the least cost of one echo,
    less 1e-9 per echo for the rounding of the computed costs.

    Proof: an echo's mixture density ``f_A P_A (1 - P_B (1 - w)) + f_B P_B (1 - P_A w)``
    is at most ``max(f_A, f_B) (P_A + P_B - P_A P_B) <= max(f_A, f_B)``, and a normal
    density is at most ``1 / sqrt(2 pi s2)`` with the TOF variance ``s2`` at least its
    zero-delay value (:func:`sonarloc.fit.model.tof_variance_us2`: jitter and counting
    plus a non-negative delay term; the waveform tier's delay variance is interpolated
    between non-negative nodes). With the floor ``exp(-cap / 2)`` an echo then costs at
    least ``-2 log(1 / sqrt(2 pi s2(0)) + exp(-cap / 2))``; the no-echo terms
    ``-2 log((1 - P_A)(1 - P_B))`` and the kappa prior are non-negative. So no pair gains
    more than ``cost_single - floor`` over a single fit of cost ``cost_single``.
    """
    first = segs[0]
    lb = -2.0 * float(np.logaddexp(
        -0.5 * math.log(2.0 * math.pi * float(M.tof_variance_us2(0.0, first.cfg.module))),
        -0.5 * first.cap))
    return np.array([seg.y.size for seg in segs]) * (lb - 1e-9)


def _bounded(c0: float, bound: float, price: float, bar: float) -> PairFit:
    """The result of a candidate whose pair cannot reach the bar (:func:`_pair_cost_floor`):
    not searched; ``cost_pair`` the floor (so ``gain`` is the bound), fitted values NaN."""
    nan2 = np.full(2, np.nan)
    return PairFit(np.full((2, 3), np.nan), np.full((2, 3, 3), np.nan), float(c0),
                   float(c0 - bound), nan2, nan2.copy(), float(price), False,
                   f"two reflectors cannot fit enough better than one: -2 log-likelihood "
                   f"gain at most {bound:.1f} (no echo more likely than at zero delay) <= "
                   f"{bar:.1f}", nan2.copy(), hidden=nan2.copy())


def _search_pairs(ev: _Segment, idx: NDArray[np.intp] | None, segs: Sequence[_Segment],
                  singles: Sequence[Array], s0: Array, c0: Array, price: Array, bar: Array,
                  n_starts: int) -> list[PairFit]:
    """:func:`_fit_pairs`' search of segments ``segs`` (rows ``idx`` of ``ev``, None: ``ev``
    is the one segment): the single fits refitted from ``s0`` (scaled, cost ``c0``), the
    grid starts, the screen, the optima and the decisions."""
    C = len(segs)

    def own(rows: Sequence[int] | NDArray[np.intp]) -> NDArray[np.intp] | None:
        return None if idx is None else idx[np.asarray(rows, dtype=np.intp)]

    every = np.arange(C)
    x1, c1 = _minimise_batch(ev, s0, owner=own(every))
    c1 = np.minimum(c1, c0)
    # grid starts of every segment, ranked by the full likelihood in one call
    grids: list[_Grid | None] = [None] * C
    for tier in sorted({seg.tier for seg in segs}):     # (the grid's beam is the tier's)
        sub = [c for c in range(C) if segs[c].tier == tier]
        for c, grid in zip(sub, _start_grids([segs[c] for c in sub], [singles[c] for c in sub]),
                           strict=True):
            grids[c] = grid
    have = [c for c in range(C) if grids[c] is not None]
    starts: list[list[Array]] = [[] for _ in range(C)]
    if have:
        gx = np.concatenate([grids[c][0] for c in have])  # type: ignore[index]
        go = np.concatenate([np.full(len(grids[c][0]), c) for c in have])  # type: ignore[index]
        full = np.concatenate([np.asarray(ev.cost(_unscale(gx[k:k + COST_CHUNK]),
                                                  own(go[k:k + COST_CHUNK])))
                               for k in range(0, go.size, COST_CHUNK)])
        for c in have:
            grid = grids[c]
            assert grid is not None
            starts[c] = _pick_starts(full[go == c], grid, n_starts)
    # and the single landmark split in two 1 deg either side: the pair can only gain
    d1 = np.array([0.0, 1.0 / _SCALE[1] * math.radians(1.0), 0.0])
    for c in range(C):
        starts[c].append(np.concatenate([x1[c] - d1, x1[c] + d1]))
    # all starts in lockstep; a few iterations first: a pair that then still gains far
    # less than the bar will not reach it (screen; docs/FITTING.md). The screen runs
    # each candidate's best grid start and its split single fit (SCREEN_ITER); the
    # other grid starts only of the candidates it passes, which go on from all of them
    X = np.array([x for st in starts for x in st])
    n_st = np.array([len(st) for st in starts])
    O = np.repeat(every, n_st)
    pos = np.arange(O.size) - np.repeat(np.cumsum(n_st) - n_st, n_st)
    ran = (pos == 0) | (pos == n_st[O] - 1)
    xs, cs = X.copy(), np.zeros(O.size)
    rows = np.flatnonzero(ran)
    xs[rows], cs[rows] = _minimise_batch(ev, X[rows], maxiter=SCREEN_ITER, owner=own(O[rows]))
    best_cs = np.full(C, np.inf)
    np.minimum.at(best_cs, O[rows], cs[rows])
    screened = c1 - best_cs < bar - SCREEN_MARGIN
    rows = np.flatnonzero(~ran & ~screened[O])
    if rows.size:
        xs[rows], cs[rows] = _minimise_batch(ev, X[rows], maxiter=SCREEN_ITER,
                                             owner=own(O[rows]))
        ran[rows] = True
    go_on = np.flatnonzero(~screened[O])
    if go_on.size:
        xs[go_on], cs[go_on] = _minimise_batch(ev, xs[go_on], maxiter=60 - SCREEN_ITER,
                                               owner=own(O[go_on]))
    optima: list[list[tuple[float, Array]]] = [[] for _ in range(C)]
    for x, c, o in zip(xs[ran], cs[ran].tolist(), O[ran].tolist(), strict=True):
        if x[1] > x[4]:                       # components ordered by bearing
            x = np.concatenate([x[3:], x[:3]])
        optima[o].append((c, x))
    for opt in optima:
        opt.sort(key=lambda o: o[0])
    best_x = np.array([opt[0][1] for opt in optima])
    c_arr, resp, resid = ev.detail(_unscale(best_x), own(every))
    comps = _unscale(best_x)
    # without either component (the other kept as fitted)
    c_one = np.asarray(ev.cost([np.concatenate([comps[1], comps[0]])],
                               own(np.concatenate([every, every]))))
    out = []
    for c, seg in enumerate(segs):
        n_c = seg.y.size
        without = [float(c_one[c] - c_arr[c]), float(c_one[C + c] - c_arr[c])]
        out.append(_decide(seg, float(c1[c]), optima[c], float(c_arr[c]), resp[c, :, :n_c],
                           resid[c, :n_c], without, float(price[c]), bool(screened[c])))
    # the covariance (Hessian and kappa profiles: most of the cost) only of the accepted
    # pairs: no test reads it
    acc = np.flatnonzero([pf.accepted for pf in out])
    if acc.size:
        H = _hessian_batch(ev, best_x[acc], own(acc))
        sds = _profile_bearing_sds_batch(
            ev, best_x[acc], np.array([optima[c][0][0] for c in acc.tolist()]), own(acc))
        for j, c in enumerate(acc.tolist()):
            out[c] = _covariance(out[c], segs[c], optima[c], H[j], sds[j])
    return out


def _decide(seg: _Segment, c1: float, optima: list[tuple[float, Array]], c_pair: float,
            resp: Array, resid: Array, without: list[float], price: float, screened: bool
            ) -> PairFit:
    """The pair's support tests and decision for one segment (``resp`` (2, n), ``resid``
    (n,) of the best optimum); the covariance is NaN here (:func:`_covariance` adds it
    to the accepted ones: no test reads it)."""
    cfg = seg.cfg
    comps = _unscale(optima[0][1])
    n_first = resp.sum(1)
    gain = c1 - c_pair
    pick = np.argmax(resp, axis=0)
    r2 = resid * resid
    chi2 = np.array([float(r2[pick == 0].sum()), float(r2[pick == 1].sum())])
    local = np.zeros((2, 3))
    for k in range(2):
        q = comps[k][0]
        local[k] = (q[0], _wrap_scalar(float(q[1])), math.exp(q[2]))
    sep = abs(math.degrees(float(M.wrap_angle(local[1, 1] - local[0, 1]))))
    side_lobe = bool(local[:, 2].max() > SIDE_LOBE_KAPPA_US
                     and local[:, 2].min() < SIDE_LOBE_STRONG_US
                     and SIDE_LOBE_DEG[0] <= sep <= SIDE_LOBE_DEG[1])
    support = np.array(without)
    if gain <= price:
        accepted = False
        basis = (f"two reflectors do not fit better than one: -2 log-likelihood gain "
                 f"{gain:.1f} <= BIC price {price:.1f}")
    elif sep < MIN_SEPARATION_DEG:
        accepted = False
        basis = f"the two components are {sep:.1f} deg apart: one reflector"
    elif min(without) <= price:
        accepted = False
        basis = (f"gain {gain:.1f} over one reflector, but one component is not supported "
                 f"on its own (removing it costs {min(without):.1f} <= {price:.1f})")
    elif gain <= MIN_GAIN:
        accepted = False
        basis = (f"-2 log-likelihood gain {gain:.1f} of two reflectors over one is within "
                 f"what model misfit gives single reflectors (<= {MIN_GAIN:g})")
    elif min(n_first) < cfg.min_echoes:
        accepted = False
        basis = (f"one component is the first echo of only {min(n_first):.1f} readings "
                 f"(< {cfg.min_echoes})")
    elif min(run_share := _run_shares(seg, local, pick)) < MIN_RUN_SHARE:
        accepted = False
        basis = (f"the readings one component explains are scattered (longest run "
                 f"{min(run_share):.0%} of them): spikes, not a second U")
    elif side_lobe:
        accepted = False
        basis = (f"the weak component (kappa {local[:, 2].max():.2f} us) lies "
                 f"{sep:.1f} deg from a strong one (kappa {local[:, 2].min():.2f} us): "
                 "its side lobe, not a second reflector")
    else:
        accepted = True
        basis = (f"two reflectors {sep:.1f} deg apart: -2 log-likelihood gain {gain:.1f} > "
                 f"BIC price {price:.1f}; each supported (removing one costs "
                 f"{min(without):.1f})")
    if screened:
        basis += f" (screened after {SCREEN_ITER} quasi-Newton iterations)"
    # where each component's minimum is seen: the reading whose beam axis is nearest
    # to its bearing must exist (within 1 deg) and have it as the first echo, else the
    # minimum is hidden by the other reflector (or lies beyond the scan)
    hidden = np.zeros(2)
    for k in range(2):
        off = np.abs(M.wrap_angle(seg.yaw - local[k, 1]))
        j = int(np.argmin(off))
        hidden[k] = (math.degrees(float(off[j])) if off[j] > math.radians(1.0)
                     else (0.0 if pick[j] == k else math.nan))
    return PairFit(local, np.full((2, 3, 3), np.nan), float(c1), c_pair, support, n_first,
                   price, accepted, basis, chi2, {}, hidden)


def _covariance(pf: PairFit, seg: _Segment, optima: list[tuple[float, Array]], H: Array,
                profile_sd: list[float]) -> PairFit:
    """``pf`` with the covariance of its components (the Hessian ``H`` of the best
    optimum, scaled by the residual chi-square, bearings widened to their kappa
    profile's spread ``profile_sd`` [rad]) and their ambiguity: other optima that fit
    as well with other bearings widen the bearing's variance to cover them."""
    best_c, best_x = optima[0]
    dof = max(seg.y.size - 6, 1)
    cov_s = _inverse(0.5 * H) * max(float(pf.chi2.sum()) / dof, 1.0)
    T = np.diag(np.tile(_SCALE, 2))
    cov = T @ cov_s @ T
    cov_out = np.zeros((2, 3, 3))
    for k in range(2):
        Jk = np.diag([1.0, 1.0, pf.local[k, 2]])    # ln kappa -> kappa
        cov_out[k] = Jk @ cov[3 * k:3 * k + 3, 3 * k:3 * k + 3] @ Jk
        cov_out[k, 1, 1] = max(cov_out[k, 1, 1], profile_sd[k] ** 2)
    ambiguous: dict[int, str] = {}
    for c, x in optima[1:]:
        if c - best_c >= AMBIGUOUS_DCOST:
            continue
        for k in range(2):
            d = math.radians(float(x[3 * k + 1] - best_x[3 * k + 1]))
            if abs(d) > max(AMBIGUOUS_SD * math.sqrt(cov_out[k, 1, 1]), math.radians(1.0)):
                ambiguous.setdefault(k, f"bearings {math.degrees(pf.local[k, 1]):.1f} and "
                                        f"{math.degrees(pf.local[k, 1] + d):.1f} deg, -2 log-"
                                        f"likelihood {c - best_c:.1f} apart")
                cov_out[k, 1, 1] = max(cov_out[k, 1, 1], d * d)
    return replace(pf, cov=cov_out, ambiguous=ambiguous)


def _wrap_scalar(a: float) -> float:
    """:func:`sonarloc.fit.model.wrap_angle` of one angle [rad] (the same float)."""
    w = (a + math.pi) % (2.0 * math.pi) - math.pi
    return math.pi if w == -math.pi else w


def _run_shares(seg: _Segment, local: Array, pick: NDArray[np.intp]) -> Array:
    """(2,) share of each component's first echoes (``pick``: the component of each
    echo) in its longest contiguous run in beam-axis order."""
    order = np.argsort(M.wrap_angle(seg.yaw - local[:, 1].mean()))
    seq = pick[order]
    run_share = np.zeros(2)
    for k in range(2):
        mine = (seq == k).astype(int)
        if mine.sum():
            edges = np.diff(np.concatenate([[0], mine, [0]]))
            runs = np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)
            run_share[k] = runs.max() / mine.sum()
    return run_share


def _inverse(H: Array) -> Array:
    """Inverse of a symmetric information matrix, finite when singular (huge variance)."""
    Hs = 0.5 * (H + H.T)
    Hs = np.where(np.isfinite(Hs), Hs, 0.0)
    w, V = np.linalg.eigh(Hs)
    floor = max(float(w.max()) * 1e-14, 1e-30)
    inv = np.minimum(1.0 / np.maximum(w, floor), 1e30)
    return (V * inv) @ V.T


AMBIGUOUS_DCOST = 2.0
"""Another local optimum of the pair within this much -2 log-likelihood whose bearings
differ by more than ``AMBIGUOUS_SD`` SDs (and 1 deg) makes the bearings ambiguous."""

AMBIGUOUS_SD = 2.0

CANDIDATE_P = 0.01
"""An ``OK`` single fit is tried as a pair when its TOF chi-square has p below this or
its residuals run in blocks (runs z below ``CANDIDATE_RUNS_Z``)."""

CANDIDATE_RUNS_Z = -2.5


def is_candidate(lm: Landmark, cfg: FitConfig) -> bool:
    """Whether a single-landmark result is worth the two-reflector test.

    Point-like results (points, and walls by strength from one viewpoint: the same
    fit) that are ``UNRESOLVED`` or ``FLAT`` with at least ``2 min_echoes`` echoes, and
    ``OK`` ones whose residuals say the single model is strained: their chi-square, or
    residuals in blocks (runs test) where the odometry's random walk was not profiled
    out of the chi-square (``chi2_odom``): the walk itself puts a moving segment's
    residuals in blocks. On a moving ring's 300 s drive (benchmarks/bench_fit.py
    section 4) the runs test made 8 more candidates of `OK` moving points, all single
    reflectors by the simulator's truth, one of them then split into two ``PARTIAL``
    halves.
    """
    n = lm.n_readings
    if n < 2 * cfg.min_echoes or lm.tier == "conventional":
        return False
    extra = lm.extra
    if lm.kind == "line" and extra.get("kind_basis") == "motion":
        return False
    status = lm.status
    if status is FitStatus.UNRESOLVED or status is FitStatus.FLAT:
        return True
    if status is not FitStatus.OK:
        return False
    runs_z = float(extra.get("runs_z", 0.0))  # type: ignore[arg-type]
    if runs_z < CANDIDATE_RUNS_Z and "chi2_odom" not in extra:
        return True
    # the status test's chi-square (odometry's pose error profiled out where moving)
    chi2 = max(float(extra.get("chi2_odom", extra.get("chi2", 0.0))), 0.0)  # type: ignore[arg-type]
    dof = max(n - 3, 1)
    if chi2 <= dof:               # p > 0.3 (at dof = 1; the chi-square's median < dof)
        return False
    lo, hi = _chi2_band(dof)      # p < CANDIDATE_P certainly above hi, certainly not below lo
    if chi2 < lo or chi2 > hi:
        return chi2 > hi
    return float(chdtrc(dof, chi2)) < CANDIDATE_P   # scipy.stats.chi2.sf


@functools.lru_cache(maxsize=1024)
def _chi2_band(dof: int) -> tuple[float, float]:
    """A band around the chi-square value where the survival function of ``dof``
    degrees of freedom crosses :data:`CANDIDATE_P` (1 % either side; exactly evaluated
    only within it)."""
    x = float(chdtri(dof, CANDIDATE_P))
    return 0.99 * x, 1.01 * x


_ARMS_OF_ONE_U = ("neither component's minimum is seen (both PARTIAL) where the single "
                  "fit's is: the two arms of one U")
"""Why an accepted pair does not replace an ``OK`` single landmark whose components would
both be ``PARTIAL``: two half-U's explain a U whose minimum the single fit sees. On a
moving ring's 300 s drive (benchmarks/bench_fit.py section 4) the pairs accepted for
``OK`` singles were all of this kind and all single reflectors by the simulator's truth
(odometry error bends the U)."""


def pair_landmarks(pf: PairFit, single: Landmark, cfg: FitConfig) -> list[Landmark]:
    """Two landmarks from an accepted pair fit, each with its own status (``PARTIAL``
    when its minimum is hidden by the other reflector or beyond the scan)."""
    ref = np.array(single.ref_pose[:2])
    out = []
    mod = cfg.module
    reach = M.module_reach_m(mod)
    for k in range(2):
        local = pf.local[k]
        params, cov, _ = M.to_frame("point", local, pf.cov[k], ref)
        sd = np.sqrt(np.maximum(np.diag(pf.cov[k]), 0.0))
        K = float(local[2])
        status, reason = FitStatus.OK, ""
        if not (np.all(np.isfinite(params)) and np.all(np.isfinite(cov))):
            status, reason = FitStatus.BAD_INPUT, "non-finite pair fit"
        elif not reach[0] <= local[0] <= reach[1]:
            status = FitStatus.BAD_INPUT
            reason = (f"one of two overlapping reflectors at {local[0]:.4g} m, outside what "
                      f"the module measures ({reach[0]:.3g}..{reach[1]:.3g} m)")
        elif not (0.5 * cfg.kappa_lo_us <= K <= 2.0 * cfg.kappa_hi_us):
            status = FitStatus.UNRESOLVED
            reason = (f"kappa {K:.3g} us of one of two overlapping reflectors is outside any "
                      "real reflector's range")
        elif k in pf.ambiguous:
            status = FitStatus.FLAT
            reason = ("two reflectors, but another pair of bearings fits as well "
                      f"({pf.ambiguous[k]}): bearing not determined")
        elif pf.hidden[k] != 0.0:
            status = FitStatus.PARTIAL
            where = ("hidden by the other reflector" if math.isnan(pf.hidden[k]) else
                     f"{pf.hidden[k]:.1f} deg beyond the readings")
            reason = (f"one of two overlapping reflectors, its minimum {where}: "
                      "bearing bounded only")
        elif K < 1.5 * cfg.kappa_lo_us:
            status = FitStatus.FLAT
            reason = (f"one of two overlapping reflectors with kappa {K:.3f} us at the lower "
                      "bound of the prior: its bearing rests on the curve's shape alone")
        elif sd[1] > math.radians(cfg.flat_bearing_sd_deg):
            status = FitStatus.FLAT
            reason = (f"one of two overlapping reflectors, bearing SD "
                      f"{math.degrees(sd[1]):.1f} deg > {cfg.flat_bearing_sd_deg:g} deg")
        extra: dict[str, object] = {
            key: single.extra[key] for key in ("seg_id", "closed_by", "n_bad_input",
                                              "n_noecho") if key in single.extra}
        extra.update(
            pair_of=single.extra.get("seg_id", -1), pair_gain=pf.gain,
            pair_price=pf.price, pair_basis=pf.basis, pair_support=float(pf.support[k]),
            bearing_sd_deg=math.degrees(sd[1]), range_sd_m=float(sd[0]),
            kappa_sd_us=float(sd[2]),
            strength_db=20.0 * math.log10(mod.detection_limit_us / max(K, 1e-12)),
            kind_basis="pair", chi2=float(pf.chi2[k]), cost=pf.cost_pair,
            tier_basis=f"{single.tier} (that of the single fit)")
        n_k = int(round(float(pf.n_first[k])))
        out.append(Landmark(
            kind="point", params=params, cov=cov, range_m=float(local[0]),
            bearing_rad=float(local[1]), n_readings=n_k, ref_t_s=single.ref_t_s,
            ref_pose=single.ref_pose, status=status, reason=reason, tier=single.tier,
            rms_us=math.sqrt(float(pf.chi2[k]) / max(n_k, 1)), sensors=single.sensors,
            extra=extra))
    return out


def resolve_pairs(segments: Sequence[Segment], landmarks: Sequence[Landmark],
                  config: FitConfig | None = None) -> list[Landmark]:
    """Replace single landmarks by two where the two-reflector model is accepted.

    Tries the two-reflector model on the results :func:`is_candidate` picks; an accepted pair
    gives two point landmarks (``extra["pair_of"]`` = the segment id, ``pair_gain``,
    ``pair_basis``); a rejected one leaves the single landmark, with the test's
    numbers in ``extra["pair_basis"]`` (and appended to the reason when it was not
    ``OK``: the two could not be told apart). All candidates are searched together
    (:func:`resolve_pair_groups`).
    """
    return [lm for g in resolve_pair_groups(segments, landmarks, config) for lm in g]


def resolve_pair_groups(segments: Sequence[Segment], landmarks: Sequence[Landmark],
                        config: FitConfig | None = None) -> list[list[Landmark]]:
    """:func:`resolve_pairs`, the result of each segment in its own list (two landmarks
    where the pair is accepted, else the single one).

    The candidates of one kind of motion, whatever their tiers, are searched in lockstep
    (every quasi-Newton step of all of them in one cost call, :class:`_Segments`: their
    readings end to end, whatever their sizes: three searches at most, not one per tier
    and kind of motion); each candidate's search
    is the one it would have alone (up to floating-point rounding: the sums, and
    :func:`sonarloc.fit.model.echo_terms` evaluates the terms of a call all at once or
    masked by how many need them).
    """
    cfg = config or FitConfig()
    out: list[list[Landmark]] = [[lm] for lm in landmarks]
    if len(segments) != len(landmarks):
        raise ValueError(f"`segments` ({len(segments)}) and `landmarks` ({len(landmarks)}) "
                         "must have equal lengths")
    cand = [i for i, lm in enumerate(landmarks) if is_candidate(lm, cfg)]
    if not cand:
        return out
    # the candidates' readings end to end; the usable ones packed
    reads = [segments[i].readings for i in cand]
    t, x, y, yaw, tof = (np.concatenate([getattr(r, f) for r in reads])
                         for f in ("t_s", "x_m", "y_m", "yaw_rad", "tof_us"))
    good = (np.isfinite(t) & np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
            & (np.isnan(tof) | (np.isfinite(tof) & (tof > 0))))
    which = np.repeat(np.arange(len(cand)), [len(r.t_s) for r in reads])
    batch = pack_flat(which[good], t[good], x[good], y[good], M.wrap_angle(yaw[good]),
                      tof[good], n_segments=len(cand))
    groups: dict[tuple[bool, bool | None], list[tuple[int, _Segment, Array]]] = {}
    for j, i in enumerate(cand):
        lm = landmarks[i]
        seg = _Segment(batch, j, cfg, lm.tier)
        local = (lm.range_m, lm.bearing_rad, lm.kappa_us)
        if seg.y.size < 2 * cfg.min_echoes or not all(map(math.isfinite, local)):
            continue
        # a segment without no-echo readings never evaluates their geometry: it joins
        # either kind (below), so fewer groups' searches run (the cost of a search step
        # is mostly per-call overhead)
        ne_key = seg.ne_moving if seg.npx.size else None
        groups.setdefault((seg.moving, ne_key), []).append((i, seg, np.array(local)))
    for key in [k for k in groups if k[1] is None]:
        joins = next((k2 for k2 in ((key[0], True), (key[0], False)) if k2 in groups), None)
        if joins is not None:
            groups[joins] += groups.pop(key)
    fits: dict[int, PairFit] = {}
    for members in groups.values():
        for (i, _, _), pf in zip(members, _fit_pairs([m[1] for m in members],
                                                     [m[2] for m in members]), strict=True):
            fits[i] = pf
    for i, pf in fits.items():
        lm = landmarks[i]
        basis = pf.basis
        if pf.accepted:
            pair = pair_landmarks(pf, lm, cfg)
            if not (lm.status is FitStatus.OK
                    and all(p.status is FitStatus.PARTIAL for p in pair)):
                out[i] = pair
                continue
            basis = f"{basis}; not taken: {_ARMS_OF_ONE_U}"
        lm.extra["pair_basis"] = basis
        lm.extra["pair_gain"] = pf.gain
        if lm.status is not FitStatus.OK:
            out[i] = [replace(lm, reason=f"{lm.reason}; {pf.basis}")]
    return out

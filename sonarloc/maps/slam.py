"""Graph SLAM for map building: robot poses and landmarks estimated together.

A map built by dead reckoning holds the odometry's drift (walls doubled and tilted,
poles seen twice decimetres apart). :func:`optimize` corrects the poses with the
landmarks the builder fitted along the drive: every landmark fit is an *observation*
of a landmark from the robot pose at the fit's reference time (a point (x, y) or a
wall (rho, alpha) in ``base_link``), and the odometry between those poses is a
measurement too. The poses and landmarks that best explain all of them (weighted
least squares, Gauss-Newton with Levenberg-Marquardt damping over a sparse Jacobian)
hold far less drift than the odometry alone, because the landmarks are seen again
(loop closures).

The graph
---------
* **nodes**: the robot pose (x, y, yaw) at the first odometry record (node 0, where the
  log's ``init`` pose puts the map frame) and at every fit's reference time (times
  closer than ``node_merge_s`` share a node);
* **odometry factors** between consecutive nodes: the odometry increment, with the
  covariance of the odometry noise model integrated over the records between them
  (:func:`~sonarloc.localize.ekf.predict_lists`), plus ``reset_cov`` across an
  odometry reset or jump (the motion across it is unknown: a weak factor);
* **a prior** on node 0: the ``init`` record's pose and SDs (it fixes the map frame:
  the gauge);
* **observation factors**: a point fit is the reflecting point ``c + R u`` of a landmark
  of centre ``c`` and radius ``R`` (``u``: unit vector from ``c`` towards where the
  transducers saw it from; R has a zero-mean prior of SD ``radius_prior_sd_m``, as the
  builder's), a wall fit the landmark's line seen from the node. Each is weighted by
  the fit's covariance (floored at ``fit_sd_floor_m`` / ``fit_sd_floor_deg``) and
  robustified by a Huber loss of threshold ``huber`` (whitened units) against wrong
  associations.

Association
-----------
A fit belongs to the landmark whose prediction is nearest within the builder's gates
(``point_gate_m``; ``wall_gate_m`` and ``wall_gate_deg`` with overlapping extents),
in the current pose estimate, or starts a new landmark; a fit within the gates of two
landmarks alike (nearest less than 1.5 times nearer) is left out. The first round is
incremental: the fits are taken in time order, ``window_s`` of them at a time, and the
graph is solved after each window (the poses of the last ``free_window_s`` free, the
older ones held: the cost stays linear in the log's length), so that the poses a fit
is placed with have only a window's drift; the gates grow with the distance
travelled since the landmark was last seen (``gate_growth_per_m``, up to
``gate_max_m``) for the drift that no landmark held in between. Later rounds
re-associate every fit with the last round's poses (base gates: duplicate landmarks of
the first round merge) and solve once; rounds stop when the poses move less than
``converge_m`` / ``converge_deg`` (at most ``rounds``).

When it cannot help
-------------------
:func:`optimize` returns ``ok`` False with a reason, and the build keeps the dead
reckoning, when there are no landmark fits or fewer than two odometry records, fewer
than ``min_landmarks`` landmarks seen twice, no landmark seen again more than
``visit_gap_s`` after a sighting (no loop closure), a solve that fails or leaves
non-finite values, a singular information matrix, or more than ``max_outlier_share`` of
the associated fits beyond the Huber threshold at the solution (associations not
trusted).

Uncertainty
-----------
The poses' marginal covariances come from the information matrix at the solution
(sparse LU, solved for the node columns); a built feature carries them as an error its
sightings share (the init prior's error and the drift left are common to all), as
the dead reckoning's covariance is carried (:class:`sonarloc.maps.build._Drift`), in
its ``sd_m``. Most of that is the map frame's own error (the init prior's), which moves
every feature alike; the poses' covariances *relative to the map frame* (the rigid
motion of the frame that best fits the landmarks' errors taken out, whatever the
prior: :func:`_pose_marginals`) go the same way into the features' ``sd_rel_m``, the
map error the Localizer uses.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.localize.ekf import OdomNoise, predict_lists

Array = NDArray[np.float64]

#: information matrices up to this size are inverted densely for the marginals
_DENSE_MARGINALS = 3000

#: weight of turning in the travel that widens the association gates [m per rad]
_TURN_M_PER_RAD = 0.5


@dataclass(frozen=True)
class SlamConfig:
    """Settings of :func:`optimize` (see the module docstring); ``BuildConfig`` holds
    them as ``slam_*`` fields."""

    point_gate_m: float = 0.10
    wall_gate_m: float = 0.08
    wall_gate_deg: float = 6.0
    wall_gap_m: float = 0.6
    radius_prior_sd_m: float = 0.03
    rounds: int = 4
    window_s: float = 5.0
    free_window_s: float = 60.0
    node_merge_s: float = 0.05
    huber: float = 3.0
    gate_growth_per_m: float = 0.01
    gate_max_m: float = 0.3
    fit_sd_floor_m: float = 0.002
    fit_sd_floor_deg: float = 0.2
    min_landmarks: int = 2
    converge_m: float = 0.005
    converge_deg: float = 0.2
    max_iterations: int = 30
    max_marginal_nodes: int = 400
    max_outlier_share: float = 0.25

    def __post_init__(self) -> None:
        for name in ("point_gate_m", "wall_gate_m", "wall_gate_deg", "wall_gap_m",
                     "radius_prior_sd_m", "window_s", "free_window_s", "huber", "gate_max_m",
                     "converge_m", "converge_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`slam_{name}` must be positive, got {v!r}")
        if not 0.0 < self.max_outlier_share <= 1.0:
            raise ValueError(f"`slam_max_outlier_share` must be in (0, 1], got "
                             f"{self.max_outlier_share!r}")
        for name in ("node_merge_s", "gate_growth_per_m", "fit_sd_floor_m",
                     "fit_sd_floor_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"`slam_{name}` must be non-negative, got {v!r}")
        for name in ("rounds", "min_landmarks", "max_iterations", "max_marginal_nodes"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"`slam_{name}` must be a positive integer, got {v!r}")


@dataclass
class Observation:
    """One landmark fit seen from the robot: ``kind`` ``point`` or ``line``; ``t_s`` its
    reference time; ``base`` (3,) the dead-reckoned base_link pose then (map frame);
    ``z`` (2,) the point (x, y) or line (rho, alpha) in that base_link frame, ``cov``
    (2, 2) its covariance; ``view`` (2,) where the transducers saw a point from and
    ``feet`` (k, 2) where a wall's echoes met it, both in base_link; ``landmark``: the
    fit itself (for the rebuild with the optimized poses)."""

    kind: str
    t_s: float
    base: Array
    z: Array
    cov: Array
    view: Array
    feet: Array
    landmark: Any = None


@dataclass
class OdomTrace:
    """The odometry of a log, joined across resets (see ``build._readings``): times
    ``t`` [s], poses ``p`` (x, y, yaw) in the joined odometry frame and whether a
    record restarted it (``restart``: a reset or jump, its increment not motion)."""

    t: list[float] = field(default_factory=list)
    p: list[Array] = field(default_factory=list)
    restart: list[bool] = field(default_factory=list)
    #: the map frame's anchor: the init pose (None: the first odometry pose is the
    #: origin) and its covariance
    init: Array | None = None
    init_cov: Array = field(default_factory=lambda: np.zeros((3, 3)))


@dataclass
class SlamResult:
    """What :func:`optimize` found (``ok`` False: it did not, ``reason`` says why).

    ``node_t`` (N,) [s], ``node_dr`` (N, 3) the dead-reckoned poses, ``node_pose``
    (N, 3) the optimized ones, ``node_cov`` (N, 3, 3) their marginal covariances (map
    frame of the observations' ``base``), ``node_cov_rel`` (N, 3, 3) the same relative to the
    map frame (its error against the world, common to all, taken out). ``moved_m`` /
    ``moved_deg``: the largest difference of an optimized pose from the dead reckoning;
    ``last_move_m`` / ``last_move_deg``: the largest change in the last round.
    ``chi2_odom`` / ``chi2_obs``: mean squared whitened residual per degree of freedom
    of the odometry factors and of the observation factors within the Huber threshold
    (about 1 when the stated noise is honest); ``outliers``: observations beyond it
    (down-weighted); ``associated``: observations in the graph (of ``observations``).
    """

    ok: bool
    reason: str = ""
    rounds: int = 0
    node_t: Array = field(default_factory=lambda: np.zeros(0))
    node_dr: Array = field(default_factory=lambda: np.zeros((0, 3)))
    node_pose: Array = field(default_factory=lambda: np.zeros((0, 3)))
    node_cov: Array = field(default_factory=lambda: np.zeros((0, 3, 3)))
    node_cov_rel: Array = field(default_factory=lambda: np.zeros((0, 3, 3)))
    obs_node: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    moved_m: float = 0.0
    moved_deg: float = 0.0
    last_move_m: float = math.nan
    last_move_deg: float = math.nan
    chi2_odom: float = math.nan
    chi2_obs: float = math.nan
    outliers: int = 0
    associated: int = 0
    observations: int = 0
    landmarks: int = 0
    revisited: int = 0
    cpu_s: float = 0.0

    def summary(self) -> str:
        """One line for the build's summary."""
        if not self.ok:
            return f"slam not used: {self.reason}"
        return (f"slam: {self.rounds} rounds, {len(self.node_t)} poses, {self.landmarks} "
                f"landmarks ({self.revisited} seen again), {self.associated} of "
                f"{self.observations} fits associated, {self.outliers} beyond the Huber "
                f"threshold (down-weighted); poses moved up to {100 * self.moved_m:.1f} cm / "
                f"{self.moved_deg:.1f} deg from the odometry (last round "
                f"{100 * self.last_move_m:.2f} cm / {self.last_move_deg:.2f} deg); factors "
                f"chi2/dof odometry {self.chi2_odom:.2f}, landmark fits {self.chi2_obs:.2f} "
                f"(within the threshold); "
                f"{self.cpu_s:.1f} s CPU")


# ------------------------------------------------------------------------ the graph


@dataclass
class _Graph:
    """Nodes, odometry factors and the prior; landmarks and observation factors are set
    per round (:meth:`set_landmarks`)."""

    node_t: Array
    node_dr: Array
    odo_z: Array          # (N-1, 3) increments node i -> i+1
    odo_a: Array          # (N-1, 3, 3) whitening (A^T A = information)
    prior: Array          # (3,)
    prior_a: Array        # (3, 3)
    radius_sd: float
    huber: float
    # per round
    lm_kind: list[str] = field(default_factory=list)
    # observations in the graph: indices into the node / landmark arrays
    p_node: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    p_lm: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    p_z: Array = field(default_factory=lambda: np.zeros((0, 2)))
    p_a: Array = field(default_factory=lambda: np.zeros((0, 2, 2)))
    p_view: Array = field(default_factory=lambda: np.zeros((0, 2)))
    w_node: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    w_lm: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    w_z: Array = field(default_factory=lambda: np.zeros((0, 2)))
    w_a: Array = field(default_factory=lambda: np.zeros((0, 2, 2)))
    lm_offset: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    n_nodes: int = 0  # nodes in the graph (a prefix, while the first round grows it)

    def linearize(self, x: Array, jacobian: bool = True
                  ) -> tuple[Array, sp.csr_matrix | None, float, dict[str, Array]]:
        """Whitened, Huber-weighted residuals, their Jacobian, the robust cost and the
        unweighted squared norms per factor kind (``odom``, ``obs``)."""
        n = self.n_nodes
        X = x[:3 * n].reshape(n, 3)
        res: list[Array] = []
        rows: list[Array] = []
        cols: list[Array] = []
        vals: list[Array] = []
        r0 = 0
        norms: dict[str, Array] = {}
        cost = 0.0

        def put(e: Array, blocks: Sequence[tuple[Array, NDArray[np.int64]]]) -> None:
            """Append factors: ``e`` (m, k) residuals, blocks of (Jacobian (m, k, d),
            first column (m,))."""
            nonlocal r0
            m, k = e.shape
            res.append(e.reshape(-1))
            if jacobian:
                rr = r0 + np.arange(m * k).reshape(m, k)
                for jb, c0 in blocks:
                    d = jb.shape[2]
                    rows.append(np.repeat(rr[:, :, None], d, axis=2).reshape(-1))
                    cols.append(np.broadcast_to(c0[:, None, None] + np.arange(d),
                                                (m, k, d)).reshape(-1))
                    vals.append(jb.reshape(-1))
            r0 += m * k

        # prior on node 0
        e = np.array([X[0, 0] - self.prior[0], X[0, 1] - self.prior[1],
                      float(se2.wrap_angle(X[0, 2] - self.prior[2]))])
        ew = self.prior_a @ e
        cost += float(ew @ ew)
        put(ew[None], [(self.prior_a[None], np.zeros(1, np.int64))])
        # odometry
        if n > 1:
            a, b = X[:-1], X[1:]
            za, aa = self.odo_z[:n - 1], self.odo_a[:n - 1]
            c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
            dx, dy = b[:, 0] - a[:, 0], b[:, 1] - a[:, 1]
            bx, by = c * dx + s * dy, -s * dx + c * dy
            e = np.stack([bx - za[:, 0], by - za[:, 1],
                          se2.wrap_angle(b[:, 2] - a[:, 2] - za[:, 2])], axis=-1)
            ew = np.einsum("mij,mj->mi", aa, e)
            sq = np.sum(ew**2, axis=1)
            norms["odom"] = sq
            cost += float(sq.sum())
            m = n - 1
            da = np.zeros((m, 3, 3))
            da[:, 0, 0], da[:, 0, 1], da[:, 0, 2] = -c, -s, by
            da[:, 1, 0], da[:, 1, 1], da[:, 1, 2] = s, -c, -bx
            da[:, 2, 2] = -1.0
            db = np.zeros((m, 3, 3))
            db[:, 0, 0], db[:, 0, 1] = c, s
            db[:, 1, 0], db[:, 1, 1] = -s, c
            db[:, 2, 2] = 1.0
            idx = np.arange(m, dtype=np.int64)
            put(ew, [(aa @ da, 3 * idx), (aa @ db, 3 * idx + 3)])
        obs_sq: list[Array] = []
        # point observations: the reflecting point c + R u seen from the node
        if len(self.p_node):
            i, off = self.p_node, self.lm_offset[self.p_lm]
            t, th = X[i, :2], X[i, 2]
            cen, rad = x[off[:, None] + np.arange(2)], x[off + 2]
            c, s = np.cos(th), np.sin(th)
            view = t + np.stack([c * self.p_view[:, 0] - s * self.p_view[:, 1],
                                 s * self.p_view[:, 0] + c * self.p_view[:, 1]], axis=-1)
            u = view - cen
            length = np.maximum(np.hypot(u[:, 0], u[:, 1]), 1e-9)
            u = u / length[:, None]
            d = cen + rad[:, None] * u - t
            hx, hy = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
            e = np.stack([hx - self.p_z[:, 0], hy - self.p_z[:, 1]], axis=-1)
            # p = c + R u, u = (v - c) / |v - c|: du = (I - u u^T) (dv - dc) / |v - c|,
            # v = t + rot(th) view: dv/dt = I, dv/dth = perp(v - t)
            m = len(i)
            proj = (np.eye(2)[None] - u[:, :, None] * u[:, None, :]) * \
                (rad / length)[:, None, None]           # R dp/dv, (m, 2, 2)
            rot_t = np.zeros((m, 2, 2))                  # rot(-th)
            rot_t[:, 0, 0], rot_t[:, 0, 1], rot_t[:, 1, 0], rot_t[:, 1, 1] = c, s, -s, c
            vt = view - t
            perp = np.stack([-vt[:, 1], vt[:, 0]], axis=-1)
            jn = np.zeros((m, 2, 3))
            jn[:, :, :2] = rot_t @ (proj - np.eye(2)[None])
            jn[:, :, 2] = np.stack([hy, -hx], axis=-1) + \
                np.einsum("mij,mj->mi", rot_t @ proj, perp)
            jl = np.zeros((m, 2, 3))
            jl[:, :, :2] = rot_t @ (np.eye(2)[None] - proj)
            jl[:, :, 2] = np.einsum("mij,mj->mi", rot_t, u)
            cost += self._robust(e, self.p_a, [(jn, 3 * i), (jl, off)], put, obs_sq)
        # wall observations: the landmark's line seen from the node
        if len(self.w_node):
            i, off = self.w_node, self.lm_offset[self.w_lm]
            rho, al = x[off], x[off + 1]
            ca, sa = np.cos(al), np.sin(al)
            e = np.stack([rho - X[i, 0] * ca - X[i, 1] * sa - self.w_z[:, 0],
                          se2.wrap_angle(al - X[i, 2] - self.w_z[:, 1])], axis=-1)
            jn = np.zeros((len(i), 2, 3))
            jn[:, 0, 0], jn[:, 0, 1], jn[:, 1, 2] = -ca, -sa, -1.0
            jl = np.zeros((len(i), 2, 2))
            jl[:, 0, 0], jl[:, 1, 1] = 1.0, 1.0
            jl[:, 0, 1] = X[i, 0] * sa - X[i, 1] * ca
            cost += self._robust(e, self.w_a, [(jn, 3 * i), (jl, off)], put, obs_sq)
        norms["obs"] = np.concatenate(obs_sq) if obs_sq else np.zeros(0)
        # radius priors
        pts = np.array([o for o, k in zip(self.lm_offset, self.lm_kind, strict=True)
                        if k == "point"], dtype=np.int64)
        if len(pts):
            e = x[pts + 2][:, None] / self.radius_sd
            cost += float(np.sum(e**2))
            put(e, [(np.full((len(pts), 1, 1), 1.0 / self.radius_sd), pts + 2)])
        r = np.concatenate(res)
        jac = None
        if jacobian:
            nv = len(x)
            jac = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows),
                                                         np.concatenate(cols))),
                                shape=(len(r), nv))
        return r, jac, cost, norms

    def _robust(self, e: Array, a: Array, blocks: list[tuple[Array, NDArray[np.int64]]],
                put: object, sq_out: list[Array]) -> float:
        """Whiten ``e`` by ``a``, weight by Huber (IRLS: rows scaled by sqrt(w)), add the
        factors; return their robust cost."""
        ew = np.einsum("mij,mj->mi", a, e)
        sq = np.sum(ew**2, axis=1)
        sq_out.append(sq)
        s = np.sqrt(sq)
        k = self.huber
        w = np.where(s <= k, 1.0, k / np.maximum(s, 1e-12))
        sw = np.sqrt(w)
        jbs = [(sw[:, None, None] * (a @ jb), c0) for jb, c0 in blocks]
        put(sw[:, None] * ew, jbs)  # type: ignore[operator]
        return float(np.sum(np.where(s <= k, sq, 2 * k * s - k * k)))


def _solve(g: _Graph, x: Array, max_iterations: int, first_free_node: int = 0
           ) -> tuple[Array, float, bool]:
    """Levenberg-Marquardt from ``x``: the solution, its robust cost, success. Nodes
    before ``first_free_node`` are held fixed (the first round's sliding window)."""
    n = g.n_nodes
    angle_idx = np.concatenate([3 * np.arange(n) + 2,
                                [o + 1 for o, k in zip(g.lm_offset, g.lm_kind, strict=True)
                                 if k == "line"]]).astype(np.int64)
    free = np.arange(3 * first_free_node, len(x))
    r, jac, cost, _ = g.linearize(x)
    lam = 1e-4
    small = False
    for _ in range(max_iterations):
        assert jac is not None
        jf = jac.tocsc()[:, free] if first_free_node > 0 else jac
        h = (jf.T @ jf).tocsc()
        grad = jf.T @ r
        dgn = h.diagonal()
        improved = False
        while lam < 1e8:
            try:
                step = spla.spsolve(h + sp.diags(lam * dgn + 1e-12, format="csc"), -grad)
            except (RuntimeError, np.linalg.LinAlgError):  # pragma: no cover - singular
                lam *= 10
                continue
            if not np.all(np.isfinite(step)):
                lam *= 10
                continue
            xn = x.copy()
            xn[free] += step
            xn[angle_idx] = se2.wrap_angle(xn[angle_idx])
            rn, jn, cn, _ = g.linearize(xn)
            if cn <= cost:
                x, r, jac = xn, rn, jn
                small = float(np.max(np.abs(step))) < 1e-5 or cost - cn < 1e-6 * max(cost, 1)
                cost = cn
                lam = max(lam / 10, 1e-9)
                improved = True
                break
            lam *= 10
        if not improved or small:
            break
    return x, cost, bool(np.all(np.isfinite(x)))


# ------------------------------------------------------------------- association


@dataclass
class _Lm:
    kind: str
    params: Array          # point (cx, cy, R); line (rho, alpha)
    last_travel: float
    n: int = 0
    t_min: float = math.inf   # extent along a wall (t = p . d, d = (-sin a, cos a))
    t_max: float = -math.inf
    last_t: float = math.nan
    revisited: bool = False


def _obs_in_map(o: Observation, pose: Array) -> tuple[Array, Array, Array]:
    """An observation placed with base pose ``pose``: (point, or line (rho, alpha) with
    its normal pointing away from the robot, as seen: rho may be negative), view (2,)
    and feet (k, 2) in the map."""
    if o.kind == "point":
        z = se2.transform_points(pose, o.z)
    else:
        a = float(o.z[1] + pose[2])
        z = np.array([float(o.z[0]) + pose[0] * math.cos(a) + pose[1] * math.sin(a),
                      float(se2.wrap_angle(a))])
    return z, se2.transform_points(pose, o.view), se2.transform_points(pose, o.feet)


def _associate(obs: list[Observation], obs_node: NDArray[np.int64], X: Array,
               lms: list[_Lm], travel: Array, cfg: SlamConfig, grow: bool,
               assoc: NDArray[np.int64], flip: NDArray[np.bool_], order: Sequence[int],
               visit_gap_s: float) -> None:
    """Associate observations ``order`` (time order) with the landmarks ``lms`` (new
    ones appended), in the poses ``X``; writes ``assoc`` (-1: left out) and ``flip``
    (a wall seen with its normal opposite the landmark's)."""
    gate_deg = math.radians(cfg.wall_gate_deg)
    for k in order:
        o = obs[k]
        i = int(obs_node[k])
        tr = float(travel[i])
        z, view, feet = _obs_in_map(o, X[i])
        best, best_s, second_s = -1, math.inf, math.inf
        for j, lm in enumerate(lms):
            if lm.kind != o.kind:
                continue
            extra = min(cfg.gate_growth_per_m * max(tr - lm.last_travel, 0.0), cfg.gate_max_m) \
                if grow else 0.0
            if o.kind == "point":
                c, rad = lm.params[:2], lm.params[2]
                u = view - c
                u = u / max(float(np.hypot(*u)), 1e-9)
                score = float(np.hypot(*(c + rad * u - z))) / (cfg.point_gate_m + extra)
            else:
                rho, al = lm.params
                dal = abs(float(se2.wrap_angle(z[1] - al)))
                opposite = dal > math.pi / 2
                if opposite:
                    dal = math.pi - dal
                nrm = np.array([math.cos(al), math.sin(al)])
                mid = feet.mean(axis=0) if len(feet) else z[0] * np.array(
                    [math.cos(z[1]), math.sin(z[1])])
                drho = abs(float(mid @ nrm) - rho)
                g_m = cfg.wall_gate_m + extra
                g_a = gate_deg + (extra / 2.0 if grow else 0.0)  # (rad per 2 m of range)
                if drho > g_m or dal > g_a:
                    continue
                if len(feet) and math.isfinite(lm.t_min):
                    t = feet @ np.array([-nrm[1], nrm[0]])
                    gap = cfg.wall_gap_m + extra
                    if t.max() < lm.t_min - gap or t.min() > lm.t_max + gap:
                        continue
                score = max(drho / g_m, dal / g_a)
            if score < best_s:
                best, best_s, second_s = j, score, best_s
            elif score < second_s:
                second_s = score
        if best >= 0 and best_s <= 1.0:
            if second_s <= 1.0 and second_s < 1.5 * best_s:
                assoc[k] = -1  # ambiguous: left out
                continue
            lm = lms[best]
        else:
            if o.kind == "point":
                params = np.array([z[0], z[1], 0.0])
            else:
                params = np.asarray(z, dtype=float).copy()
            lm = _Lm(o.kind, params, tr, last_t=o.t_s)
            lms.append(lm)
            best = len(lms) - 1
        assoc[k] = best
        if lm.kind == "line":
            al = lm.params[1]
            flip[k] = abs(float(se2.wrap_angle(z[1] - al))) > math.pi / 2
            if len(feet):
                t = feet @ np.array([-math.sin(al), math.cos(al)])
                lm.t_min, lm.t_max = min(lm.t_min, float(t.min())), max(lm.t_max, float(t.max()))
            if lm.n > 0 and not grow:
                # running mean of the line (for later gates); the solve refines it
                zz = np.array([-z[0], float(se2.wrap_angle(z[1] + math.pi))]) if flip[k] \
                    else np.asarray(z, dtype=float)
                dz = np.array([zz[0] - lm.params[0], float(se2.wrap_angle(zz[1] - al))])
                lm.params = lm.params + dz / (lm.n + 1)
        elif lm.n > 0 and not grow:
            lm.params[:2] = lm.params[:2] + (z - lm.params[:2]) / (lm.n + 1)
        if math.isfinite(lm.last_t) and o.t_s - lm.last_t > visit_gap_s:
            lm.revisited = True
        lm.last_t = o.t_s
        lm.n += 1
        lm.last_travel = tr


def _set_observations(g: _Graph, obs: list[Observation], obs_node: NDArray[np.int64],
                      lms: list[_Lm], assoc: NDArray[np.int64], flip: NDArray[np.bool_],
                      a_obs: Array, upto_node: int) -> Array:
    """Put the landmarks and associated observations (of nodes < ``upto_node``) into the
    graph; returns the landmark part of the state vector."""
    g.n_nodes = upto_node
    g.lm_kind = [lm.kind for lm in lms]
    sizes = np.array([3 if lm.kind == "point" else 2 for lm in lms], dtype=np.int64)
    g.lm_offset = 3 * upto_node + np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64) \
        if len(lms) else np.zeros(0, np.int64)
    use = (assoc >= 0) & (obs_node < upto_node)
    pk = np.array([k for k in np.flatnonzero(use) if obs[k].kind == "point"], dtype=np.int64)
    wk = np.array([k for k in np.flatnonzero(use) if obs[k].kind == "line"], dtype=np.int64)
    g.p_node, g.p_lm = obs_node[pk], assoc[pk]
    g.p_z = np.array([obs[k].z for k in pk]).reshape(-1, 2)
    g.p_view = np.array([obs[k].view for k in pk]).reshape(-1, 2)
    g.p_a = a_obs[pk]
    g.w_node, g.w_lm = obs_node[wk], assoc[wk]
    wz = np.array([obs[k].z for k in wk]).reshape(-1, 2).copy()
    f = flip[wk]
    wz[f, 0] = -wz[f, 0]
    wz[f, 1] = se2.wrap_angle(wz[f, 1] + math.pi)
    g.w_z = wz
    g.w_a = a_obs[wk]
    return np.concatenate([lm.params for lm in lms]) if lms else np.zeros(0)


# ------------------------------------------------------------------------- driver


def transform_with_cov(kind: str, pose: Array, z: Array, cov: Array) -> tuple[Array, Array]:
    """A point (x, y) or a line (rho, alpha) of the pose's child frame, and its (2, 2)
    covariance, in the pose's parent frame (:func:`sonarloc.se2.transform_points`,
    :func:`~sonarloc.se2.transform_line`: rho >= 0)."""
    x, y, th = (float(v) for v in pose)
    if kind == "point":
        rot = se2.rotation(th)
        return se2.transform_points(pose, z), rot @ cov @ rot.T
    a = float(z[1]) + th
    jr = np.array([[1.0, -x * math.sin(a) + y * math.cos(a)], [0.0, 1.0]])
    if float(z[0]) + x * math.cos(a) + y * math.sin(a) < 0:
        jr[0] = -jr[0]  # the line's normal flipped
    return se2.transform_line(pose, z), jr @ cov @ jr.T


def _whitening(cov: Array) -> Array:
    """(..., k, k) A with A^T A = cov^-1."""
    info = np.linalg.inv(0.5 * (cov + np.swapaxes(cov, -1, -2)))
    return np.swapaxes(np.linalg.cholesky(info), -1, -2)


def build_nodes(obs: list[Observation], odom: OdomTrace, dr_first: Array, noise: OdomNoise,
                reset_cov: Array, merge_s: float
                ) -> tuple[Array, Array, Array, Array, NDArray[np.int64]]:
    """Nodes at the observations' times (and node 0 at the first odometry, pose
    ``dr_first``): times (N,), dead-reckoned poses (N, 3) in the observations' map
    frame, odometry increments (N-1, 3) and their covariances (N-1, 3, 3), and each
    observation's node (M,). Observations are re-expressed in their node's frame."""
    order = sorted(range(len(obs)), key=lambda k: obs[k].t_s)
    node_t = [odom.t[0]]
    node_dr = [np.asarray(dr_first, dtype=float)]
    obs_node = np.zeros(len(obs), np.int64)
    for k in order:
        o = obs[k]
        if len(node_t) == 1 or o.t_s - node_t[-1] > merge_s or o.t_s < node_t[-1]:
            node_t.append(o.t_s)
            node_dr.append(np.asarray(o.base, dtype=float))
        obs_node[k] = len(node_t) - 1
        nb = node_dr[-1]
        if not np.array_equal(nb, o.base):  # into the node's frame
            rel = se2.between(nb, o.base)
            o.z, o.cov = transform_with_cov(o.kind, rel, o.z, o.cov)
            o.view = se2.transform_points(rel, o.view)
            o.feet = se2.transform_points(rel, o.feet)
            o.base = nb
    t_arr = np.array(node_t)
    dr = np.array(node_dr)
    # odometry increments between consecutive nodes: the records between them integrated
    ot = np.asarray(odom.t)
    op = np.array(odom.p)
    n = len(t_arr)
    z = np.zeros((n - 1, 3))
    cov = np.zeros((n - 1, 3, 3))

    def odom_at(t: float) -> Array:
        i = int(np.searchsorted(ot, t, "right"))
        if i <= 0:
            return op[0]
        if i >= len(ot):
            return op[-1]
        span = ot[i] - ot[i - 1]
        f = 0.0 if span <= 0 else (t - ot[i - 1]) / span
        return se2.interpolate(op[i - 1], op[i], f)

    for j in range(n - 1):
        ta, tb = t_arr[j], t_arr[j + 1]
        lo = int(np.searchsorted(ot, ta, "right"))
        hi = int(np.searchsorted(ot, tb, "right"))
        chain = [odom_at(ta), *op[lo:hi], odom_at(tb)]
        mean: list[float] = [0.0, 0.0, 0.0]
        c: list[list[float]] = [[0.0] * 3 for _ in range(3)]
        for p, q in zip(chain[:-1], chain[1:], strict=True):
            step = se2.between_floats(p.tolist(), q.tolist())
            mean, c = predict_lists(mean, c, step, noise)
        cj = np.array(c)
        if any(odom.restart[lo:hi]):
            # the motion across a reset is unknown (in the frame of the node before it)
            cj = cj + reset_cov * sum(odom.restart[lo:hi])
        z[j] = se2.between(dr[j], dr[j + 1])
        cov[j] = cj + np.diag([1e-8, 1e-8, 1e-10])
    return t_arr, dr, z, cov, obs_node


def optimize(obs: list[Observation], odom: OdomTrace, dr_first: Array, prior_cov: Array,
             noise: OdomNoise, reset_cov: Array, cfg: SlamConfig,
             visit_gap_s: float = 10.0) -> SlamResult:
    """Poses of the robot at the observations' times, optimized with the landmarks.

    Parameters
    ----------
    obs : the landmark fits (see :class:`Observation`); re-expressed in place in their
        nodes' frames.
    odom : the log's joined odometry.
    dr_first : (3,) pose of the first odometry record in the map frame (the ``init``
        pose), the mean of the prior on node 0; ``prior_cov`` (3, 3) its covariance
        (floored: without an ``init`` record it is zero, the frame exact).
    noise, reset_cov : odometry increment noise; (3, 3) covariance added across a reset.
    cfg : settings.
    visit_gap_s : observations of a landmark further apart than this are a new visit.

    Returns
    -------
    SlamResult, ``ok`` False with a reason when the graph cannot improve on the
    odometry (no observations, too few landmarks, no landmark seen again, a failed
    solve): the caller keeps the dead reckoning.
    """
    t0 = time.process_time()
    res = SlamResult(ok=False, observations=len(obs))
    if not obs:
        res.reason = "no landmark fits to correct the odometry with"
        return res
    if len(odom.t) < 2:
        res.reason = "fewer than two odometry records"
        return res
    node_t, dr, odo_z, odo_cov, obs_node = build_nodes(
        obs, odom, dr_first, noise, reset_cov, cfg.node_merge_s)
    n = len(node_t)
    pc = np.asarray(prior_cov, dtype=float) + np.diag([1e-6**2, 1e-6**2, 1e-6**2])
    g = _Graph(node_t, dr, odo_z, _whitening(odo_cov), np.asarray(dr_first, float),
               _whitening(pc), cfg.radius_prior_sd_m, cfg.huber)
    floor = np.array([cfg.fit_sd_floor_m, cfg.fit_sd_floor_m])
    a_list = []
    for o in obs:
        fl = floor if o.kind == "point" else np.array([cfg.fit_sd_floor_m,
                                                       math.radians(cfg.fit_sd_floor_deg)])
        a_list.append(np.asarray(o.cov, float) + np.diag(fl**2))
    a_obs = _whitening(np.array(a_list))
    # distance travelled (turns counted at _TURN_M_PER_RAD) up to each node
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(odo_z[:, 0], odo_z[:, 1]) +
                                              _TURN_M_PER_RAD * np.abs(odo_z[:, 2]))])
    order = sorted(range(len(obs)), key=lambda k: obs[k].t_s)
    X = dr.copy()
    lms: list[_Lm] = []
    assoc = np.full(len(obs), -1, np.int64)
    flip = np.zeros(len(obs), bool)
    ok = True
    # round 1: incremental, solved after every window
    k0 = 0
    solved = 1  # nodes placed so far (node 0: the prior)
    try:
        while k0 < len(order):
            t_end = obs[order[k0]].t_s + cfg.window_s
            k1 = k0
            while k1 < len(order) and obs[order[k1]].t_s < t_end:
                k1 += 1
            upto = int(obs_node[order[k1 - 1]]) + 1
            # the new nodes placed by odometry from the last solved one
            for i in range(solved, upto):
                X[i] = se2.compose(X[i - 1], odo_z[i - 1])
            solved = max(solved, upto)
            _associate(obs, obs_node, X, lms, travel, cfg, True, assoc, flip,
                       order[k0:k1], visit_gap_s)
            lm_x = _set_observations(g, obs, obs_node, lms, assoc, flip, a_obs, upto)
            x = np.concatenate([X[:upto].reshape(-1), lm_x])
            # the nodes of the last ``free_window_s`` free (older ones hold their place:
            # every later round solves them all)
            t_free = float(node_t[upto - 1]) - cfg.free_window_s
            first_free = max(int(np.searchsorted(node_t[:upto], t_free)), 0)
            x, _, ok = _solve(g, x, cfg.max_iterations, first_free)
            if not ok:
                break
            X[:upto] = x[:3 * upto].reshape(-1, 3)
            _update_lms(lms, x, g)
            k0 = k1
        for i in range(int(obs_node[order[-1]]) + 1, n):  # pragma: no cover - all have obs
            X[i] = se2.compose(X[i - 1], odo_z[i - 1])
        rounds = 1
        last = X.copy()
        move_m = move_deg = math.inf
        while ok and rounds < cfg.rounds:
            lms2: list[_Lm] = []
            assoc2 = np.full(len(obs), -1, np.int64)
            flip2 = np.zeros(len(obs), bool)
            _associate(obs, obs_node, X, lms2, travel, cfg, False, assoc2, flip2, order,
                       visit_gap_s)
            lm_x = _set_observations(g, obs, obs_node, lms2, assoc2, flip2, a_obs, n)
            x, _, ok = _solve(g, np.concatenate([X.reshape(-1), lm_x]), cfg.max_iterations)
            if not ok:
                break
            lms, assoc, flip = lms2, assoc2, flip2
            X = x[:3 * n].reshape(-1, 3).copy()
            _update_lms(lms, x, g)
            rounds += 1
            move_m = float(np.max(np.hypot(*(X[:, :2] - last[:, :2]).T)))
            move_deg = math.degrees(float(np.max(np.abs(se2.wrap_angle(X[:, 2] - last[:, 2])))))
            last = X.copy()
            if move_m < cfg.converge_m and move_deg < cfg.converge_deg:
                break
    except (np.linalg.LinAlgError, RuntimeError, ValueError) as err:
        res.reason = f"the least-squares solve failed ({err})"
        return res
    if not ok or not np.all(np.isfinite(X)):
        res.reason = "the least-squares solve did not converge to finite poses"
        return res
    n_revisit = sum(1 for lm in lms if lm.revisited)
    n_multi = sum(1 for lm in lms if lm.n >= 2)
    if n_multi < cfg.min_landmarks:
        res.reason = (f"{n_multi} landmarks seen more than once (needs "
                      f"{cfg.min_landmarks})")
        return res
    if n_revisit == 0:
        res.reason = (f"no landmark seen again after more than {visit_gap_s:g} s (no loop "
                      "closure to correct the drift with)")
        return res
    # final linearization: statistics and marginal covariances
    lm_x = _set_observations(g, obs, obs_node, lms, assoc, flip, a_obs, n)
    x = np.concatenate([X.reshape(-1), lm_x])
    r, jac, _, norms = g.linearize(x)
    assert jac is not None
    try:
        cov, cov_rel = _pose_marginals(jac, n, cfg.max_marginal_nodes, node_t,
                                       _rigid_generators(x, g), _alignment_rows(g))
    except (RuntimeError, np.linalg.LinAlgError, ValueError) as err:
        res.reason = f"the information matrix is singular ({err})"
        return res
    if not (np.all(np.isfinite(cov)) and np.all(np.isfinite(cov_rel))):
        res.reason = "the information matrix is singular (non-finite covariances)"
        return res
    res.ok = True
    res.rounds = rounds
    res.node_t, res.node_dr, res.node_pose, res.node_cov = node_t, dr, X, cov
    res.node_cov_rel = cov_rel
    res.obs_node = obs_node
    res.moved_m = float(np.max(np.hypot(*(X[:, :2] - dr[:, :2]).T)))
    res.moved_deg = math.degrees(float(np.max(np.abs(se2.wrap_angle(X[:, 2] - dr[:, 2])))))
    res.last_move_m, res.last_move_deg = (move_m, move_deg) if rounds > 1 else (math.nan,
                                                                                 math.nan)
    res.chi2_odom = float(np.mean(norms["odom"]) / 3) if len(norms.get("odom", [])) else \
        math.nan
    inl = norms["obs"][norms["obs"] <= cfg.huber**2]
    n_out = int(len(norms["obs"]) - len(inl))
    if n_out > cfg.max_outlier_share * max(len(norms["obs"]), 1):
        res.reason = (f"{n_out} of {len(norms['obs'])} associated landmark fits disagree "
                      f"with the optimized poses beyond {cfg.huber:g} SDs (more than "
                      f"{100 * cfg.max_outlier_share:.0f} %): the associations are not "
                      "trusted")
        return res
    res.chi2_obs = float(np.mean(inl) / 2) if len(inl) else math.nan
    res.outliers = n_out
    res.associated = int(np.count_nonzero(assoc >= 0))
    res.landmarks = len(lms)
    res.revisited = n_revisit
    res.cpu_s = time.process_time() - t0
    return res


def _update_lms(lms: list[_Lm], x: Array, g: _Graph) -> None:
    for lm, off in zip(lms, g.lm_offset, strict=True):
        lm.params = x[off:off + (3 if lm.kind == "point" else 2)].copy()


def _rigid_generators(x: Array, g: _Graph) -> Array:
    """(len(x), 3): how the state moves under a small rigid motion of the map frame
    (translation x, y; rotation about the origin). No factor but the prior on node 0
    sees it: the odometry and the observations are relative measurements."""
    n = g.n_nodes
    gen = np.zeros((len(x), 3))
    X = x[:3 * n].reshape(n, 3)
    rows = 3 * np.arange(n)
    gen[rows, 0] = gen[rows + 1, 1] = gen[rows + 2, 2] = 1.0
    gen[rows, 2], gen[rows + 1, 2] = -X[:, 1], X[:, 0]
    for off, kind in zip(g.lm_offset, g.lm_kind, strict=True):
        if kind == "point":   # (cx, cy, R): the centre moves, the radius does not
            gen[off, 0] = gen[off + 1, 1] = 1.0
            gen[off, 2], gen[off + 1, 2] = -x[off + 1], x[off]
        else:                 # (rho, alpha): rho moves with the translation across it
            gen[off, 0], gen[off, 1] = math.cos(x[off + 1]), math.sin(x[off + 1])
            gen[off + 1, 2] = 1.0
    return gen


def _alignment_rows(g: _Graph) -> NDArray[np.int64]:
    """(k, 2) the pairs of state rows of the landmarks that the frame-relative
    covariances align on (:func:`_pose_marginals`): the point landmarks' centres
    (cx, cy); with fewer than two, every landmark's (a wall's rho, alpha too)."""
    pts = [int(o) for o, k in zip(g.lm_offset, g.lm_kind, strict=True) if k == "point"]
    offsets = pts if len(pts) >= 2 else [int(o) for o in g.lm_offset]
    return np.array([[o, o + 1] for o in offsets], dtype=np.int64).reshape(-1, 2)


def _interpolated(node_t: Array, pick: NDArray[np.int64], blocks: Array) -> Array:
    """(n, 3, 3) blocks given at the nodes ``pick`` (increasing) linearly interpolated in
    time to every node (``blocks`` itself if every node is picked)."""
    if len(pick) == len(node_t):
        return blocks
    out = np.empty((len(node_t), 3, 3))
    for a in range(3):
        for b in range(3):
            out[:, a, b] = np.interp(node_t, node_t[pick], blocks[:, a, b])
    return out


def _pose_marginals(jac: sp.csr_matrix, n: int, max_nodes: int, node_t: Array,
                    gen: Array, pairs: NDArray[np.int64]) -> tuple[Array, Array]:
    """(n, 3, 3) marginal covariances of the nodes, and the same relative to the map
    frame: of the nodes' errors less the rigid motion of the frame (generators ``gen``
    (N, 3), :func:`_rigid_generators`) that best fits the errors of the landmarks'
    state rows ``pairs`` (k, 2).

    The covariances come from the information matrix H = J^T J (inverted if small; else
    solved for the columns of at most ``max_nodes`` nodes, linearly interpolated in time
    between them). The frame-relative ones are the blocks of P H⁻¹ Pᵀ, P = I - G K,
    K = (Gᵀ W G)⁻¹ Gᵀ W: the rigid motion that a weighted least-squares fit of the
    landmarks' errors finds, taken out of every node's error (three more solves). W is
    block-diagonal over ``pairs``: each landmark's information relative to node 0 (its
    covariance with node 0's pose taken out, P₀ H⁻¹ P₀ᵀ, P₀ = I - G G₀⁻¹ E₀). Only the
    prior on node 0 sees a rigid motion of the frame, so neither W nor P H⁻¹ Pᵀ depends
    on it: they are what the relative measurements (odometry, landmark fits) say about
    the map's shape. With landmarks that fix no rigid motion, node 0's pose is the one
    taken out (P₀: the covariances conditioned on it). Raises ``LinAlgError`` (dense) or
    ``RuntimeError`` (sparse) if H is singular."""
    h = (jac.T @ jac).tocsc()
    dense = h.shape[0] <= _DENSE_MARGINALS   # a dense inverse is quicker than sparse solves
    if dense:
        inv = scipy.linalg.cho_solve(scipy.linalg.cho_factor(h.toarray()), np.eye(h.shape[0]))
        cov = np.stack([inv[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(n)])
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))

        def solve(rhs: Array) -> Array:
            return np.asarray(inv @ rhs)
    else:
        lu = spla.splu(h)

        def solve(rhs: Array) -> Array:
            return np.asarray(lu.solve(rhs))

    def blocks(first: NDArray[np.int64], d: int) -> Array:
        """(len(first), d, d) diagonal blocks of H⁻¹ from the rows ``first``, 32 at a
        time (memory bounded)."""
        out: list[Array] = []
        for k0 in range(0, len(first), 32):
            part = first[k0:k0 + 32]
            rhs = np.zeros((h.shape[0], d * len(part)))
            for j, r in enumerate(part):
                rhs[r:r + d, d * j:d * j + d] = np.eye(d)
            sol = solve(rhs)
            out += [sol[r:r + d, d * j:d * j + d] for j, r in enumerate(part)]
        return np.stack(out) if out else np.zeros((0, d, d))

    pick = np.arange(n)
    if not dense:
        pick = np.unique(np.linspace(0, n - 1, min(n, max_nodes)).round().astype(np.int64))
        cov_p = blocks(3 * pick, 3)
        cov_p = 0.5 * (cov_p + np.swapaxes(cov_p, 1, 2))
        cov = _interpolated(node_t, pick, cov_p)

    def relative(idx: NDArray[np.int64], blk: Array, wg: Array) -> Array:
        """Blocks ``blk`` (k, d, d) of H⁻¹ at the rows ``idx`` (k, d), less the rigid
        motion K x of the weighted fit W G: the blocks of P H⁻¹ Pᵀ there."""
        m_inv = np.linalg.inv(gen.T @ wg)
        k_sigma = m_inv @ solve(wg).T            # K H⁻¹, (3, N)
        c = k_sigma @ wg @ m_inv                 # K H⁻¹ Kᵀ, (3, 3)
        g_i = gen[idx]                           # (k, d, 3)
        gb = g_i @ np.swapaxes(k_sigma[:, idx], 0, 1)   # (k, d, d)
        out = blk - gb - np.swapaxes(gb, 1, 2) + g_i @ c @ np.swapaxes(g_i, 1, 2)
        return 0.5 * (out + np.swapaxes(out, 1, 2))

    # conditioned on node 0 (the fit of its pose alone)
    wg0 = np.zeros_like(gen)
    wg0[:3] = gen[:3]
    wg = wg0
    if len(pairs):
        # each landmark weighted by its information relative to node 0 (whatever the
        # prior on node 0 says: the weights, too, are the map's shape's)
        lm_cov = np.stack([inv[np.ix_(p, p)] for p in pairs]) if dense else \
            blocks(pairs[:, 0], 2)
        lm_rel = relative(pairs, lm_cov, wg0)
        wg = np.zeros_like(gen)
        if np.all(np.linalg.eigvalsh(lm_rel)[:, 0] > 0):
            wg[pairs.reshape(-1)] = np.linalg.solve(lm_rel, gen[pairs]).reshape(-1, 3)
        if np.linalg.cond(gen.T @ wg) > 1e12:  # no rigid motion fixed: node 0's
            wg = wg0
    # at the nodes solved for, then interpolated as the marginals are (their own
    # interpolation error would be the size of the frame-relative part)
    rel = _interpolated(node_t, pick, relative(3 * pick[:, None] + np.arange(3), cov[pick], wg))
    # (the marginals themselves where that fails: no frame error taken out)
    return cov, rel if np.all(np.isfinite(rel)) else cov

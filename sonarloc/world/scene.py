"""Echo geometry of a map seen by transducers: reflecting points, occlusion, readings.

For a transducer at p with axis yaw, each reflector near the beam gives at most one
echo candidate (reflecting point q, range |q - p|, off-axis angle theta):

* a wall/plane segment echoes only from its normal-incidence point (the foot of the
  perpendicular from p), and only if that lies within the segment;
* a cylinder (pole, rod, point) from its nearest surface point, range |c - p| - radius;
  its strength (kappa at 1.5 m in the map) falls off with range as the physics
  radius rule says (:func:`~sonarloc.physics.reflectors.kappa_at_range_us`);
* a corner like a plane-strength point at the vertex, seen from inside its angle;
* an edge like a weak point at the vertex, seen from outside its angle and only within
  ``EDGE_MAX_RANGE_M`` (about 0.5 m);
* the path p -> q must not cross a nearer wall or cylinder (line of sight).

:meth:`Scene.ping` turns the candidates into readings with the physics tiers and the
module model: the nearest detected threshold crossing wins. Everything is vectorised
over the transducers of a batch and their candidates, and the candidates come from the
map's STRtree, so a ping's cost grows with what is near the beam, not with map size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.maps.geojson import CYLINDER_KINDS, Map
from sonarloc.physics import reflectors as physics_reflectors
from sonarloc.physics.beam import gaussian_echo, piston_echo
from sonarloc.physics.sound import tof_from_range_us
from sonarloc.physics.tiers import Tier, echo_delays_us
from sonarloc.physics.tof import ModuleParams, apply_module

_DEFAULT_RADIUS_M = {"pole": physics_reflectors.POLE_RADIUS_M,
                     "rod": physics_reflectors.ROD_RADIUS_M}

SEGMENT, CYLINDER, CORNER, EDGE = 0, 1, 2, 3
"""Geometry codes of reflectors in :class:`Scene` arrays."""

LOS_CLEARANCE_M = 1e-3
"""The line-of-sight test stops this short of the reflecting point (walls meeting at
a corner, the reflector's own surface)."""

RANGE_MARGIN_M = 0.05
"""Candidates up to this far beyond the range gate are kept (jitter may bring them in)."""


def reach_half_angle_rad(kappa_us: float, params: ModuleParams = ModuleParams(),
                         n_sd: float = 4.0) -> float:
    """Largest off-axis angle at which a reflector of strength ``kappa_us`` can be detected.

    The echo amplitude (the larger of the Gaussian and piston patterns, so every tier
    is covered, side lobes included) times an amplitude fluctuation of ``n_sd`` SDs must
    bring the delay kappa/a under the detection limit. Plus 1 deg of margin, at most 90.
    """
    if not (math.isfinite(kappa_us) and kappa_us > 0):
        raise ValueError(f"`kappa_us` must be positive, got {kappa_us!r}")
    grid = np.deg2rad(np.arange(0.0, 90.0, 0.1))
    amp = np.maximum(gaussian_echo(grid, params.sigma_deg),
                     piston_echo(grid, params.diameter_m, params.carrier_hz, params.c_mps))
    need = kappa_us / (params.detection_limit_us * math.exp(n_sd * params.amplitude_fluctuation))
    ok = np.flatnonzero(amp >= need)
    if ok.size == 0:
        return math.radians(1.0)
    return min(float(grid[ok[-1]]) + math.radians(1.0), math.pi / 2)


def sector_bounds(x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike, radius_m: float,
                  half_angle_rad: float) -> NDArray[np.float64]:
    """Axis-aligned bounding boxes of beam sectors, shape (K, 4) ``minx, miny, maxx, maxy``.

    The box of the apex, the two arc ends and every axis direction (0, 90, 180, 270
    deg) the sector spans: exact for any half-angle up to pi.
    """
    x, y, yaw = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, dtype=float))
                                      for a in (x_m, y_m, yaw_rad)))
    h = min(float(half_angle_rad), math.pi)
    r = float(radius_m)
    # directions: arc ends, then the four axis directions where the sector spans them
    ends = yaw[:, None] + np.array([-h, h])
    axes = np.array([0.0, 0.5, 1.0, 1.5]) * math.pi
    spans = np.abs(_wrap(axes[None, :] - yaw[:, None])) <= h
    apex = np.zeros((yaw.shape[0], 1))  # unspanned axes also fall back to the apex
    ux = np.concatenate([np.cos(ends), np.where(spans, np.cos(axes), 0.0), apex], axis=1)
    uy = np.concatenate([np.sin(ends), np.where(spans, np.sin(axes), 0.0), apex], axis=1)
    return np.column_stack([x + r * ux.min(axis=1), y + r * uy.min(axis=1),
                            x + r * ux.max(axis=1), y + r * uy.max(axis=1)])


def _wrap(a: ArrayLike) -> NDArray[np.float64]:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(a, dtype=float) + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class EchoCandidates:
    """Echo candidates of a batch of transducers, one per (transducer, reflector) pair.

    All arrays have shape (n,), sorted by ``ping`` then ``reflector``.

    Attributes
    ----------
    ping : index of the transducer in the batch.
    reflector : index into ``Map.reflectors``.
    range_m : distance from the transducer to the reflecting point.
    theta_rad : off-axis angle of the reflecting point, in [-pi, pi).
    kappa_us : reflector strength at this range [us].
    qx_m, qy_m : reflecting point in the map frame.
    """

    ping: NDArray[np.int64]
    reflector: NDArray[np.int64]
    range_m: NDArray[np.float64]
    theta_rad: NDArray[np.float64]
    kappa_us: NDArray[np.float64]
    qx_m: NDArray[np.float64]
    qy_m: NDArray[np.float64]

    def __len__(self) -> int:
        return len(self.ping)


@dataclass(frozen=True)
class PingResult:
    """Readings of a batch of K transducers.

    Attributes
    ----------
    tof_us : (K,) module reading, NaN = no echo.
    tier : (K,) :class:`~sonarloc.physics.tiers.Tier` code of the winning echo, -1 if none.
    reflector : (K,) index into ``Map.reflectors`` of the winning echo, -1 if none.
    range_m : (K,) true range of the winning reflecting point, NaN if none.
    n_candidates : (K,) echo candidates in line of sight (detected or not).
    """

    tof_us: NDArray[np.float64]
    tier: NDArray[np.int8]
    reflector: NDArray[np.int64]
    range_m: NDArray[np.float64]
    n_candidates: NDArray[np.int64]


class Scene:
    """A map prepared for echo computation (reflector arrays + the map's spatial index).

    Parameters
    ----------
    world_map : the map.
    params : ranging module; its ``max_range_m`` is the range gate of candidates.
    half_angle_rad : largest off-axis angle considered; default from the strongest
        reflector of the map (:func:`reach_half_angle_rad`).
    use_index : False = test every reflector (the brute-force baseline; same results).
    """

    def __init__(self, world_map: Map, params: ModuleParams = ModuleParams(),
                 half_angle_rad: float | None = None, use_index: bool = True):
        self.map = world_map
        self.params = params
        self.use_index = use_index
        refl = world_map.reflectors
        n = len(refl)
        self.code = np.empty(n, dtype=np.int8)
        self.ax, self.ay, self.bx, self.by = (np.zeros(n) for _ in range(4))
        self.radius = np.zeros(n)
        self.kappa = np.zeros(n)
        # radius that sets a cylinder's range fall-off (the kind's default when none given)
        self.falloff_radius = np.zeros(n)
        self.has_cone = np.zeros(n, dtype=bool)
        self.u1 = np.zeros((n, 2))
        self.u2 = np.zeros((n, 2))
        for i, r in enumerate(refl):
            self.kappa[i] = r.kappa_us
            if r.geometry.geom_type == "LineString":
                (ax, ay), (bx, by) = r.geometry.coords
                self.code[i] = SEGMENT
                self.ax[i], self.ay[i], self.bx[i], self.by[i] = ax, ay, bx, by
                continue
            self.ax[i] = self.bx[i] = r.geometry.x
            self.ay[i] = self.by[i] = r.geometry.y
            if r.kind in CYLINDER_KINDS:
                self.code[i] = CYLINDER
                self.radius[i] = r.radius_m
                self.falloff_radius[i] = r.radius_m if r.radius_m > 0 else \
                    _DEFAULT_RADIUS_M.get(r.kind, 0.0)
            else:
                self.code[i] = CORNER if r.kind == "corner" else EDGE
                if r.cone_rad is not None:
                    self.has_cone[i] = True
                    self.u1[i] = math.cos(r.cone_rad[0]), math.sin(r.cone_rad[0])
                    self.u2[i] = math.cos(r.cone_rad[1]), math.sin(r.cone_rad[1])
        self.occluder = (self.code == SEGMENT) | ((self.code == CYLINDER) & (self.radius > 0))
        if half_angle_rad is None:
            # strongest echo the map can give: cylinders are strongest at the nearest
            # range the module sees (blanking)
            near_m = max(params.blanking_us * 1e-6 * params.c_mps / 2, 0.01)
            strongest = self.kappa.copy()
            cyl = self.code == CYLINDER
            if np.any(cyl):
                strongest[cyl] = physics_reflectors.kappa_at_range_us(
                    self.kappa[cyl], "point", near_m, self.falloff_radius[cyl])
            half_angle_rad = reach_half_angle_rad(float(strongest.min()) if n else 1.0, params)
        if not (math.isfinite(half_angle_rad) and 0 < half_angle_rad <= math.pi):
            raise ValueError(f"`half_angle_rad` must be in (0, pi], got {half_angle_rad!r}")
        self.half_angle_rad = float(half_angle_rad)
        self.cylinder = self.code == CYLINDER
        self.edge_max_range_m = physics_reflectors.max_range_m("edge")

    def with_params(self, params: ModuleParams) -> Scene:
        """The same scene (arrays shared) with another module (e.g. a rig's range gate)."""
        other = object.__new__(Scene)
        other.__dict__.update(self.__dict__)
        other.params = params
        return other

    # ------------------------------------------------------------------ geometry

    def _pairs(self, x: NDArray[np.float64], y: NDArray[np.float64],
               yaw: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
        reach = self.params.max_range_m + RANGE_MARGIN_M
        n = len(self.code)
        if not self.use_index:
            k = np.repeat(np.arange(len(x)), n)
            i = np.tile(np.arange(n), len(x))
            return k, i
        pairs = self.map.query_bounds(sector_bounds(x, y, yaw, reach, self.half_angle_rad))
        return pairs[0], pairs[1]

    def candidates(self, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike) -> EchoCandidates:
        """Echo candidates in line of sight of K transducers (no randomness).

        Parameters
        ----------
        x_m, y_m, yaw_rad : (K,) transducer positions [m] and axis directions [rad]
            in the map frame (scalars allowed).
        """
        x, y, yaw = self._poses(x_m, y_m, yaw_rad)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y)) and np.all(np.isfinite(yaw))):
            raise ValueError("transducer poses `x_m`, `y_m`, `yaw_rad` must be finite")
        k, i = self._pairs(x, y, yaw)
        px, py, pyaw = x[k], y[k], yaw[k]
        code = self.code[i]
        ax, ay, bx, by = self.ax[i], self.ay[i], self.bx[i], self.by[i]

        # reflecting point q per pair
        dx, dy = bx - ax, by - ay
        len2 = dx * dx + dy * dy
        seg = code == SEGMENT
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(seg, ((px - ax) * dx + (py - ay) * dy) / np.where(seg, len2, 1.0), 0.0)
        qx = ax + t * dx
        qy = ay + t * dy
        cx, cy = qx - px, qy - py
        dist = np.hypot(cx, cy)  # to the segment foot / cylinder centre / vertex
        rad = self.radius[i]
        rng_m = dist - rad
        with np.errstate(invalid="ignore", divide="ignore"):
            shrink = np.where(dist > 0, rad / np.where(dist > 0, dist, 1.0), 0.0)
        qx = qx - shrink * cx  # cylinder: nearest surface point
        qy = qy - shrink * cy
        theta = _wrap(np.arctan2(cy, cx) - pyaw)

        ok = (rng_m > 1e-9) & (rng_m <= self.params.max_range_m + RANGE_MARGIN_M)
        ok &= np.abs(theta) <= self.half_angle_rad
        ok &= ~seg | ((t >= 0.0) & (t <= 1.0))
        vert = (code == CORNER) | (code == EDGE)
        if np.any(vert & self.has_cone[i]):
            inside = self._inside_cone(i, px - ax, py - ay)
            cone = self.has_cone[i]
            ok &= ~(vert & cone) | np.where(code == CORNER, inside, ~inside)
        ok &= (code != EDGE) | (rng_m <= self.edge_max_range_m)

        keep = np.flatnonzero(ok)
        if keep.size:
            blocked = self._blocked(k, i, keep, px[keep], py[keep], qx[keep], qy[keep])
            keep = keep[~blocked]
        ik, rk = i[keep], rng_m[keep]
        kappa = self.kappa[ik]
        cyl = self.cylinder[ik]
        if np.any(cyl):
            kappa = kappa.copy()
            # every cylinder as kind "point" with its fall-off radius filled in above
            kappa[cyl] = physics_reflectors.kappa_at_range_us(
                kappa[cyl], "point", rk[cyl], self.falloff_radius[ik[cyl]])
        return EchoCandidates(k[keep], ik, rk, theta[keep], kappa, qx[keep], qy[keep])

    def _inside_cone(self, i: NDArray[np.int64], dx: NDArray[np.float64],
                     dy: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Whether direction (dx, dy) from a vertex lies strictly inside its (< pi) wall angle."""
        u1, u2 = self.u1[i], self.u2[i]
        s = np.sign(u1[:, 0] * u2[:, 1] - u1[:, 1] * u2[:, 0])
        c1 = u1[:, 0] * dy - u1[:, 1] * dx
        c2 = dx * u2[:, 1] - dy * u2[:, 0]
        return (s * c1 > 0) & (s * c2 > 0)

    def _blocked(self, k: NDArray[np.int64], i: NDArray[np.int64], keep: NDArray[np.int64],
                 px: NDArray[np.float64], py: NDArray[np.float64], qx: NDArray[np.float64],
                 qy: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Line-of-sight test of the kept candidates against every occluder near their ping."""
        occ = np.flatnonzero(self.occluder[i])
        blocked = np.zeros(keep.size, dtype=bool)
        if occ.size == 0:
            return blocked
        ke, ko = k[keep], k[occ]  # both sorted by ping
        n_pings = int(max(ke.max(), ko.max())) + 1
        cnt_o = np.bincount(ko, minlength=n_pings)
        start_o = np.cumsum(cnt_o) - cnt_o
        per_e = cnt_o[ke]
        total = int(per_e.sum())
        if total == 0:
            return blocked
        e_idx = np.repeat(np.arange(keep.size), per_e)
        offs = np.arange(total) - np.repeat(np.cumsum(per_e) - per_e, per_e)
        o_idx = occ[np.repeat(start_o[ke], per_e) + offs]
        oi = i[o_idx]
        not_self = oi != i[keep][e_idx]
        e_idx, oi = e_idx[not_self], oi[not_self]

        # path p -> q', stopping LOS_CLEARANCE_M short of q
        sx, sy = px[e_idx], py[e_idx]
        vx, vy = qx[e_idx] - sx, qy[e_idx] - sy
        length = np.hypot(vx, vy)
        f = np.clip(1.0 - LOS_CLEARANCE_M / np.maximum(length, 1e-12), 0.0, 1.0)
        ex, ey = sx + f * vx, sy + f * vy
        ax, ay, bx, by = self.ax[oi], self.ay[oi], self.bx[oi], self.by[oi]
        seg = self.code[oi] == SEGMENT

        def orient(ux: NDArray[np.float64], uy: NDArray[np.float64], wx: NDArray[np.float64],
                   wy: NDArray[np.float64], zx: NDArray[np.float64],
                   zy: NDArray[np.float64]) -> NDArray[np.float64]:
            return (wx - ux) * (zy - uy) - (wy - uy) * (zx - ux)

        d1 = orient(sx, sy, ex, ey, ax, ay)
        d2 = orient(sx, sy, ex, ey, bx, by)
        d3 = orient(ax, ay, bx, by, sx, sy)
        d4 = orient(ax, ay, bx, by, ex, ey)
        hit_seg = seg & (d1 * d2 < 0) & (d3 * d4 < 0)
        # cylinders: distance from the centre to the path below the radius
        wx, wy = ex - sx, ey - sy
        w2 = np.maximum(wx * wx + wy * wy, 1e-24)
        s = np.clip(((ax - sx) * wx + (ay - sy) * wy) / w2, 0.0, 1.0)
        dc = np.hypot(sx + s * wx - ax, sy + s * wy - ay)
        start_inside = np.hypot(sx - ax, sy - ay) <= self.radius[oi]
        hit_cyl = ~seg & (dc < self.radius[oi]) & ~start_inside
        hit = hit_seg | hit_cyl
        blocked[np.unique(e_idx[hit])] = True
        return blocked

    # ------------------------------------------------------------------ readings

    def _poses(self, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        x, y, yaw = (np.atleast_1d(np.asarray(a, dtype=float)) for a in (x_m, y_m, yaw_rad))
        bx, by, byaw = np.broadcast_arrays(x, y, yaw)
        if bx.ndim != 1:
            raise ValueError(f"transducer poses must be scalars or 1-D arrays, got shape "
                             f"{bx.shape}")
        return bx, by, byaw

    @staticmethod
    def _by_ping(cand: EchoCandidates, tm: NDArray[np.float64], n_pings: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """Candidates' crossing times as a (K, width) NaN-padded grid, and the flat index
        (into ``cand``) of each ping's earliest crossing (-1 if none)."""
        counts = np.bincount(cand.ping, minlength=n_pings)
        width = int(counts.max()) if counts.size else 0
        first = np.cumsum(counts) - counts
        col = np.arange(len(cand)) - np.repeat(first, counts)
        grid = np.full((n_pings, width), np.nan)
        grid[cand.ping, col] = tm
        if width == 0:
            return grid, np.full(n_pings, -1, dtype=np.int64)
        filled = np.where(np.isnan(grid), np.inf, grid)
        best = filled.argmin(axis=-1)
        has = np.isfinite(filled[np.arange(n_pings), best])
        return grid, np.where(has, first + best, -1).astype(np.int64)

    def ping(self, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
             rng: np.random.Generator, tier: Tier | str = Tier.AUTO) -> PingResult:
        """Simulated readings of K transducers fired together (no crosstalk).

        Each candidate echo gets a random threshold delay from the tier
        (:func:`~sonarloc.physics.tiers.echo_delays_us`); the module keeps the nearest
        detected crossing, adds jitter, applies blanking, range gate and counting
        (:func:`~sonarloc.physics.tof.apply_module`).

        Parameters
        ----------
        x_m, y_m, yaw_rad : (K,) transducer poses in the map frame [m, rad].
        rng : seeded generator (the only source of randomness).
        tier : model tier (``auto`` picks per echo; the winner's tier is returned).
        """
        x, y, yaw = self._poses(x_m, y_m, yaw_rad)
        n_pings = x.shape[0]
        cand = self.candidates(x, y, yaw)
        delay, used = echo_delays_us(cand.theta_rad, cand.kappa_us, tier, rng, self.params)
        tm = tof_from_range_us(cand.range_m, self.params.c_mps) + delay
        grid, win = self._by_ping(cand, tm, n_pings)
        reading = apply_module(grid, rng, self.params, axis=-1)
        win = np.where(np.isfinite(reading), win, -1)
        has = win >= 0
        w = np.where(has, win, 0)
        if len(cand):
            tier_w = np.where(has, used[w], -1).astype(np.int8)
            refl_w = np.where(has, cand.reflector[w], -1).astype(np.int64)
            range_w = np.where(has, cand.range_m[w], np.nan)
        else:
            tier_w = np.full(n_pings, -1, dtype=np.int8)
            refl_w = np.full(n_pings, -1, dtype=np.int64)
            range_w = np.full(n_pings, np.nan)
        counts = np.bincount(cand.ping, minlength=n_pings).astype(np.int64)
        return PingResult(reading, tier_w, refl_w, range_w, counts)

    def predict_tof_us(self, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
                       tier: Tier | str = Tier.AUTO) -> tuple[NDArray[np.float64],
                                                             NDArray[np.int64]]:
        """Noise-free first-echo time To + kappa/a(theta) of K transducers.

        No amplitude fluctuation, jitter or counting; blanking and range gate apply.

        Returns
        -------
        tm_us : (K,) predicted crossing time, NaN = no echo expected.
        reflector : (K,) index of the reflector expected to win, -1 if none.
        """
        quiet = replace(self.params, amplitude_fluctuation=0.0, jitter_sd_us=0.0)
        x, y, yaw = self._poses(x_m, y_m, yaw_rad)
        cand = self.with_params(quiet).candidates(x, y, yaw)
        delay, _ = echo_delays_us(cand.theta_rad, cand.kappa_us, tier,
                                  np.random.default_rng(0), quiet)
        tm = tof_from_range_us(cand.range_m, quiet.c_mps) + delay
        _, win = self._by_ping(cand, tm, x.shape[0])
        has = win >= 0
        w = np.where(has, win, 0)
        out = np.where(has, tm[w], np.nan) if len(cand) else np.full(x.shape[0], np.nan)
        out = np.where((out >= quiet.blanking_us) & (out <= quiet.max_tof_us), out, np.nan)
        refl = np.where(np.isfinite(out), cand.reflector[w], -1) if len(cand) \
            else np.full(x.shape[0], -1)
        return out, refl.astype(np.int64)

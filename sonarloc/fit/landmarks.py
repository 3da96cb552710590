"""From segments (or a whole scan, or a live stream) to :class:`Landmark` results.

* :func:`fit_segments` fits a list of segments with the batch fitter and selects the
  model of each (point or line, Gaussian or piston beam), giving every result a
  status and, when it cannot be trusted, a reason.
* :func:`fit_scan` cleans a :class:`~sonarloc.io.scancsv.ScanReadings`, segments it
  with the online :class:`~sonarloc.fit.segment.Segmenter` and fits the segments.
* :class:`OnlineFitter` does the same reading by reading: ``push`` returns the
  landmarks whose segments the reading closed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import chdtrc

from sonarloc.fit import model as M
from sonarloc.fit import odomcov
from sonarloc.fit.lsq import FitConfig, SegmentBatch, _take, pack_flat
from sonarloc.fit.pair import resolve_pair_groups
from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.fit.segment import (
    Segment,
    SegmentBlock,
    Segmenter,
    SegmenterConfig,
    SegmenterStats,
    usable,
)
from sonarloc.fit.select import KAPPA_WALL_US, Selection, overlap_reasons, select_models
from sonarloc.io.scancsv import ScanReadings

Array = NDArray[np.float64]

WEAK_WALL_KAPPA_US = 3.0 * KAPPA_WALL_US
"""Kappa [us] above which a wall fit is ``UNRESOLVED`` where the data say so
(:func:`weak_wall`: walls echo strongly at normal incidence, a weak "wall" is a corner
or merged echoes); the cut stage's weak-wall rule (:func:`_fits_alone`) uses the same
bound."""


def weak_wall(kind: ArrayLike, kappa_us: ArrayLike, kappa_sd_us: ArrayLike) -> NDArray[np.bool_]:
    """Whether wall fits are weaker than walls (``WEAK_WALL_KAPPA_US``) by more than two
    SDs of ln kappa (``kappa_sd / kappa``).

    A wall seen at normal incidence only (one transducer facing it squarely, the off-
    axis angle ~0 throughout) shows no U: its TOFs fix ``To + kappa``, not kappa. Such
    fits land anywhere in the prior's box (kappa 4 +- 17 us on a moving ring's drive,
    ``past_wall_ends``); their walls are where the motion puts them and their strength
    is not known, not weak."""
    k = np.asarray(kappa_us, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return ((np.asarray(kind) == "line") & (k > WEAK_WALL_KAPPA_US)
                & (np.log(k / WEAK_WALL_KAPPA_US) > 2.0 * np.asarray(kappa_sd_us) / k))

OCCLUDED_KAPPA_LOG_SD = 0.35
"""Relative SD of kappa above which a segment occluded on both sides (by nearer echoes)
is ``FLAT``: wall and pole differ by a factor 4.5 in kappa (ln 1.5), so telling them
apart at two SDs needs the SD of ln kappa below ~0.35."""

OCCLUDED_CURVATURE_DCOST = 9.0
"""A segment occluded on both sides must fit better with its curvature than with a flat
curve (kappa at the prior's lower bound, range and bearing refitted) by this much -2 log-
likelihood (3 SDs) for its strength to count: the Wald SD of kappa is optimistic there,
the likelihood being flat towards small kappa."""


def _curvature_support(batch: SegmentBatch, j: int, local: Array, tier: str,
                       cfg: FitConfig, extra: dict[str, object]) -> float:
    """-2 log-likelihood rise from the fit to the best flat curve (kappa at the prior's
    lower bound) for segment ``j`` (stored in ``extra["curvature_dcost"]``)."""
    from sonarloc.fit.pair import _SCALE, _minimise, _Segment, _unscale
    if tier == "conventional" or not np.all(np.isfinite(local)):
        return math.inf
    seg = _Segment(batch, j, cfg, tier)
    x = np.array([local[0] / _SCALE[0], local[1] / _SCALE[1], math.log(local[2])])
    c_fit = float(seg.cost(_unscale(x[None, :]))[0])
    flat = x.copy()
    flat[2] = math.log(cfg.kappa_lo_us)
    _, c_flat = _minimise(seg, flat, fixed=2)
    d = c_flat - c_fit
    extra["curvature_dcost"] = d
    return d


SegmentLike = Segment | ScanReadings | tuple[Array, Array, Array, Array, Array]
_Cleaned = tuple[Array, Array, Array, Array, Array, NDArray[np.int64]]


def _arrays(seg: SegmentLike) -> _Cleaned:
    if isinstance(seg, Segment):
        seg = seg.readings
    if isinstance(seg, ScanReadings):
        return seg.t_s, seg.x_m, seg.y_m, seg.yaw_rad, seg.tof_us, seg.sensor
    t, x, y, yaw, tof = (np.asarray(a, dtype=float) for a in seg)
    if not all(a.ndim == 1 and a.size == t.size for a in (t, x, y, yaw, tof)):
        # (numpy's own error further on names no argument, or there is none: a segment
        # of scalars failed in len(), a 2-D one in indexing)
        raise ValueError("a segment's (t_s, x_m, y_m, yaw_rad, tof_us) must be 1-D arrays "
                         f"of one length, got shapes {[a.shape for a in (t, x, y, yaw, tof)]}")
    return t, x, y, yaw, tof, np.zeros(len(t), dtype=np.int64)


def _clean(t: Array, x: Array, y: Array, yaw: Array, tof: Array
           ) -> tuple[NDArray[np.bool_], int]:
    """Readings usable by the fitter (:func:`~sonarloc.fit.segment.usable`)."""
    ok = usable(t, x, y, yaw, tof)
    return ok, int((~ok).sum())


def conventional(t_s: Array, x_m: Array, y_m: Array, yaw_rad: Array, tof_us: Array,
                 config: FitConfig | None = None) -> tuple[float, float, float]:
    """The conventional reading of a segment: the object on the beam axis at min TOF.

    Returns ``(range_m, bearing_rad, t_s)`` of the minimum-TOF echo (range from the
    reading less the counting bias); NaN if there is no echo.
    """
    cfg = config or FitConfig()
    tof = np.asarray(tof_us, dtype=float)
    finite = np.isfinite(tof)
    if not finite.any():
        return math.nan, math.nan, math.nan
    i = int(np.argmin(np.where(finite, tof, np.inf)))
    r = (tof[i] - 0.5 * cfg.module.count_period_us) / M.us_per_m(cfg.module)
    return float(r), float(M.wrap_angle(yaw_rad[i])), float(t_s[i])


def _fallback(seg_arrays: _Cleaned, status: FitStatus, reason: str,
              cfg: FitConfig, extra: dict[str, object]) -> Landmark:
    """A result for a segment that could not be fitted: the conventional reading with a
    covariance as wide as the beam (finite), or NaN parameters if there was no echo."""
    t, x, y, yaw, tof, sensor = seg_arrays
    finite = np.isfinite(tof)
    sensors = tuple(sorted({int(s) for s in np.asarray(sensor)[finite]}))
    if not finite.any():
        nan3 = np.full(3, np.nan)
        ref = len(t) - 1
        pose = ((float(x[ref]), float(y[ref]), float(yaw[ref])) if len(t)
                else (math.nan, math.nan, math.nan))
        return Landmark("point", nan3, np.full((3, 3), np.nan), math.nan, math.nan, 0,
                        float(t[ref]) if len(t) else math.nan, pose, status, reason,
                        extra={**extra, "n_noecho": int(len(t))}, sensors=sensors)
    r, bearing, _ = conventional(t, x, y, yaw, tof, cfg)
    ref = int(np.flatnonzero(finite)[-1])
    i = int(np.argmin(np.where(finite, tof, np.inf)))
    # the object is on the min-TOF beam axis at range r, seen from that reading; its
    # offset from the reference formed from the readings' difference first (the same in
    # any frame: absolute points at x ~ 5e5 m would round to 1e-10 m)
    rx, ry = float(x[ref]), float(y[ref])
    px = float(x[i] - rx) + r * math.cos(bearing)
    py = float(y[i] - ry) + r * math.sin(bearing)
    r_ref = math.hypot(px, py)
    b_ref = math.atan2(py, px) if r_ref > 0 else bearing
    half_beam = math.radians(12.0)
    sd_r = math.sqrt(float(M.tof_variance_us2(0.0, cfg.module))) / M.us_per_m(cfg.module)
    local = np.array([r_ref, b_ref, cfg.kappa_guess_us])
    local_cov = np.diag([sd_r ** 2, half_beam ** 2 / 3.0, 1e4])
    params, cov, _ = M.to_frame("point", local, local_cov, np.array([rx, ry]))
    return Landmark("point", params, cov, r_ref, b_ref, int(finite.sum()), float(t[ref]),
                    (rx, ry, float(yaw[ref])), status, reason, tier="conventional",
                    sensors=sensors, extra={**extra, "n_noecho": int((~finite).sum())})


def _add_odometry_terms(batch: SegmentBatch, sel: Selection, cfg: FitConfig,
                        sd_deg_per_m: float | None, to_ref: Array | None,
                        arm_m: float = 0.0) -> Array:
    """The odometry's share of moving segments' fits (:mod:`sonarloc.fit.odomcov`, one
    :func:`~sonarloc.fit.odomcov.odometry_terms` call per kind and tier): the curvature
    error's and the random walks' covariances added to ``sel.cov`` (recorded in ``extra``
    as ``odom_range_sd_m`` / ``odom_bearing_sd_deg``), and the TOF chi-square the status
    test reads (B,): with the walks profiled out (``extra["chi2_odom"]``), else the fit's.
    The overlap test (:func:`~sonarloc.fit.select.overlap_check`) is made again on what
    the walks leave (``extra["runs_z_odom"]``): the walk itself puts a moving segment's
    residuals in blocks (on a moving ring's 300 s drive, benchmarks/bench_fit.py section
    4, 29 single reflectors by the simulator's truth were ``UNRESOLVED`` by the runs
    test, 7 with it; most of the others still fail the chi-square).
    ``to_ref``: :func:`_travel_to_ref` (None: no segment moved); ``arm_m``: the
    transducers' lever arm (:func:`~sonarloc.fit.odomcov.ring_arm`)."""
    sd = _odometry_sd(sd_deg_per_m)
    if sd == 0.0:
        return sel.chi2
    if not batch.moving or to_ref is None:
        # no segment moved (pans): every share is zero (added all the same, as the
        # general path does: a -0.0 entry becomes 0.0)
        sel.cov += 0.0
        return sel.chi2
    chi2 = sel.chi2.copy()
    for kind in ("point", "line"):
        for tier in set(sel.tier[sel.kind == kind]):
            idx = np.flatnonzero((sel.kind == kind) & (sel.tier == tier))
            curv, c2, walk, runs = odomcov.odometry_terms(_take(batch, idx), sel.rows(idx),
                                                          to_ref[idx], cfg, sd, arm_m)
            sel.cov[idx] += curv
            for j in np.flatnonzero((curv[:, 0, 0] > 0.0) | (curv[:, 1, 1] > 0.0)).tolist():
                ex = sel.extra[int(idx[j])]
                ex["odom_range_sd_m"] = math.sqrt(curv[j, 0, 0])
                ex["odom_bearing_sd_deg"] = math.degrees(math.sqrt(curv[j, 1, 1]))
            chi2[idx] = c2
            sel.cov[idx] += walk
            walked = np.flatnonzero(c2 != sel.chi2[idx])
            overlap = overlap_reasons(runs[walked], c2[walked], sel.n_used[idx[walked]])
            for j, reason in zip(walked.tolist(), overlap, strict=True):
                ex = sel.extra[int(idx[j])]
                ex["chi2_odom"] = float(c2[j])
                # the overlap test on what the walks leave (their residuals and chi-square)
                ex["runs_z_odom"] = float(runs[j])
                ex.pop("overlap", None)
                if reason:
                    ex["overlap"] = reason
                ex["odom_range_sd_m"] = math.hypot(float(ex.get("odom_range_sd_m", 0.0)),  # type: ignore[arg-type]
                                                   math.sqrt(walk[j, 0, 0]))
                ex["odom_bearing_sd_deg"] = math.hypot(
                    float(ex.get("odom_bearing_sd_deg", 0.0)),  # type: ignore[arg-type]
                    math.degrees(math.sqrt(walk[j, 1, 1])))
    return chi2


def _odometry_sd(sd_deg_per_m: float | None) -> float:
    """The odometry SD [deg/m] a caller asked for (None: the default), checked."""
    sd = odomcov.CURVATURE_SD_DEG_PER_M if sd_deg_per_m is None else float(sd_deg_per_m)
    if not (math.isfinite(sd) and sd >= 0.0):
        raise ValueError(f"`odometry_sd_deg_per_m` must be non-negative, got {sd_deg_per_m!r}")
    return sd


def _travel_to_ref(batch: SegmentBatch, seg: NDArray[np.int64], t: Array, x: Array,
                   y: Array, sensor: NDArray[np.int64], echo: NDArray[np.bool_]) -> Array:
    """Distance travelled from each echo to its segment's reference (last) echo, (B, Nd)
    as the batch's echo columns (:func:`sonarloc.fit.odomcov.travel_from_start`);
    ``seg, t, x, y, sensor, echo``: the batch's readings, flat."""
    travel = odomcov.travel_from_start(seg, t, x, y, sensor, batch.size)[echo]
    ref = np.zeros(batch.size)
    np.maximum.at(ref, seg[echo], travel)          # the last echo's (time order)
    to_ref = np.zeros(batch.valid.shape)
    to_ref[batch.valid] = ref[seg[echo]] - travel
    return to_ref


def fit_segments(segments: Sequence[SegmentLike], config: FitConfig | None = None,
                 odometry_sd_deg_per_m: float | None = None) -> list[Landmark]:
    """Fit one landmark to each segment (vectorised over all of them).

    Parameters
    ----------
    segments : :class:`Segment`, :class:`ScanReadings` or ``(t_s, x_m, y_m, yaw_rad,
        tof_us)`` arrays; poses in one fixed frame, TOF NaN = no echo.
    config : fitter settings (speed of sound, detection model, thresholds).
    odometry_sd_deg_per_m : SD of the odometry's path-curvature error within a segment
        (:mod:`sonarloc.fit.odomcov`), added to the covariance of segments taken while
        moving; None: the default (calibrated on the simulator's default odometry); 0
        for exact poses.

    Returns
    -------
    One :class:`Landmark` per segment, in order. Parameters are in the frame of the
    poses; ``ref_t_s``/``ref_pose`` are those of the segment's last echo.
    """
    cfg = config or FitConfig()
    if len(segments) == 0:
        return []
    return _select_segments(segments, cfg).landmarks(cfg, odometry_sd_deg_per_m)


def _select_segments(segments: Sequence[SegmentLike], cfg: FitConfig) -> _Selected:
    """The fits and model choices of :func:`fit_segments` (one or more segments)."""
    n = len(segments)
    if isinstance(segments, SegmentBlock):   # already end to end
        r = segments.readings
        lengths = np.diff(segments.bounds)
        t, x, y, yaw, tof, sensor = r.t_s, r.x_m, r.y_m, r.yaw_rad, r.tof_us, r.sensor
        info: Sequence[tuple[int, str, tuple[bool, bool]] | None] = list(
            zip(segments.seg_id, segments.closed_by, segments.occluded, strict=True))
    else:
        parts = [_arrays(s) for s in segments]
        lengths = np.array([p[0].size for p in parts], dtype=np.int64)
        t, x, y, yaw, tof = (np.concatenate([p[k] for p in parts], dtype=float)
                             for k in range(5))
        sensor = np.concatenate([p[5] for p in parts], dtype=np.int64, casting="unsafe")
        info = [(s.seg_id, s.closed_by, s.occluded) if isinstance(s, Segment) else None
                for s in segments]
    return _select_packed(np.repeat(np.arange(n), lengths), t, x, y, yaw, tof, sensor,
                          info, cfg)


@dataclass
class _Selected:
    """Segments fitted and their models chosen, before the odometry term and the
    statuses (:func:`_select_packed`): the landmarks of any of them, with or without
    the term (it only widens covariances; fits, costs and chi-squares stay)."""

    fallback: list[Landmark | None]   # per segment: its landmark if it has < 3 echoes
    row: NDArray[np.int64]            # per segment: its row of batch/sel (-1: fallback)
    batch: SegmentBatch | None        # None: no segment has 3 echoes
    sel: Selection | None
    meta: list[dict[str, object]]     # per row, as the arguments of _landmarks
    sensors: list[tuple[int, ...]]
    n_echo: NDArray[np.int64]
    n_noecho: NDArray[np.int64]
    to_ref: Array | None              # (rows, Nd) travel from each echo to the reference
    arm_m: float                      # the transducers' lever arm (odomcov.ring_arm)

    def landmarks(self, cfg: FitConfig, odometry_sd_deg_per_m: float | None,
                  which: Sequence[int] | None = None) -> list[Landmark]:
        """The landmarks of segments ``which`` (all: None), in that order. All of them at
        once with the odometry term add it to ``sel`` in place: the last call; without
        it (``odometry_sd_deg_per_m`` 0) nothing changes, and a part of them takes a
        copy: both can be asked for again (with another ``odometry_sd``)."""
        seg = np.arange(self.row.size) if which is None else np.asarray(which, dtype=np.int64)
        rows = self.row[seg]
        take = rows[rows >= 0]
        lms: list[Landmark] = []
        if take.size:
            assert self.batch is not None and self.sel is not None
            whole = which is None
            batch = self.batch if whole else _take(self.batch, take)
            sel = self.sel if whole else self.sel.subset(take)
            chi2 = _add_odometry_terms(batch, sel, cfg, odometry_sd_deg_per_m,
                                       None if self.to_ref is None else self.to_ref[take],
                                       self.arm_m)
            r = take.tolist()
            lms = _landmarks(batch, sel, cfg, [self.meta[j] for j in r],
                             [self.sensors[j] for j in r], self.n_echo[take],
                             self.n_noecho[take], chi2)
        it = iter(lms)
        out: list[Landmark] = []
        for i, k in zip(seg.tolist(), rows.tolist(), strict=True):
            lm = next(it) if k >= 0 else self.fallback[i]
            assert lm is not None    # (a segment not fitted has a fallback)
            out.append(lm)
        return out


def _select_packed(seg: NDArray[np.int64], t: Array, x: Array, y: Array, yaw: Array,
                   tof: Array, sensor: NDArray[np.int64],
                   info: Sequence[tuple[int, str, tuple[bool, bool]] | None],
                   cfg: FitConfig) -> _Selected:
    """:func:`_select_segments` of segments end to end: reading ``k`` belongs to segment
    ``seg[k]`` (non-decreasing, (N,)); ``info``: each segment's ``(seg_id, closed_by,
    occluded)`` (None: not a :class:`Segment`)."""
    n = len(info)
    ok, bad = _clean(t, x, y, yaw, tof)
    n_bad = np.bincount(seg[~ok], minlength=n)
    if bad:   # (a segmenter's readings are all clean)
        t, x, y, yaw, tof = (a[ok] for a in (t, x, y, yaw, tof))
        seg, sensor = seg[ok], sensor[ok]
    yaw = M.wrap_angle(yaw)
    echo = np.isfinite(tof)
    n_echo = np.bincount(seg[echo], minlength=n)
    n_noecho = np.bincount(seg[~echo], minlength=n)
    bounds = np.searchsorted(seg, np.arange(n + 1))
    meta: list[dict[str, object]] = []
    for nb, s in zip(n_bad.tolist(), info, strict=True):
        m: dict[str, object] = {"n_bad_input": nb}
        if s is not None:
            m["seg_id"], m["closed_by"], occ = s
            if occ[0] or occ[1]:
                m["occluded"] = "both" if occ[0] and occ[1] else "first" if occ[0] else "last"
        meta.append(m)
    out: list[Landmark | None] = [None] * n
    for i in np.flatnonzero(n_echo < 3).tolist():
        a, b = bounds[i], bounds[i + 1]
        arrs = (t[a:b], x[a:b], y[a:b], yaw[a:b], tof[a:b], sensor[a:b])
        if n_echo[i] == 0 and n_bad[i]:
            # its echoes (if any) were unusable: say so, not "no echo"
            out[i] = _fallback(arrs, FitStatus.BAD_INPUT,
                               f"no usable echo: {n_bad[i]} reading(s) with a non-finite "
                               "or absurd pose or an inf, zero, negative or absurd TOF "
                               "dropped", cfg, meta[i])
        elif n_echo[i] == 0:
            out[i] = _fallback(arrs, FitStatus.NO_ECHO, "no echo in the segment", cfg, meta[i])
        else:
            out[i] = _fallback(arrs, FitStatus.TOO_FEW_POINTS,
                               f"{n_echo[i]} echo(es); at least 3 are needed for "
                               "(range, bearing, kappa)", cfg, meta[i])
    todo = np.flatnonzero(n_echo >= 3)
    row = np.full(n, -1, dtype=np.int64)
    row[todo] = np.arange(todo.size)
    if todo.size < n:   # the readings of those, renumbered
        keep = row[seg] >= 0
        t, x, y, yaw, tof = (a[keep] for a in (t, x, y, yaw, tof))
        seg, sensor, echo = row[seg[keep]], sensor[keep], echo[keep]
    batch, sel = None, None
    sensors: list[tuple[int, ...]] = []
    if todo.size:
        batch = pack_flat(seg, t, x, y, yaw, tof, n_segments=todo.size)
        sel, batch = select_models(batch, cfg)
        # transducers that contributed echoes, per segment (each has echoes)
        s_echo = sensor[echo]
        s_lo = int(s_echo.min())
        width = int(s_echo.max()) - s_lo + 1
        if width == 1:      # one transducer (the sort below takes milliseconds)
            sensors = [(s_lo,)] * todo.size
        else:
            ids = None
            if width * todo.size >= 1 << 62:
                # ids too far apart for the keys below in int64 (they would overflow or
                # wrap): keyed by their rank instead
                ids, s_echo = np.unique(s_echo, return_inverse=True)
                s_lo, width = 0, ids.size
            keys = np.unique(seg[echo] * width + (s_echo - s_lo))
            cut = np.searchsorted(keys // width, np.arange(todo.size + 1))
            vals = (keys % width + s_lo if ids is None else ids[keys % width]).tolist()
            sensors = [tuple(vals[a:b]) for a, b in zip(cut[:-1].tolist(), cut[1:].tolist(),
                                                         strict=True)]
    to_ref, arm = None, 0.0
    if batch is not None and batch.moving:
        to_ref = _travel_to_ref(batch, seg, t, x, y, sensor, echo)
        arm = odomcov.ring_arm(t, x, y, yaw, sensor)
    return _Selected(out, row, batch, sel, [meta[i] for i in todo.tolist()], sensors,
                     n_echo[todo], n_noecho[todo], to_ref, arm)


def _landmarks(batch: SegmentBatch, sel: Selection, cfg: FitConfig,
               meta: list[dict[str, object]], sensors: list[tuple[int, ...]],
               n_echo: NDArray[np.int64], n_noecho: NDArray[np.int64],
               chi2_status: Array | None = None) -> list[Landmark]:
    """Landmarks with statuses from the selected fits (vectorised, then one object each);
    ``chi2_status``: the TOF chi-square of the fit test (default: the fits')."""
    B = batch.size
    mod = cfg.module
    local = sel.local.copy()
    local[:, 1] = M.wrap_angle(local[:, 1])
    params = np.zeros((B, 3))
    cov = np.zeros((B, 3, 3))
    span = np.zeros(B)
    lo, hi = sel.arc[:, 0], sel.arc[:, 1]
    outside = np.abs(M.wrap_angle(local[:, 1] - 0.5 * (lo + hi))) - 0.5 * (hi - lo)
    # the span is read only by the PARTIAL test, for minima outside the arc: computed
    # there (with the geometry of a moving sensor where any segment of its group moved,
    # as for the whole group)
    far = outside > math.radians(1.0)
    moves = np.zeros(B, dtype=bool)
    if batch.moving:
        moves = np.any(batch.px != 0.0, axis=1) | np.any(batch.py != 0.0, axis=1)
    for kind in ("point", "line"):
        idx = np.flatnonzero(sel.kind == kind)
        if idx.size == 0:
            continue
        params[idx], cov[idx], _ = M.to_frame(kind, local[idx], sel.cov[idx],
                                              batch.ref_xy[idx])
        # how much the fitted delay varies over the used echoes: a partial U shows a
        # clear arm, a flat curve (strong plane) does not
        for tier in set(sel.tier[idx]):
            jdx = idx[sel.tier[idx] == tier]
            moving = bool(moves[jdx].any())
            jdx = jdx[far[jdx]]
            if jdx.size == 0:
                continue
            geo = M.geometry(kind, local[jdx, 0:1], local[jdx, 1:2], batch.px[jdx],
                             batch.py[jdx], batch.yaw[jdx], moving=moving)
            g, _, _ = M.beam_delay_factor(geo.theta, str(tier), mod, derivative=False)
            d = np.minimum(local[jdx, 2:3] * g, 1e6)
            u = sel.used[jdx]
            span[jdx] = (np.max(np.where(u, d, -np.inf), axis=1)
                         - np.min(np.where(u, d, np.inf), axis=1))
    sd = np.sqrt(np.maximum(np.einsum("bkk->bk", sel.cov), 0.0))
    finite = np.all(np.isfinite(params), axis=1) & np.all(np.isfinite(cov), axis=(1, 2))
    n_used = sel.n_used
    rms = np.sqrt((sel.resid ** 2 * sel.used).sum(1) / np.maximum(n_used, 1))
    strength = 20.0 * np.log10(mod.detection_limit_us / np.maximum(local[:, 2], 1e-12))
    flat_sd = math.radians(cfg.flat_bearing_sd_deg)
    chi2_test = sel.chi2 if chi2_status is None else chi2_status
    p_fit = _chi2_sf(chi2_test, np.maximum(n_used - 3, 1))
    # per-segment values as Python lists (the loop below runs once per segment)
    sd_l, local_l = sd.tolist(), local.tolist()
    n_used_l, p_fit_l = n_used.tolist(), p_fit.tolist()
    chi2_l, chi2_test_l = sel.chi2.tolist(), chi2_test.tolist()
    finite_l, outside_l, span_l = finite.tolist(), outside.tolist(), span.tolist()
    kind_l = np.where(sel.kind == "point", "point", "line").tolist()
    tier_l = [str(t) for t in sel.tier.tolist()]
    # the fields of each landmark but status and reason, and the first of its extras
    fields = zip(kind_l, params, cov, local_l, n_used_l, batch.ref_t_s.tolist(),
                 zip(*batch.ref_xy.T.tolist(), batch.ref_yaw.tolist(), strict=True), tier_l,
                 rms.tolist(), sensors, strict=True)
    extras = zip(meta, sel.extra, np.degrees(sd[:, 1]).tolist(), sd_l, strength.tolist(),
                 n_noecho.tolist(), (n_echo - n_used).tolist(), chi2_l, sel.cost.tolist(),
                 strict=True)
    # segments that may fail a test below (a superset of each, NaN failing as there):
    # the rest are OK without going through them one by one
    kap = local[:, 2]
    weak = weak_wall(sel.kind, kap, sd[:, 2])
    weak_l = weak.tolist()
    occluded = np.array(["occluded" in m for m in meta], dtype=bool)
    overlap = np.array(["overlap" in ex for ex in sel.extra], dtype=bool)
    reach_lo, reach_hi = M.module_reach_m(mod)
    rng_l = local[:, 0]
    check_l = (~finite | ~((reach_lo <= rng_l) & (rng_l <= reach_hi))
               | (n_used < cfg.min_echoes) | overlap | occluded
               | ~((0.5 * cfg.kappa_lo_us <= kap) & (kap <= 2.0 * cfg.kappa_hi_us))
               | weak
               | (p_fit < cfg.min_fit_p) | ((outside > math.radians(1.0)) & (span > 3.0))
               | (kap < 1.5 * cfg.kappa_lo_us) | (sd[:, 1] > flat_sd)).tolist()
    out = []
    for j, (check, f, e) in enumerate(zip(check_l, fields, extras, strict=True)):
        m_j, ex_j, b_sd, sd_j, strength_j, n_noecho_j, n_spikes_j, chi2_j, cost_j = e
        extra: dict[str, object] = {
            **m_j, **ex_j, "bearing_sd_deg": b_sd, "range_sd_m": sd_j[0],
            "kappa_sd_us": sd_j[2], "strength_db": strength_j, "n_noecho": n_noecho_j,
            "n_spikes": n_spikes_j, "chi2": chi2_j, "cost": cost_j}
        status, reason = FitStatus.OK, ""
        if not check:
            pass                  # passes every test below
        elif not finite_l[j]:
            status, reason = FitStatus.BAD_INPUT, "non-finite fit (bad input)"
        elif not reach_lo <= local_l[j][0] <= reach_hi:
            status = FitStatus.BAD_INPUT
            reason = (f"range {local_l[j][0]:.4g} m is outside what the module measures "
                      f"({reach_lo:.3g}..{reach_hi:.3g} m): TOFs in other units, or from "
                      "another module (its blanking and maximum range)?")
        elif n_used_l[j] < cfg.min_echoes:
            status = FitStatus.TOO_FEW_POINTS
            reason = (f"{n_used_l[j]} echoes (after removing spikes); {cfg.min_echoes} are "
                      "needed to check a 3-parameter fit")
        elif "overlap" in sel.extra[j]:
            status, reason = FitStatus.UNRESOLVED, str(sel.extra[j]["overlap"])
        elif not (0.5 * cfg.kappa_lo_us <= local_l[j][2] <= 2.0 * cfg.kappa_hi_us):
            status = FitStatus.UNRESOLVED
            reason = (f"kappa {local_l[j][2]:.3g} us is outside any real reflector's range "
                      f"({cfg.kappa_lo_us:g}..{cfg.kappa_hi_us:g} us): merged or misread echoes?")
        elif weak_l[j]:
            status = FitStatus.UNRESOLVED
            reason = (f"a wall with kappa {local_l[j][2]:.2f} +- {sd_l[j][2]:.2f} us: walls echo "
                      "strongly at normal incidence (kappa ~0.15 us); corner or merged echoes?")
        elif p_fit_l[j] < cfg.min_fit_p:
            status = FitStatus.UNRESOLVED
            reason = (f"no single landmark explains the readings (chi2 {chi2_test_l[j]:.0f} for "
                      f"{n_used_l[j]} echoes, p = {p_fit_l[j]:.1e}): several reflectors merged?")
        elif outside_l[j] > math.radians(1.0) and span_l[j] > 3.0:
            status = FitStatus.PARTIAL
            reason = (f"minimum of the U {math.degrees(outside_l[j]):.1f} deg outside the arc "
                      "covered by echoes: bearing bounded only")
        elif local_l[j][2] < 1.5 * cfg.kappa_lo_us and (
                kind_l[j] == "point" or sel.extra[j].get("kind_basis") != "motion"):
            # a bearing read off the U's shape (a point, or anything seen from one spot);
            # pinned at the prior's bound, the shape did not fix it (a wall whose normal
            # comes from the motion's range trend survives this)
            status = FitStatus.FLAT
            reason = (f"kappa {local_l[j][2]:.3f} us sits at the lower bound of the prior: "
                      "the curve is too flat to fix strength and bearing")
        elif (meta[j].get("occluded") == "both" and sel.extra[j].get("kind_basis") != "motion"
              and (sd_l[j][2] > OCCLUDED_KAPPA_LOG_SD * local_l[j][2]
                   or _curvature_support(batch, j, local[j], str(tier_l[j]), cfg, extra)
                   < OCCLUDED_CURVATURE_DCOST)):
            # no arc end of its own and a curve too flat to give the strength: a pole
            # and a wall (0.67 / 0.15 us) cannot be told apart from one viewpoint
            status = FitStatus.FLAT
            reason = (f"occluded on both sides by nearer echoes (the arc's ends say nothing "
                      f"about this reflector) and the curve within does not fix its strength "
                      f"(kappa {local_l[j][2]:.2f} +- {sd_l[j][2]:.2f} us; a flat curve costs "
                      f"{float(extra.get('curvature_dcost', math.nan)):.1f} in -2 log-"  # type: ignore[arg-type]
                      f"likelihood, < {OCCLUDED_CURVATURE_DCOST:g} needed): strength and kind "
                      "(wall or pole) not determined")
        elif ("occluded" in meta[j] and sel.extra[j].get("kind_basis") == "strength"
              and abs(math.log(local_l[j][2] / KAPPA_WALL_US)) < 2.0 * sd_l[j][2] / local_l[j][2]):
            # an arc end hidden by a nearer echo: the strength rests on the curve and
            # that cannot place it on either side of the wall/pole boundary
            status = FitStatus.FLAT
            reason = (f"occluded ({meta[j]['occluded']} end) and kappa {local_l[j][2]:.2f} +- "
                      f"{sd_l[j][2]:.2f} us straddles the wall/pole boundary ({KAPPA_WALL_US} "
                      "us); one viewpoint cannot tell them apart otherwise: kind not "
                      "determined")
        elif sd_l[j][1] > flat_sd:
            status = FitStatus.FLAT
            reason = (f"curve too flat for its bearing (SD {math.degrees(sd_l[j][1]):.1f} deg "
                      f"> {cfg.flat_bearing_sd_deg:g} deg)")
        kind, p_j, c_j, loc_j, n_j, ref_t, ref_pose, tier, rms_j, sensors_j = f
        out.append(Landmark._from_fields({   # every field, in order
            "kind": kind, "params": p_j, "cov": c_j, "range_m": loc_j[0],
            "bearing_rad": loc_j[1], "n_readings": n_j, "ref_t_s": ref_t,
            "ref_pose": ref_pose, "status": status, "reason": reason, "tier": tier,
            "rms_us": rms_j, "sensors": sensors_j, "extra": extra}))
    return out


def split_unresolved(segments: Sequence[Segment], landmarks: Sequence[Landmark],
                     config: FitConfig | None = None, n_cuts: int = 8,
                     odometry_sd_deg_per_m: float | None = None) -> list[Landmark]:
    """Try to split segments that no single landmark explains into two landmarks.

    For each ``UNRESOLVED`` segment with at least ``2 * min_echoes`` echoes, cut it in
    time at ``n_cuts`` evenly spaced places and at its four largest steps between
    consecutive echoes (each part keeping ``min_echoes`` echoes), fit both parts,
    and keep the best cut if both parts are ``OK`` and -2 log-likelihood drops by more
    than the BIC price of three more parameters; the two landmarks then replace the
    one (``extra["split_of"]`` = the segment id). Returns the landmarks in order.
    ``odometry_sd_deg_per_m``: that of :func:`fit_segments`, for the parts (the same as
    the whole segments were fitted with).
    """
    return [lm for g in _split_groups(segments, landmarks, config, n_cuts,
                                      odometry_sd_deg_per_m) for lm in g]


@dataclass
class _Cuts:
    """Where an ``UNRESOLVED`` segment is cut: the readings' positions of its echoes, the
    cuts (echo indices, sorted) and whether its single fit is a weak wall
    (:func:`_fits_alone`)."""

    seg: Segment
    echo: NDArray[np.int64]
    cuts: list[int]
    weak_wall: bool


def _cut_plan(seg: Segment, whole: Landmark, cfg: FitConfig, n_cuts: int
              ) -> _Cuts | None:
    """The cuts of a segment: ``n_cuts`` evenly spaced and at its four largest steps
    between consecutive echoes (where one reflector's echoes give way to the other's),
    each part keeping ``min_echoes`` echoes; None if it has too few echoes."""
    r = seg.readings
    echo = np.flatnonzero(np.isfinite(r.tof_us))
    n = echo.size
    if n < 2 * cfg.min_echoes:
        return None
    even = np.linspace(cfg.min_echoes, n - cfg.min_echoes, n_cuts).astype(int)
    step = np.abs(np.diff(r.tof_us[echo]))
    order = np.argsort(-step) + 1
    jumps = order[(order >= cfg.min_echoes) & (order <= n - cfg.min_echoes)][:4]
    return _Cuts(seg, echo, np.unique(np.concatenate([even, jumps])).tolist(),
                 bool(weak_wall(whole.kind, whole.kappa_us, _kappa_sd(whole))))


_Part = tuple[int, int, int]
"""A part of a cut: ``(segment, cut, side)``; side 0: the readings before the cut's echo,
1: from it on."""


class _Parts:
    """Fitted parts of cuts: each one's landmark without the odometry term (what the
    search ranks cuts by: the term only widens covariances, costs and chi-squares do
    not change) and, for those asked for, with it, from the same fits (no refit)."""

    def __init__(self) -> None:
        self.bare: dict[_Part, Landmark] = {}
        self._fits: dict[_Part, tuple[_Selected, int]] = {}

    def fit(self, plans: dict[int, _Cuts], todo: Sequence[_Part], cfg: FitConfig) -> None:
        """Fit parts ``todo`` in one batch."""
        if not todo:
            return
        parts: list[Segment] = []
        for i, c, side in todo:
            seg = plans[i].seg
            pos = int(plans[i].echo[c])
            if side == 0:
                parts.append(Segment(seg.readings.select(slice(0, pos)), seg.seg_id,
                                     seg.closed_by, (seg.occluded[0], False)))
            else:
                parts.append(Segment(seg.readings.select(slice(pos, None)), seg.seg_id,
                                     seg.closed_by, (False, seg.occluded[1])))
        fitted = _select_segments(parts, cfg)
        self.bare.update(zip(todo, fitted.landmarks(cfg, 0.0), strict=True))
        self._fits.update((part, (fitted, k)) for k, part in enumerate(todo))

    def with_odometry(self, todo: Sequence[tuple[int, int]], cfg: FitConfig,
                      odometry_sd: float | None
                      ) -> dict[tuple[int, int], tuple[Landmark, Landmark]]:
        """Both (fitted) parts of cuts ``todo`` with the odometry term, their statuses
        tested again with it: one call per batch that fitted any of them."""
        keys = [(i, c, side) for i, c in todo for side in (0, 1)]
        by_batch: dict[int, tuple[_Selected, list[_Part], list[int]]] = {}
        for key in keys:
            fitted, k = self._fits[key]
            entry = by_batch.setdefault(id(fitted), (fitted, [], []))
            entry[1].append(key)
            entry[2].append(k)
        out: dict[_Part, Landmark] = {}
        for fitted, group, rows in by_batch.values():
            out.update(zip(group, fitted.landmarks(cfg, odometry_sd, rows), strict=True))
        return {(i, c): (out[i, c, 0], out[i, c, 1]) for i, c in todo}


def _fits_alone(lm: Landmark, weak_wall: bool) -> bool:
    """A part of a cut that may stand as a landmark: ``OK`` and fitting well on its own (a
    stricter test than for whole segments: cutting at the best of several places
    favours chance fits); of a segment whose single fit is a weak wall (``weak_wall``:
    :func:`weak_wall`, the status test: a corner or merged echoes?), a point part must
    be as strong as that test expects of a wall (a corner, a pole).

    A point as weak as the wall is that wall seen from part of the path, not a corner:
    on a moving ring's drive (benchmarks/bench_fit.py section 4, second table) 19 parts
    of 14 such splits were points of kappa 4.8-9.8 us on a wall's line (within 15 mm)
    placed along it with SDs of 0.9-22 cm where the wall has no point (the simulator's
    truth); the one weak-wall split into two lines is kept."""
    return (lm.ok and _fit_p(lm) > 0.01
            and not (weak_wall and lm.kind == "point" and lm.kappa_us > WEAK_WALL_KAPPA_US))


def _search(plans: dict[int, _Cuts], cfg: FitConfig) -> tuple[
        _Parts, dict[tuple[int, int], tuple[Landmark, Landmark]]]:
    """The cuts that can win, fitted: of every cut the part with fewer echoes, the other
    part only where that one fits alone (a cut whose other part is not fitted cannot
    pass: it is missing). Returns the fits and the cuts' landmarks without the odometry
    term: the cuts that pass are those of fitting every cut.

    Two batches, whatever the number of cuts. Not a probing batch first (the middle cut
    of each segment, a part whose fit found a plausible reflector ruling out the cuts
    that would leave a part holding it): on moving ring16 room drives
    (benchmarks/bench_fit.py section 4's 300 s CSV: 139 ``UNRESOLVED`` segments; a 60 s
    one: 27) that rule lost splits fitting every cut finds, 3 of 51 and 2 of 14 (two a
    corner and a wall each, both parts within 2.8 cm of the simulator's reflectors; one
    a corner cut into a line and a point), and its batch cost more than it saved: the
    middle cut's parts hold both reflectors' echoes, the slowest to fit (spike refits,
    tier trials, fresh brackets). Cachegrind, the stage alone (1.8 G of start-up left
    out): the probing batch against these two, 300 s 11.98 / 10.78 G instructions, 60 s
    5.03 / 4.58 G; these two against one batch of every cut: 10.78 / 12.47 G (300 s),
    4.58 / 4.29 (60 s), 6.91 / 8.56 (a 30 s drive, 261 cuts), 2.45 / 2.73 (10 s, 92
    cuts), 0.669 / 0.660 (a rotation's 17 cuts). The cost goes mostly with the number
    of model evaluations (~2 M instructions each, against ~700 per padded reading):
    lockstep tails of the tier fits, half of them on <= 10 rows."""
    parts = _Parts()
    short = [(i, c, int(2 * c > p.echo.size)) for i, p in plans.items() for c in p.cuts]
    parts.fit(plans, short, cfg)
    other = [(i, c, 1 - side) for i, c, side in short
             if _fits_alone(parts.bare[i, c, side], plans[i].weak_wall)]
    parts.fit(plans, other, cfg)
    fits = {(i, c): (parts.bare[i, c, 0], parts.bare[i, c, 1]) for i, c, _ in other}
    return parts, fits


def _split_groups(segments: Sequence[Segment], landmarks: Sequence[Landmark],
                  config: FitConfig | None = None, n_cuts: int = 8,
                  odometry_sd_deg_per_m: float | None = None) -> list[list[Landmark]]:
    """:func:`split_unresolved`, the result of each segment in its own list.

    The cuts that can win are fitted without the odometry term (:func:`_search`). Cuts whose
    parts both pass are ranked by total cost, and the first whose parts still pass with
    the term wins (the term only widens covariances, so it can only fail a part: the
    winner is the one fitting every cut with it would give). The term is added to the
    fits made (:class:`_Parts`), not by fitting them again (that round of fits cost 0.31
    of the 6.1 s CPU of the cut stage of a moving ring's 300 s drive,
    benchmarks/bench_fit.py section 4)."""
    cfg = config or FitConfig()
    plans: dict[int, _Cuts] = {}
    for i, (seg, lm) in enumerate(zip(segments, landmarks, strict=True)):
        if lm.status is FitStatus.UNRESOLVED:
            plan = _cut_plan(seg, lm, cfg, n_cuts)
            if plan is not None:
                plans[i] = plan
    if not plans:
        return [[lm] for lm in landmarks]
    parts, fits = _search(plans, cfg)
    # each segment's passing cuts, best total first (ties: the earlier cut)
    ranked: dict[int, list[tuple[float, int]]] = {}
    for (i, c), (a, b) in sorted(fits.items()):
        p = plans[i]
        if _fits_alone(a, p.weak_wall) and _fits_alone(b, p.weak_wall):
            ranked.setdefault(i, []).append(
                (float(a.extra["cost"]) + float(b.extra["cost"]), c))  # type: ignore[arg-type]
    checked = parts.with_odometry([(i, c) for i, v in ranked.items() for _, c in v], cfg,
                                  odometry_sd_deg_per_m)
    best: dict[int, tuple[float, Landmark, Landmark]] = {}
    for i, v in ranked.items():
        for total, c in sorted(v):
            a, b = checked[i, c]
            if _fits_alone(a, plans[i].weak_wall) and _fits_alone(b, plans[i].weak_wall):
                best[i] = (total, a, b)
                break
    out: list[list[Landmark]] = []
    for i, lm in enumerate(landmarks):
        if i in best:
            total, a, b = best[i]
            n = a.n_readings + b.n_readings
            gain = float(lm.extra.get("cost", np.inf)) - total  # type: ignore[arg-type]
            if gain > 3.0 * math.log(max(n, 2)):
                for part in (a, b):
                    part.extra["split_of"] = lm.extra.get("seg_id", i)
                    part.extra["split_gain"] = gain
                out.append([a, b])
                continue
        out.append([lm])
    return out


def _kappa_sd(lm: Landmark) -> float:
    """A landmark's SD of kappa [us] (NaN where not known)."""
    return float(lm.extra.get("kappa_sd_us", math.nan))  # type: ignore[arg-type]


def _fit_p(lm: Landmark) -> float:
    """p-value of a landmark's TOF chi-square (1 without one: a fallback)."""
    if "chi2" not in lm.extra:
        return 1.0
    return float(_chi2_sf(float(lm.extra["chi2"]),  # type: ignore[arg-type]
                          max(lm.n_readings - 3, 1)))


def _chi2_sf(x: ArrayLike, df: ArrayLike) -> Array:
    """Chi-square survival function, ``scipy.stats.chi2.sf(x, df)`` (the same numbers;
    scipy.special's, so ``sonarloc fit`` does not import scipy.stats, ~0.3 s)."""
    return np.asarray(chdtrc(df, np.maximum(x, 0.0)), dtype=float)


@dataclass
class FitReport:
    """Landmarks of a scan, with the segmenter's counters."""

    landmarks: list[Landmark]
    stats: SegmenterStats


def fit_scan(scan: ScanReadings, config: FitConfig | None = None,
             segmenter: SegmenterConfig | None = None,
             odometry_sd_deg_per_m: float | None = None) -> FitReport:
    """Segment a scan (in reading order) and fit every segment.

    Readings with non-finite or absurd poses or inf/zero/negative/absurd TOF
    (:func:`~sonarloc.fit.segment.usable`) are ignored (counted in
    ``stats.bad``); duplicate times are allowed (ring transducers firing together).
    """
    cfg = config or FitConfig()
    seg = Segmenter(segmenter, cfg.module)
    segments = seg.feed_block(scan)
    return FitReport(_resolve(segments, fit_segments(segments, cfg, odometry_sd_deg_per_m),
                              cfg, odometry_sd_deg_per_m), seg.stats)


class OnlineFitter:
    """Readings in, landmarks out, one reading at a time (bounded memory).

    ``push`` takes the *transducer* pose at the ping in a fixed frame (for a robot:
    odometry pose composed with the transducer's mount and pan angle) and returns the
    landmarks of the segments that reading closed; ``flush`` closes the rest.
    """

    def __init__(self, config: FitConfig | None = None,
                 segmenter: SegmenterConfig | None = None,
                 odometry_sd_deg_per_m: float | None = None) -> None:
        self.config = config or FitConfig()
        self.odometry_sd_deg_per_m = odometry_sd_deg_per_m
        self.segmenter = Segmenter(segmenter, self.config.module)

    @property
    def stats(self) -> SegmenterStats:
        return self.segmenter.stats

    def push(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, tof_us: float,
             sensor: int = 0) -> list[Landmark]:
        closed = self.segmenter.push(t_s, x_m, y_m, yaw_rad, tof_us, sensor)
        return self._fit(closed) if closed else []

    def push_block(self, scan: ScanReadings, flush: bool = False) -> list[Landmark]:
        """:meth:`push` of many readings: the landmarks of the segments they closed, fitted
        together (a scan read in blocks: :func:`sonarloc.io.scancsv.iter_scan_csv`).
        ``flush``: the last block; the segments still open are closed and fitted in the
        same batch (one block with ``flush`` is :func:`fit_scan`)."""
        closed = self.segmenter.push_block(scan)
        if flush:
            closed = SegmentBlock.join([closed, SegmentBlock.of(self.segmenter.flush())])
        return self._fit(closed) if len(closed) else []

    def flush(self) -> list[Landmark]:
        closed = self.segmenter.flush()
        return self._fit(closed) if closed else []

    def _fit(self, closed: Sequence[Segment]) -> list[Landmark]:
        return _resolve(closed, fit_segments(closed, self.config, self.odometry_sd_deg_per_m),
                        self.config, self.odometry_sd_deg_per_m)


def _resolve(segments: Sequence[Segment], landmarks: list[Landmark], cfg: FitConfig,
             odometry_sd_deg_per_m: float | None = None) -> list[Landmark]:
    """Overlapping reflectors: the two-reflector model where one landmark is strained
    (:func:`sonarloc.fit.pair.resolve_pairs`), then cuts in time for what is still
    ``UNRESOLVED`` (:func:`split_unresolved`: a wall running into a corner)."""
    groups = resolve_pair_groups(segments, landmarks, cfg)   # all candidates together
    todo = [k for k, res in enumerate(groups)
            if len(res) == 1 and res[0].status is FitStatus.UNRESOLVED]
    if todo:   # one batched call for all that are still unresolved
        parts = _split_groups([segments[i] for i in todo], [groups[i][0] for i in todo],
                              cfg, odometry_sd_deg_per_m=odometry_sd_deg_per_m)
        for i, part in zip(todo, parts, strict=True):
            groups[i] = part
    out = [lm for g in groups for lm in g]
    return out

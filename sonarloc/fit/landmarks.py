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
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from sonarloc.fit import model as M
from sonarloc.fit.lsq import BatchFit, FitConfig, SegmentBatch, fit_batch, pack_segments
from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.fit.segment import Segment, Segmenter, SegmenterConfig, SegmenterStats
from sonarloc.fit.select import KAPPA_WALL_US, choose_kind, choose_tier, overlap_check
from sonarloc.io.scancsv import ScanReadings

Array = NDArray[np.float64]

SegmentLike = Segment | ScanReadings | tuple[Array, Array, Array, Array, Array]
_Cleaned = tuple[Array, Array, Array, Array, Array, NDArray[np.int64]]


def _arrays(seg: SegmentLike) -> _Cleaned:
    if isinstance(seg, Segment):
        seg = seg.readings
    if isinstance(seg, ScanReadings):
        return seg.t_s, seg.x_m, seg.y_m, seg.yaw_rad, seg.tof_us, seg.sensor
    t, x, y, yaw, tof = (np.asarray(a, dtype=float) for a in seg)
    return t, x, y, yaw, tof, np.zeros(len(t), dtype=np.int64)


def _clean(t: Array, x: Array, y: Array, yaw: Array, tof: Array
           ) -> tuple[NDArray[np.bool_], int]:
    """Readings usable by the fitter (finite pose; TOF NaN or finite positive)."""
    ok = np.isfinite(t) & np.isfinite(x) & np.isfinite(y) & np.isfinite(yaw)
    ok &= np.isnan(tof) | (np.isfinite(tof) & (tof > 0))
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
    # the object is on the min-TOF beam axis at range r, seen from that reading
    px, py = x[i] + r * math.cos(bearing), y[i] + r * math.sin(bearing)
    rx, ry = float(x[ref]), float(y[ref])
    r_ref = math.hypot(px - rx, py - ry)
    b_ref = math.atan2(py - ry, px - rx) if r_ref > 0 else bearing
    half_beam = math.radians(12.0)
    sd_r = math.sqrt(float(M.tof_variance_us2(0.0, cfg.module))) / M.us_per_m(cfg.module)
    local = np.array([r_ref, b_ref, cfg.kappa_guess_us])
    local_cov = np.diag([sd_r ** 2, half_beam ** 2 / 3.0, 1e4])
    params, cov, _ = M.to_frame("point", local, local_cov, np.array([rx, ry]))
    return Landmark("point", params, cov, r_ref, b_ref, int(finite.sum()), float(t[ref]),
                    (rx, ry, float(yaw[ref])), status, reason, tier="conventional",
                    sensors=sensors, extra={**extra, "n_noecho": int((~finite).sum())})


@dataclass
class _Choice:
    kind: str
    tier: str
    fit: BatchFit   # one row
    notes: list[str] = field(default_factory=list)
    extra: dict[str, object] = field(default_factory=dict)


def fit_segments(segments: Sequence[SegmentLike], config: FitConfig | None = None
                 ) -> list[Landmark]:
    """Fit one landmark to each segment (vectorised over all of them).

    Parameters
    ----------
    segments : :class:`Segment`, :class:`ScanReadings` or ``(t_s, x_m, y_m, yaw_rad,
        tof_us)`` arrays; poses in one fixed frame, TOF NaN = no echo.
    config : fitter settings (speed of sound, detection model, thresholds).

    Returns
    -------
    One :class:`Landmark` per segment, in order. Parameters are in the frame of the
    poses; ``ref_t_s``/``ref_pose`` are those of the segment's last echo.
    """
    cfg = config or FitConfig()
    n = len(segments)
    out: list[Landmark | None] = [None] * n
    cleaned: list[_Cleaned] = []
    meta: list[dict[str, object]] = []
    for seg in segments:
        t, x, y, yaw, tof, sensor = _arrays(seg)
        ok, n_bad = _clean(t, x, y, yaw, tof)
        cleaned.append((t[ok], x[ok], y[ok], M.wrap_angle(yaw[ok]), tof[ok], sensor[ok]))
        m: dict[str, object] = {"n_bad_input": n_bad}
        if isinstance(seg, Segment):
            m.update(seg_id=seg.seg_id, closed_by=seg.closed_by)
        meta.append(m)
    todo = []
    for i, arrs in enumerate(cleaned):
        n_echo = int(np.isfinite(arrs[4]).sum())
        if n_echo == 0:
            out[i] = _fallback(arrs, FitStatus.NO_ECHO, "no echo in the segment", cfg,
                               meta[i])
        elif n_echo < 3:
            out[i] = _fallback(arrs, FitStatus.TOO_FEW_POINTS,
                               f"{n_echo} echo(es); at least 3 are needed for "
                               "(range, bearing, kappa)", cfg, meta[i])
        else:
            todo.append(i)
    if todo:
        batch = pack_segments([cleaned[i][:5] for i in todo])
        choices = _fit_and_select(batch, cfg)
        for j, i in enumerate(todo):
            out[i] = _landmark(batch, j, choices[j], cleaned[i], cfg, meta[i])
    return [lm for lm in out if lm is not None]


def _fit_and_select(batch: SegmentBatch, cfg: FitConfig) -> list[_Choice]:
    """Fit point (and line where motion can tell), then the piston tier where needed."""
    B = batch.size
    base = np.max(np.hypot(np.where(batch.valid, batch.px, 0.0),
                           np.where(batch.valid, batch.py, 0.0)), axis=1)
    point = fit_batch(batch, "point", "gauss", cfg)
    moving = np.flatnonzero(base > cfg_baseline(cfg))
    line = None
    if moving.size:
        sub = _take_batch(batch, moving)
        line = fit_batch(sub, "line", "gauss", cfg)
    kinds, kind_notes, kind_extra = choose_kind(point, line, moving, cfg)
    choices: list[_Choice] = []
    for b in range(B):
        if kinds[b] == "line" and line is not None and b in set(moving.tolist()):
            j = int(np.flatnonzero(moving == b)[0])
            row = line.take(np.array([j]))
        else:
            row = point.take(np.array([b]))
        choices.append(_Choice(kinds[b], "gauss", row, list(kind_notes[b]), dict(kind_extra[b])))
    choose_tier(batch, choices, cfg)
    for b, ch in enumerate(choices):
        if base[b] <= cfg_baseline(cfg) and ch.extra.get("kind_basis") == "strength":
            # one viewpoint: point and line are the same fit; the final kappa decides
            ch.kind = "line" if ch.fit.local[0, 2] < KAPPA_WALL_US else "point"
    overlap_check(batch, choices, cfg)
    return choices


def cfg_baseline(cfg: FitConfig) -> float:
    """Transducer displacement within a segment [m] above which point and line are
    both fitted (motion may tell them apart)."""
    return 0.02


def _take_batch(batch: SegmentBatch, idx: NDArray[np.int64]) -> SegmentBatch:
    from sonarloc.fit.lsq import _take

    return _take(batch, idx)


def _landmark(batch: SegmentBatch, j: int, ch: _Choice, arrs: _Cleaned,
              cfg: FitConfig, meta: dict[str, object]) -> Landmark:
    f = ch.fit
    local = f.local[0].copy()
    local[1] = float(M.wrap_angle(local[1]))
    lcov = f.cov[0]
    ref_xy = batch.ref_xy[j]
    params, cov, _ = M.to_frame(ch.kind, local, lcov, ref_xy)
    t, x, y, yaw, tof, sensor = arrs
    finite = np.isfinite(tof)
    sensors = tuple(sorted({int(s) for s in sensor[finite]}))
    n_used = int(f.n_used[0])
    sd_phi = math.sqrt(max(lcov[1, 1], 0.0))
    sd_r = math.sqrt(max(lcov[0, 0], 0.0))
    kappa = float(local[2])
    resid_us = _raw_rms(f)
    extra: dict[str, object] = dict(meta)
    extra.update(ch.extra)
    extra.update(
        bearing_sd_deg=math.degrees(sd_phi), range_sd_m=sd_r,
        kappa_sd_us=math.sqrt(max(lcov[2, 2], 0.0)),
        strength_db=20.0 * math.log10(cfg.module.detection_limit_us / max(kappa, 1e-12)),
        n_noecho=int((~finite).sum()), n_spikes=int(finite.sum()) - n_used,
        chi2=float(f.chi2[0]), cost=float(f.cost[0]))
    status = FitStatus.OK
    reasons = list(ch.notes)
    lo, hi = f.arc[0]
    off = float(M.wrap_angle(local[1] - 0.5 * (lo + hi)))
    half = 0.5 * (hi - lo)
    outside = abs(off) - half
    finite_all = np.all(np.isfinite(params)) and np.all(np.isfinite(cov))
    if not finite_all:
        status = FitStatus.BAD_INPUT
        reasons.insert(0, "non-finite fit (bad input)")
    elif n_used < 3:
        status = FitStatus.TOO_FEW_POINTS
        reasons.insert(0, f"{n_used} echoes left after removing spikes")
    elif ch.extra.get("overlap"):
        status = FitStatus.UNRESOLVED
        reasons.insert(0, str(ch.extra["overlap"]))
    elif outside > math.radians(1.0) and _delay_span_us(batch, j, ch, cfg) > 3.0:
        status = FitStatus.PARTIAL
        reasons.insert(0, f"minimum of the U {math.degrees(outside):.1f} deg outside the arc "
                          "covered by echoes: bearing bounded only")
    elif sd_phi > math.radians(cfg.flat_bearing_sd_deg):
        status = FitStatus.FLAT
        reasons.insert(0, f"curve too flat for its bearing (SD {math.degrees(sd_phi):.1f} deg "
                          f"> {cfg.flat_bearing_sd_deg:g} deg)")
    ref_i = int(np.flatnonzero(finite)[-1])
    return Landmark(
        kind="point" if ch.kind == "point" else "line", params=params, cov=cov,
        range_m=float(local[0]), bearing_rad=float(local[1]), n_readings=n_used,
        ref_t_s=float(t[ref_i]), ref_pose=(float(x[ref_i]), float(y[ref_i]), float(yaw[ref_i])),
        status=status, reason="; ".join(reasons), tier=ch.tier, rms_us=resid_us,
        sensors=sensors, extra=extra)


def _delay_span_us(batch: SegmentBatch, j: int, ch: _Choice, cfg: FitConfig) -> float:
    """How much the fitted threshold delay varies over the used echoes [us]: a partial U
    shows a clear arm, a flat curve (strong plane) does not."""
    f = ch.fit
    used = f.used[0]
    if not used.any():
        return 0.0
    p = f.local[0]
    geo = M.geometry(ch.kind, p[0], p[1], batch.px[j, used], batch.py[j, used],
                     batch.yaw[j, used])
    g, _, _ = M.beam_delay_factor(geo.theta, ch.tier, cfg.module, derivative=False)
    d = np.minimum(p[2] * g, 1e6)
    return float(d.max() - d.min())


def _raw_rms(f: BatchFit) -> float:
    """RMS of the standardised residuals of the used echoes (1 = as the jitter model says)."""
    used = f.used[0]
    if not used.any():
        return math.nan
    return float(np.sqrt(np.mean(f.resid[0][used] ** 2)))


@dataclass
class FitReport:
    """Landmarks of a scan, with the segmenter's counters."""

    landmarks: list[Landmark]
    stats: SegmenterStats


def fit_scan(scan: ScanReadings, config: FitConfig | None = None,
             segmenter: SegmenterConfig | None = None) -> FitReport:
    """Segment a scan (in reading order) and fit every segment.

    Readings with non-finite poses or inf/zero/negative TOF are ignored (counted in
    ``stats.bad``); duplicate times are allowed (ring transducers firing together).
    """
    cfg = config or FitConfig()
    seg = Segmenter(segmenter, cfg.module)
    segments = list(seg.feed(scan))
    return FitReport(fit_segments(segments, cfg), seg.stats)


class OnlineFitter:
    """Readings in, landmarks out, one reading at a time (bounded memory).

    ``push`` takes the *transducer* pose at the ping in a fixed frame (for a robot:
    odometry pose composed with the transducer's mount and pan angle) and returns the
    landmarks of the segments that reading closed; ``flush`` closes the rest.
    """

    def __init__(self, config: FitConfig | None = None,
                 segmenter: SegmenterConfig | None = None) -> None:
        self.config = config or FitConfig()
        self.segmenter = Segmenter(segmenter, self.config.module)

    @property
    def stats(self) -> SegmenterStats:
        return self.segmenter.stats

    def push(self, t_s: float, x_m: float, y_m: float, yaw_rad: float, tof_us: float,
             sensor: int = 0) -> list[Landmark]:
        closed = self.segmenter.push(t_s, x_m, y_m, yaw_rad, tof_us, sensor)
        return fit_segments(closed, self.config) if closed else []

    def flush(self) -> list[Landmark]:
        closed = self.segmenter.flush()
        return fit_segments(closed, self.config) if closed else []

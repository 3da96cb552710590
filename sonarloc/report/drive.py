"""The report and figure of a drive: numbers against truth, and one PNG that shows them.

:class:`DriveReport` holds what ``sonarloc drive`` prints (and emits with ``--json``,
FORMATS.md section 6: at least ``pose_rmse_m``, ``yaw_rmse_deg``, ``landmarks_fitted``,
``wall_time_s``, ``plot``). :func:`drive_figure` draws the map, the true, odometry and
estimated paths, the fitted landmarks with their uncertainty, and a panel of TOF curves
with their fitted eq. 3 models.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from sonarloc import se2
from sonarloc.fit.result import Landmark
from sonarloc.physics.constants import GAUSS_SIGMA_DEG, SPEED_OF_SOUND_MPS

WARMUP_S = 5.0
"""Seconds after the start excluded from the *after warm-up* errors (the prior is off)."""


@dataclass
class DriveReport:
    """Outcome of one simulated drive (times in seconds, errors against truth)."""

    map: str
    rig: str
    device: str
    seed: int
    duration_s: float
    readings: int = 0
    echoes: int = 0
    odom_records: int = 0
    pose_rmse_m: float = math.nan
    yaw_rmse_deg: float = math.nan
    pose_max_m: float = math.nan
    pose_final_m: float = math.nan
    steady_pose_rmse_m: float = math.nan
    steady_yaw_rmse_deg: float = math.nan
    odom_pose_rmse_m: float = math.nan
    odom_yaw_rmse_deg: float = math.nan
    landmarks_fitted: int = 0
    landmarks_ok: int = 0
    landmarks_matched: int = 0
    landmarks_rejected: int = 0
    # associated and inside the gate, not fused: their map feature was fused from about
    # the same transducer pose already (LocalizerConfig.update_min_d / update_min_a)
    landmarks_skipped: int = 0
    readings_fused: int = 0
    status: str = ""
    compute_s: float = math.nan
    compute_per_reading_us: float = math.nan
    # The Localizer's CPU time per call (one record fed, the calling thread's time): what
    # a control loop that calls it must allow for. 99th percentile and worst call.
    call_p99_ms: float = math.nan
    call_max_ms: float = math.nan
    # background fit workers (LocalizerConfig.fit_workers; 0: fits in the call), and the
    # calls that waited for a fit (fit_max_lag_s)
    fit_workers: int = 0
    fit_executor: str = "thread"
    fit_waits: int = 0
    wall_time_s: float = math.nan
    realtime_factor: float = math.nan
    device_stats: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    plot: str | None = None

    @property
    def improvement(self) -> float:
        """Odometry-only pose RMSE over the estimate's (how many times better)."""
        if self.pose_rmse_m > 0:
            return self.odom_pose_rmse_m / self.pose_rmse_m
        return math.nan

    def to_json(self) -> dict[str, Any]:
        """A JSON-ready dict (NaN becomes None)."""
        out = asdict(self)
        out["improvement_over_odometry"] = self.improvement

        def clean(v: Any) -> Any:
            if isinstance(v, float) and not math.isfinite(v):
                return None
            if isinstance(v, dict):
                return {k: clean(x) for k, x in v.items()}
            if isinstance(v, list):
                return [clean(x) for x in v]
            if isinstance(v, (np.floating, np.integer)):
                return clean(v.item())
            return v

        return {k: clean(v) for k, v in out.items()}

    def text(self) -> str:
        """The short human-readable report."""
        def f(v: float, fmt: str) -> str:
            return format(v, fmt) if math.isfinite(v) else "n/a"

        lines = [
            f"sonarloc drive: {self.map}, rig {self.rig}, device {self.device}, seed {self.seed}, "
            f"{f(self.duration_s, '.1f')} s simulated",
            f"  readings        {self.readings} ({self.echoes} echoes), {self.odom_records} odom",
            f"  pose RMSE       {f(self.pose_rmse_m * 100, '.1f')} cm, yaw "
            f"{f(self.yaw_rmse_deg, '.2f')} deg   (max {f(self.pose_max_m * 100, '.1f')} cm, "
            f"final {f(self.pose_final_m * 100, '.1f')} cm)",
            f"  after warm-up   {f(self.steady_pose_rmse_m * 1000, '.1f')} mm, yaw "
            f"{f(self.steady_yaw_rmse_deg, '.2f')} deg   (from {WARMUP_S:g} s on; "
            "the prior is off by ~5 cm)",
            f"  odometry only   {f(self.odom_pose_rmse_m * 100, '.1f')} cm, yaw "
            f"{f(self.odom_yaw_rmse_deg, '.2f')} deg   (estimate "
            f"{f(self.improvement, '.1f')}x better)",
            f"  landmarks       {self.landmarks_fitted} segments ({self.landmarks_ok} fitted ok), "
            f"{self.landmarks_matched} matched to the map and fused, "
            f"{self.landmarks_rejected} rejected"
            + (f", {self.landmarks_skipped} skipped (their feature just fused from there)"
               if self.landmarks_skipped else "")
            + (f"; {self.readings_fused} readings fused" if self.readings_fused else ""),
            f"  compute         {f(self.compute_per_reading_us, '.0f')} us per reading "
            f"({'fit + filter' if not self.fit_workers else 'filter'}), "
            f"wall {f(self.wall_time_s, '.1f')} s, "
            f"{f(self.realtime_factor, '.1f')}x real time",
            f"  per record      {f(self.call_p99_ms, '.1f')} ms CPU at the 99th percentile, "
            f"{f(self.call_max_ms, '.1f')} ms at worst (one Localizer call)"
            + (f"; fits in {self.fit_workers} {self.fit_executor} worker"
               f"{'s' if self.fit_workers > 1 else ''}, {self.fit_waits} waits"
               if self.fit_workers else ""),
        ]
        if self.status:
            lines.append(f"  status          {self.status}")
        if self.device_stats:
            lines.append("  device          " + ", ".join(
                f"{k} {v}" for k, v in self.device_stats.items()))
        lines += [f"  note: {n}" for n in self.notes]
        if self.plot:
            lines.append(f"  plot            {self.plot}")
        return "\n".join(lines)


def map_from_odom(est: NDArray[np.float64], odom: NDArray[np.float64]) -> NDArray[np.float64]:
    """``map -> odom`` transforms (..., 3) from matching estimate and odometry poses (..., 3)."""
    return se2.compose(est, se2.inverse(odom))


@dataclass(frozen=True)
class SegmentView:
    """Readings of one fitted segment, for the TOF panel (poses in the fit's frame)."""

    landmark: Landmark
    x_m: NDArray[np.float64]
    y_m: NDArray[np.float64]
    yaw_rad: NDArray[np.float64]
    tof_us: NDArray[np.float64]
    label: str = ""


def pick_segments(views: Sequence[SegmentView], n: int = 4, per_panel: int = 6
                  ) -> list[list[SegmentView]]:
    """Up to ``n`` panels of segments: one label (kind) per panel, in the given order,
    each with up to ``per_panel`` segments of that kind (trusted fits, >= 5 echoes)."""
    groups: dict[str, list[SegmentView]] = {}
    for v in views:
        if v.landmark.ok and np.isfinite(v.tof_us).sum() >= 5:
            group = groups.setdefault(v.label or v.landmark.kind, [])
            if len(group) < per_panel:
                group.append(v)
    return list(groups.values())[:n]


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" + ("" if n == 1 else "s")


def drive_figure(
    out: str | Path,
    *,
    map_source: str | Path | Mapping[str, Any] | None,
    tracks: Mapping[str, NDArray[np.float64]],
    landmarks: Sequence[tuple[Landmark, bool]],
    segments: Sequence[SegmentView],
    report: DriveReport,
    c_mps: float = SPEED_OF_SOUND_MPS,
    sigma_deg: float = GAUSS_SIGMA_DEG,
    n_sigma: float = 3.0,
    outlier_us: float = 30.0,
    dpi: int = 120,
) -> Path:
    """Write the drive PNG: map + paths + landmarks (left), TOF curves with fits (right).

    ``tracks``: name -> (n, 4) poses (t_s, x_m, y_m, yaw_rad) in ``map`` (``truth``,
    ``odometry``, ``estimate``); ``landmarks``: (landmark in ``map``, matched to the map);
    ``segments``: fitted segments with their readings, in the fit frame.
    """
    from sonarloc.report.plots import (
        beam_delay_us,
        draw_excess_delay,
        draw_landmarks,
        draw_map,
        draw_tracks,
        finish_plane_axes,
        landmark_model_us,
        require_matplotlib,
    )

    plt = require_matplotlib()
    fig = plt.figure(figsize=(14.5, 7.2))
    gs = fig.add_gridspec(2, 3, width_ratios=[2.3, 1, 1], wspace=0.3, hspace=0.38)
    ax = fig.add_subplot(gs[:, 0])
    if map_source is not None:
        draw_map(ax, map_source)
        xmin, xmax = ax.get_xlim()
        ymin, ymax = ax.get_ylim()
    draw_tracks(ax, {k: (v[:, 1], v[:, 2]) for k, v in tracks.items()})
    matched = [lm for lm, fused in landmarks if fused and lm.ok]
    other = [lm for lm, fused in landmarks if not fused and lm.ok]
    draw_landmarks(ax, other, n_sigma=n_sigma, color="0.7", line_half_length_m=0.2,
                   label=f"fitted, not matched ({n_sigma:g}σ)")
    draw_landmarks(ax, matched, n_sigma=n_sigma,
                   label=f"fitted and matched to the map ({n_sigma:g}σ)")
    bad = [lm for lm, _ in landmarks if not lm.ok and lm.kind == "point"]
    if bad:
        ax.plot([lm.params[0] for lm in bad], [lm.params[1] for lm in bad], "x",
                color="0.6", alpha=0.5, ms=4, label="fits not trusted (status)")

    def f(v: float, scale: float = 1.0, fmt: str = ".1f") -> str:
        return format(v * scale, fmt) if math.isfinite(v) else "n/a"

    finish_plane_axes(ax, f"{report.map}: pose RMSE {f(report.pose_rmse_m, 100)} cm, "
                          f"{f(report.yaw_rmse_deg, 1, '.2f')}° (odometry only "
                          f"{f(report.odom_pose_rmse_m, 100)} cm, "
                          f"{f(report.odom_yaw_rmse_deg, 1, '.2f')}°)", legend=False,
                      adjustable="box")
    if map_source is not None:  # keep the view on the map, not on stray fits
        ax.set_xlim(xmin - 0.3, xmax + 0.3)
        ax.set_ylim(ymin - 0.3, ymax + 0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=4,
              frameon=False)
    panels = pick_segments(segments, 4)
    colors = ["tab:blue", "tab:green", "tab:purple", "tab:brown"]
    for i in range(4):
        sub = fig.add_subplot(gs[i // 2, 1 + i % 2])
        if i >= len(panels):
            sub.axis("off")
            continue
        n_used = 0
        marked = False
        kappas: list[float] = []
        transducers: set[int] = set()
        tiers: set[str] = set()
        for j, v in enumerate(panels[i]):
            lm = v.landmark
            model, theta = landmark_model_us(lm, v.x_m, v.y_m, v.yaw_rad, c_mps, sigma_deg)
            expected = beam_delay_us(lm.kappa_us, theta, lm.tier, sigma_deg, c_mps)
            delay = v.tof_us - (model - expected)  # each reading against its own fit's To
            finite = np.isfinite(delay)
            # readings the fit did not explain (other reflectors, spikes): marked, not hidden
            used = finite & (np.abs(delay - expected) <= outlier_us)
            draw_excess_delay(sub, theta[used], delay[used], lm.kappa_us, sigma_deg,
                              label="fitted models" if j == 0 else "", color=colors[i],
                              tier=lm.tier)
            off = finite & ~used
            if off.any():
                sub.plot(np.degrees(theta[off]),
                         np.clip(delay[off], -outlier_us * 1.5, outlier_us * 2.5), "x",
                         ms=3, color="0.6",
                         label=None if marked else f"> {outlier_us:g} µs off the fit")
                marked = True
            n_used += int(used.sum())
            kappas.append(lm.kappa_us)
            transducers.update(lm.sensors)
            tiers.add(lm.tier)
        what = panels[i][0].label or panels[i][0].landmark.kind
        k = sorted(kappas)
        ktext = f"κ={k[0]:.2f} µs" if len(k) == 1 else f"κ {k[0]:.2f}–{k[-1]:.2f} µs"
        sub.set_title(f"{what}: {_count(len(panels[i]), 'segment')}, {n_used} echoes\n"
                      f"{ktext}, {_count(len(transducers), 'transducer')}, "
                      f"tier {'/'.join(sorted(tiers))}", fontsize=8)
        sub.set_xlabel("angle off the transducer axis (deg)", fontsize=8)
        sub.set_ylabel("TOF − 2r/c (µs)", fontsize=8)
        sub.tick_params(labelsize=7)
        sub.grid(True, alpha=0.3)
        sub.legend(fontsize=6.5, loc="upper center")
        sub.set_ylim(-outlier_us * 1.6, outlier_us * 2.7)
    fig.suptitle(f"sonarloc drive — rig {report.rig}, device {report.device}, "
                 f"{f(report.duration_s)} s simulated, {report.landmarks_fitted} segments, "
                 f"{report.landmarks_matched} matched to the map and fused", fontsize=11)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return out

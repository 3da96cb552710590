"""Drawing helpers: scans with model curves, maps, sonar maps, trajectories, landmarks.

matplotlib is an optional extra (``pip install 'sonarloc[plot]'``); it is imported only
by :func:`require_matplotlib`, with the Agg backend unless one was chosen already. Every
``draw_*`` function takes a matplotlib ``Axes`` and plain arrays (SI units, angles in
radians unless the name says ``_deg``), so the same code serves ``sonarloc plot``,
``sonarloc drive`` and the benchmarks.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from sonarloc.errors import MapError, SonarlocError
from sonarloc.fit.result import Landmark
from sonarloc.physics.constants import GAUSS_SIGMA_DEG, SPEED_OF_SOUND_MPS
from sonarloc.physics.tof import eq3_tof_us

TRACK_STYLES: dict[str, dict[str, Any]] = {
    "truth": {"color": "black", "lw": 1.6, "ls": "-"},
    "odometry": {"color": "tab:orange", "lw": 1.3, "ls": "--"},
    "estimate": {"color": "tab:blue", "lw": 1.3, "ls": "-"},
}
KIND_STYLES: dict[str, dict[str, Any]] = {
    "pole": {"marker": "o", "color": "dimgray"},
    "rod": {"marker": ".", "color": "dimgray"},
    "corner": {"marker": "s", "color": "gray"},
    "edge": {"marker": "^", "color": "gray"},
    "point": {"marker": "x", "color": "gray"},
}


def matplotlib_available() -> bool:
    """Whether the optional extra ``plot`` (matplotlib) is installed."""
    import importlib.util

    return importlib.util.find_spec("matplotlib") is not None


def require_matplotlib() -> Any:
    """``matplotlib.pyplot`` (Agg backend by default), or a clear error if it is missing."""
    try:
        import matplotlib
    except ImportError as err:
        raise SonarlocError(
            "plots need matplotlib, an optional extra: pip install 'sonarloc[plot]'") from err
    if "matplotlib.pyplot" not in __import__("sys").modules:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# --------------------------------------------------------------------------- models

def beam_delay_us(kappa_us: ArrayLike, theta_rad: ArrayLike, tier: str = "gauss",
                  sigma_deg: float = GAUSS_SIGMA_DEG, c_mps: float = SPEED_OF_SOUND_MPS
                  ) -> NDArray[np.float64]:
    """Threshold delay kappa / rel_amp(theta) of the beam model a fit used [us].

    ``tier``: ``"piston"`` and ``"waveform"`` use the piston echo pattern (infinite at its
    nulls; the waveform tier's later crossing of weak echoes is not drawn); any other
    tier the Gaussian main lobe of eq. 3, kappa·exp(theta²/2sigma²).
    """
    k = np.asarray(kappa_us, dtype=float)
    t = np.asarray(theta_rad, dtype=float)
    if tier in ("piston", "waveform"):
        from sonarloc.physics.beam import piston_echo

        a = piston_echo(t, c_mps=c_mps)
        with np.errstate(divide="ignore"):
            return np.where(a > 0, k / np.where(a > 0, a, 1.0), np.inf)
    return k * np.exp(t * t / (2.0 * np.radians(sigma_deg) ** 2))


def landmark_model_us(
    lm: Landmark, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike,
    c_mps: float = SPEED_OF_SOUND_MPS, sigma_deg: float = GAUSS_SIGMA_DEG,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Noise-free TOF of a fitted landmark seen from transducer poses (eq. 3, or the
    piston pattern when the fit used that tier).

    Parameters
    ----------
    lm : a point (x, y, kappa) or line (rho, alpha, kappa) landmark, in the poses' frame.
    x_m, y_m, yaw_rad : (...,) transducer positions and axis directions.

    Returns
    -------
    tof_us : (...,) Tm = To + :func:`beam_delay_us`, To = 2 range / c.
    theta_rad : (...,) angle of the reflecting point off the transducer axis, wrapped.
    """
    x, y, yaw = (np.asarray(v, dtype=float) for v in (x_m, y_m, yaw_rad))
    p0, p1, kappa = (float(v) for v in lm.params[:3])
    if lm.kind == "point":
        dx, dy = p0 - x, p1 - y
        rng = np.hypot(dx, dy)
        direction = np.arctan2(dy, dx)
    else:
        n_dot = x * math.cos(p1) + y * math.sin(p1)
        signed = p0 - n_dot
        rng = np.abs(signed)
        direction = np.where(signed >= 0, p1, p1 + math.pi)
    theta = np.angle(np.exp(1j * (direction - yaw)))
    to_us = 2.0 * rng / c_mps * 1e6
    if lm.tier in ("piston", "waveform"):
        return to_us + beam_delay_us(kappa, theta, "piston", sigma_deg, c_mps), theta
    return eq3_tof_us(to_us, theta, kappa, sigma_deg), theta


def covariance_ellipse(mean: ArrayLike, cov: ArrayLike, n_sigma: float = 2.0, n: int = 64
                       ) -> NDArray[np.float64]:
    """(n, 2) outline of the ``n_sigma`` ellipse of a 2-D Gaussian (NaN if cov is not PSD)."""
    c = np.asarray(cov, dtype=float)[:2, :2]
    m = np.asarray(mean, dtype=float)[:2]
    c = 0.5 * (c + c.T)
    if not np.all(np.isfinite(c)):
        return np.full((n, 2), np.nan)
    w, v = np.linalg.eigh(c)
    if w[0] < -1e-12 * max(1.0, abs(w[1])):
        return np.full((n, 2), np.nan)
    t = np.linspace(0, 2 * np.pi, n)
    circle = np.stack([np.cos(t), np.sin(t)], -1) * np.sqrt(np.clip(w, 0, None)) * n_sigma
    return m + circle @ v.T


# --------------------------------------------------------------------------- drawing

def draw_scan(
    ax: Any, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike, tof_us: ArrayLike,
    landmarks: Sequence[Landmark] = (), c_mps: float = SPEED_OF_SOUND_MPS,
    sigma_deg: float = GAUSS_SIGMA_DEG, max_delay_us: float = 25.0,
) -> None:
    """A scan as TOF against bearing, referenced to its smallest TOF (the paper's Fig. 4/5).

    Readings are dots (no-echo readings are ticks below zero); each landmark's eq. 3
    curve, seen from the scan's mean transducer position over a fine grid of bearings,
    is dashed where its threshold delay stays below ``max_delay_us``. Meant for pans from
    one spot; for a moving robot use :func:`draw_excess_delay`.
    """
    yaw = np.asarray(yaw_rad, dtype=float)
    tof = np.asarray(tof_us, dtype=float)
    ok = np.isfinite(tof)
    ref = float(np.min(tof[ok])) if ok.any() else 0.0
    ax.plot(np.degrees(yaw[ok]), tof[ok] - ref, ".", ms=2.5, color="tab:gray",
            label="readings", zorder=2)
    if (~ok).any():
        ax.plot(np.degrees(yaw[~ok]), np.zeros((~ok).sum()) - 2.0, "|", ms=4,
                color="lightgray", label="no echo", zorder=1)
    px = float(np.mean(np.asarray(x_m, dtype=float)))
    py = float(np.mean(np.asarray(y_m, dtype=float)))
    grid = np.linspace(yaw.min() if yaw.size else -1.0, yaw.max() if yaw.size else 1.0, 1200)
    colors = iter(["tab:red", "tab:blue", "tab:green", "tab:purple", "tab:brown", "tab:olive",
                   "tab:cyan", "tab:pink"] * 50)
    for lm in landmarks:
        model, theta = landmark_model_us(lm, px, py, grid, c_mps, sigma_deg)
        to = model - beam_delay_us(lm.kappa_us, theta, lm.tier, sigma_deg, c_mps)
        show = (model - to) <= max_delay_us
        curve = np.where(show, model - ref, np.nan)
        color = next(colors)
        bearing = math.degrees(lm.bearing_rad)
        ax.plot(np.degrees(grid), curve, "--", lw=1.2, color=color,
                label=f"{lm.kind} {bearing:+.1f}°, κ={lm.kappa_us:.2f} µs, "
                      f"r={lm.range_m:.3f} m")
    ax.set_xlabel("transducer bearing (deg)")
    ax.set_ylabel(f"TOF − {ref:.0f} µs (µs)")
    ax.grid(True, alpha=0.3)


def draw_excess_delay(
    ax: Any, theta_rad: ArrayLike, delay_us: ArrayLike, kappa_us: float,
    sigma_deg: float = GAUSS_SIGMA_DEG, label: str = "", color: str = "tab:blue",
    tier: str = "gauss",
) -> None:
    """Readings of one landmark as delay Tm − To against the angle off the transducer axis.

    With To from the fitted landmark and each reading's own pose, readings of a moving
    ring collapse onto one curve kappa/rel_amp(theta) (:func:`beam_delay_us` of the fit's
    tier), drawn dashed.
    """
    th = np.degrees(np.asarray(theta_rad, dtype=float))
    d = np.asarray(delay_us, dtype=float)
    ax.plot(th, d, ".", ms=3, color=color, alpha=0.7)
    if th.size:
        lim = max(abs(th.min()), abs(th.max()), 1.0)
        grid = np.linspace(-lim, lim, 300)
        model = beam_delay_us(kappa_us, np.radians(grid), tier, sigma_deg)
        ax.plot(grid, np.where(np.isfinite(model), model, np.nan), "--", color=color, lw=1.2,
                label=label or None)


def _features(source: str | Path | Mapping[str, Any]) -> list[dict[str, Any]]:
    if isinstance(source, Mapping):
        obj: Any = source
    else:
        try:
            obj = json.loads(Path(source).read_text(encoding="utf-8"))
        except OSError as err:
            raise MapError(f"cannot open map {source}: {err.strerror}") from err
        except json.JSONDecodeError as err:
            raise MapError(f"map {source}: line {err.lineno}: {err.msg}") from err
    feats = obj.get("features") if isinstance(obj, Mapping) else None
    if not isinstance(feats, list):
        raise MapError(f"map {source if not isinstance(source, Mapping) else ''}: "
                       "expected a GeoJSON FeatureCollection")
    return [f for f in feats if isinstance(f, dict)]


def draw_map(ax: Any, source: str | Path | Mapping[str, Any], labels: bool = False) -> None:
    """Walls, planes and point reflectors of a map GeoJSON (FORMATS.md section 3)."""
    drawn: set[str] = set()
    for f in _features(source):
        g = f.get("geometry") or {}
        props = f.get("properties") or {}
        kind = str(props.get("kind", ""))
        gtype, coords = g.get("type"), g.get("coordinates")
        if coords is None:
            continue
        if gtype in ("LineString", "Polygon", "MultiLineString"):
            lines = [coords] if gtype == "LineString" else coords
            for line in lines:
                a = np.asarray(line, dtype=float).reshape(-1, 2)
                if kind == "route":
                    ax.plot(a[:, 0], a[:, 1], ":", color="0.6", lw=1.0,
                            label=None if "route" in drawn else "route")
                    drawn.add("route")
                    continue
                style = {"color": "0.25", "lw": 2.0} if kind != "plane" else \
                    {"color": "tab:brown", "lw": 2.0}
                ax.plot(a[:, 0], a[:, 1], solid_capstyle="butt",
                        label=None if "wall" in drawn else "map walls", **style)
                drawn.add("wall")
        elif gtype == "Point":
            x, y = float(coords[0]), float(coords[1])
            st = KIND_STYLES.get(kind, KIND_STYLES["point"])
            radius = float(props.get("radius_m", 0) or 0)
            if radius > 0.005:
                import matplotlib.patches as mpatches

                ax.add_patch(mpatches.Circle((x, y), radius, color=st["color"], alpha=0.8))
            ax.plot([x], [y], st["marker"], color=st["color"], ms=5,
                    label=None if kind in drawn else f"map {kind}s")
            drawn.add(kind)
            if labels and props.get("id") is not None:
                ax.annotate(str(props["id"]), (x, y), xytext=(3, 3),
                            textcoords="offset points", fontsize=7)


def draw_sonar_map(
    ax: Any, x_m: ArrayLike, y_m: ArrayLike, yaw_rad: ArrayLike, tof_us: ArrayLike,
    c_mps: float = SPEED_OF_SOUND_MPS, half_arc_deg: float = 11.0, max_arcs: int = 4000,
    color: str = "tab:purple",
) -> None:
    """Readings as arcs in the plane: range c·Tm/2 from each transducer, ± ``half_arc_deg``.

    The classic sonar map: an echo says "something at this range within the beam"; the
    arc's centre is where a conventional reading puts the object (on the beam axis).
    At most ``max_arcs`` arcs are drawn (evenly subsampled), every centre as a dot.
    """
    x, y, yaw, tof = (np.asarray(v, dtype=float).ravel() for v in (x_m, y_m, yaw_rad, tof_us))
    ok = np.isfinite(tof)
    x, y, yaw, r = x[ok], y[ok], yaw[ok], tof[ok] * 1e-6 * c_mps / 2.0
    if not r.size:
        return
    ax.plot(x + r * np.cos(yaw), y + r * np.sin(yaw), ".", ms=1.5, color=color, alpha=0.6,
            label="echoes on the beam axis")
    idx = np.linspace(0, r.size - 1, min(max_arcs, r.size)).astype(int)
    phi = np.radians(np.linspace(-half_arc_deg, half_arc_deg, 9))
    ang = yaw[idx, None] + phi[None, :]
    ax_x = x[idx, None] + r[idx, None] * np.cos(ang)
    ax_y = y[idx, None] + r[idx, None] * np.sin(ang)
    from matplotlib.collections import LineCollection

    segs = np.stack([ax_x, ax_y], -1)
    ax.add_collection(LineCollection(list(segs), colors=color, linewidths=0.4, alpha=0.15))


def draw_tracks(ax: Any, tracks: Mapping[str, tuple[ArrayLike, ArrayLike]],
                styles: Mapping[str, Mapping[str, Any]] | None = None) -> None:
    """Paths in the plane: ``{"truth": (x, y), "odometry": (x, y), "estimate": (x, y)}``."""
    styles = styles or TRACK_STYLES
    for name, (xs, ys) in tracks.items():
        st = dict(styles.get(name, {"lw": 1.0}))
        ax.plot(np.asarray(xs, dtype=float), np.asarray(ys, dtype=float), label=name, **st)


def draw_landmarks(ax: Any, landmarks: Iterable[Landmark], n_sigma: float = 3.0,
                   line_half_length_m: float = 0.4, color: str = "tab:red",
                   label: str = "fitted landmarks", max_bands: int = 40) -> int:
    """Fitted landmarks with their ``n_sigma`` uncertainty: ellipses (points), bands (walls).

    A wall (rho, alpha) is drawn as a segment of ``line_half_length_m`` either side of the
    foot of the perpendicular from the segment's reference pose; the first ``max_bands``
    walls also get their ±``n_sigma`` band in rho (more would hide the map). Returns how
    many were drawn.
    """
    bands = 0
    count = 0
    for lm in landmarks:
        p0, p1 = float(lm.params[0]), float(lm.params[1])
        first = count == 0
        if lm.kind == "point":
            ax.plot([p0], [p1], "+", color=color, ms=6, mew=1.2, label=label if first else None)
            e = covariance_ellipse((p0, p1), lm.cov[:2, :2], n_sigma)
            ax.plot(e[:, 0], e[:, 1], "-", color=color, lw=0.8)
        else:
            rx, ry = lm.ref_pose[0], lm.ref_pose[1]
            n = np.array([math.cos(p1), math.sin(p1)])
            foot = np.array([rx, ry]) + (p0 - n @ (rx, ry)) * n
            t = np.array([-n[1], n[0]])
            seg = foot + np.outer([-line_half_length_m, line_half_length_m], t)
            ax.plot(seg[:, 0], seg[:, 1], "-", color=color, lw=1.6,
                    label=label if first else None)
            sd_rho = math.sqrt(max(float(lm.cov[0, 0]), 0.0))
            band = n_sigma * sd_rho
            if bands < max_bands:
                bands += 1
                for s in (-band, band):
                    ax.plot(seg[:, 0] + s * n[0], seg[:, 1] + s * n[1], ":", color=color,
                            lw=0.7)
        count += 1
    return count


def finish_plane_axes(ax: Any, title: str = "", legend: bool = True,
                      adjustable: str = "datalim") -> None:
    """Equal aspect, metres on both axes, a light grid and a compact legend."""
    ax.set_aspect("equal", adjustable=adjustable)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, alpha=0.25)
    if title:
        ax.set_title(title, fontsize=10)
    if legend:
        ax.legend(fontsize=7, loc="best", framealpha=0.85)

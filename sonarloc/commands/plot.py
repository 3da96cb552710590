"""Plots: a scan with its fitted model curves, a sonar map, a trajectory.

  sonarloc plot scan SCAN.csv [--fits FITS.json] --out scan.png
  sonarloc plot map LOG.jsonl [--map MAP.geojson] [--poses POSES.csv] --out sonarmap.png
  sonarloc plot trajectory LOG.jsonl [--poses POSES.csv] [--map MAP.geojson] --out traj.png

`scan` draws TOF against transducer bearing referenced to the smallest TOF, with the
eq. 3 curve of each landmark dashed (the paper's Fig. 4/5); landmarks come from --fits
(the output of `sonarloc fit --json`) or, without it, from fitting the scan here.
`map` draws each echo as an arc at its range across the beam. `trajectory` draws truth,
odometry (aligned at the start) and the estimate. Needs matplotlib (extra `plot`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from sonarloc.commands._args import refuse_overwrite


def _kind(sub: Any, name: str, help_text: str, what: str) -> argparse.ArgumentParser:
    """A plot kind's parser; its --help says what it draws (and needs), not only usage."""
    return sub.add_parser(name, help=help_text, description=f"{what} Needs matplotlib "
                          "(extra `plot`).")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="plot_command", metavar="KIND", required=True)
    scan = _kind(sub, "scan", "TOF against bearing with fitted model curves",
                 "TOF against transducer bearing referenced to the smallest TOF, with the eq. 3 "
                 "curve of each landmark dashed (the paper's Fig. 4/5).")
    scan.add_argument("scan", help="scan CSV (FORMATS.md section 1)")
    scan.add_argument("--fits", help="landmarks JSON from `sonarloc fit --json` (default: fit "
                                     "the scan here)")
    scan.add_argument("--no-fit", action="store_true", help="draw the readings only")
    scan.add_argument("--sensor", type=int, help="only this transducer's readings")
    smap = _kind(sub, "map", "sonar map: readings as arcs in the plane",
                 "Each echo drawn as an arc at its range across the beam (the classic sonar map).")
    smap.add_argument("log", help="log JSONL (FORMATS.md section 4)")
    smap.add_argument("--poses", help="pose CSV to place the readings (default: truth if the "
                                      "log has it, else odometry)")
    smap.add_argument("--arc", type=float, default=11.0, metavar="DEG",
                      help="half-width of each reading's arc (default 11 deg)")
    traj = _kind(sub, "trajectory", "truth, odometry and estimated paths",
                 "Truth (when the log has it), odometry aligned at the start, and the estimate "
                 "of --poses.")
    traj.add_argument("log", help="log JSONL (FORMATS.md section 4)")
    traj.add_argument("--poses", help="pose CSV from `sonarloc localize`")
    for p in (smap, traj):
        p.add_argument("--map", help="map GeoJSON to draw underneath")
    for p in (scan, smap, traj):
        p.add_argument("--out", required=True, help="PNG (or PDF/SVG) to write")
        p.add_argument("--title", default="", help="figure title")
        p.add_argument("--dpi", type=int, default=130, help="resolution (default 130)")


def _scan_figure(args: argparse.Namespace, plt: Any) -> Any:
    import numpy as np

    from sonarloc.io.scancsv import read_scan_csv
    from sonarloc.report.plots import draw_scan

    readings = read_scan_csv(args.scan)
    if args.sensor is not None:
        readings = readings.select(readings.sensor == args.sensor)
    if len(readings) == 0:
        raise ValueError(f"scan {args.scan} has no readings"
                         + (f" of sensor {args.sensor}" if args.sensor is not None else ""))
    landmarks = []
    if args.fits:
        from sonarloc.report.fitjson import read_fit_json

        landmarks = read_fit_json(args.fits)
    elif not args.no_fit:
        from sonarloc.fit.landmarks import fit_scan

        landmarks = fit_scan(readings).landmarks
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    draw_scan(ax, readings.x_m, readings.y_m, readings.yaw_rad, readings.tof_us, landmarks)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2,
              frameon=False)
    n_echo = int(np.isfinite(readings.tof_us).sum())
    ax.set_title(args.title or f"{Path(args.scan).name}: {len(readings)} pings, {n_echo} echoes, "
                 f"{len(landmarks)} landmarks", fontsize=9)
    return fig


def _robot_track(data: Any, poses_path: str | None) -> tuple[Any, str]:
    import numpy as np

    from sonarloc.report.logdata import odometry_in_map

    if poses_path:
        from sonarloc.io.posescsv import read_poses_csv

        est = read_poses_csv(poses_path)
        track = np.stack([est.t_s, est.x_m, est.y_m, np.unwrap(est.yaw_rad)], -1)
        return track, "estimate"
    if data.has_truth:
        return data.truth, "truth"
    return odometry_in_map(data), "odometry"


def _map_figure(args: argparse.Namespace, plt: Any) -> Any:
    import numpy as np

    from sonarloc.report.logdata import load_log, transducer_poses
    from sonarloc.report.plots import draw_map, draw_sonar_map, draw_tracks, finish_plane_axes

    data = load_log(args.log)
    track, which = _robot_track(data, args.poses)
    if len(track) == 0:
        raise ValueError(f"log {args.log} has no poses to place its readings (no odom/truth)")
    sp = transducer_poses(data, track)
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    if args.map:
        draw_map(ax, args.map)
    draw_sonar_map(ax, sp[:, 0], sp[:, 1], sp[:, 2], data.tof[:, 2],
                   c_mps=data.rig.speed_of_sound_mps, half_arc_deg=args.arc)
    draw_tracks(ax, {which: (track[:, 1], track[:, 2])})
    n_echo = int(np.isfinite(data.tof[:, 2]).sum())
    finish_plane_axes(ax, args.title or f"sonar map of {Path(args.log).name}: {n_echo} echoes "
                      f"placed with {which} poses")
    return fig


def _trajectory_figure(args: argparse.Namespace, plt: Any) -> Any:
    import numpy as np

    from sonarloc.report.logdata import load_log, odometry_in_map
    from sonarloc.report.plots import draw_map, draw_tracks, finish_plane_axes

    data = load_log(args.log)
    tracks = {}
    if data.has_truth:
        tracks["truth"] = (data.truth[:, 1], data.truth[:, 2])
    if len(data.odom):
        o = odometry_in_map(data)
        tracks["odometry"] = (o[:, 1], o[:, 2])
    est = None
    if args.poses:
        from sonarloc.io.posescsv import read_poses_csv

        est = read_poses_csv(args.poses)
        tracks["estimate"] = (est.x_m, est.y_m)
    if not tracks:
        raise ValueError(f"log {args.log} has no odom or truth records and no --poses given")
    fig, ax = plt.subplots(figsize=(7.5, 6.5))
    if args.map:
        draw_map(ax, args.map)
    draw_tracks(ax, tracks)
    if est is not None and len(est):
        from sonarloc.report.plots import covariance_ellipse

        for i in np.linspace(0, len(est) - 1, min(25, len(est))).astype(int):
            e = covariance_ellipse((est.x_m[i], est.y_m[i]), est.cov[i], 3.0)
            ax.plot(e[:, 0], e[:, 1], color="tab:blue", lw=0.6, alpha=0.7)
    finish_plane_axes(ax, args.title or f"trajectory of {Path(args.log).name}"
                      + (" (estimate: 3-sigma ellipses)" if est is not None else ""))
    return fig


def run(args: argparse.Namespace) -> int:
    from sonarloc.report.plots import require_matplotlib

    inputs = {"SCAN": "scan", "LOG": "log", "--fits": "fits", "--poses": "poses",
              "--map": "map"}   # (each plot has some of them)
    refuse_overwrite({"--out": args.out},
                     {name: getattr(args, attr, None) for name, attr in inputs.items()})
    plt = require_matplotlib()
    make = {"scan": _scan_figure, "map": _map_figure, "trajectory": _trajectory_figure}
    fig = make[args.plot_command](args, plt)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(out, dpi=args.dpi)
    plt.close(fig)
    print(f"wrote {out}", file=sys.stderr)
    return 0

"""Landmarks from TOF readings: `sonarloc fit SCAN.csv [--json]`.

Reads a scan CSV (one row per ping with the transducer pose; FORMATS.md section 1),
segments it into one U-shaped TOF curve per landmark pass, fits each with Kuc's
forward model (range, bearing, reflecting strength kappa) and prints the landmarks
(FORMATS.md section 2 with --json; a table otherwise).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from sonarloc.fit.landmarks import fit_scan
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.result import Landmark
from sonarloc.fit.segment import SegmenterConfig
from sonarloc.io.scancsv import read_scan_csv
from sonarloc.physics.sound import speed_of_sound_mps
from sonarloc.physics.tof import ModuleParams


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scan", metavar="SCAN.csv", help="scan CSV (FORMATS.md section 1)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object {\"landmarks\": [...]} (FORMATS.md section 2)")
    sound = parser.add_mutually_exclusive_group()
    sound.add_argument("--speed-of-sound", type=float, metavar="M/S", default=None,
                       help="speed of sound in m/s (default 343)")
    sound.add_argument("--temperature", type=float, metavar="DEG_C", default=None,
                       help="air temperature in deg C (speed of sound 331.3 + 0.606 T)")
    parser.add_argument("--only-ok", action="store_true",
                        help="print only landmarks whose fit status is ok")
    parser.add_argument("--no-detection-model", action="store_true",
                        help="fit the TOF curve only (ignore what no-echo readings say)")
    parser.add_argument("--odometry-sd", type=float, metavar="DEG_PER_M", default=None,
                        help="SD of the poses' heading-drift rate within a segment (the "
                             "odometry term of moving segments' covariance; default 1.0, "
                             "calibrated on the simulator's odometry; 0 for exact poses)")
    parser.add_argument("--max-travel", type=float, metavar="M", default=None,
                        help="close a segment once its transducer is this far from where "
                             "its first echo was taken (odometry drift makes longer passes "
                             "unfittable; default 1.0; 0: whole passes, for exact poses)")


def _num(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def landmark_to_json(lm: Landmark) -> dict[str, Any]:
    """A landmark as the JSON object of FORMATS.md section 2 (non-finite -> null)."""
    p = lm.params
    d: dict[str, Any] = {"kind": lm.kind}
    if lm.kind == "point":
        d.update(x_m=_num(p[0]), y_m=_num(p[1]))
    else:
        d.update(rho_m=_num(p[0]), alpha_deg=_num(math.degrees(p[1])))
    d.update(
        range_m=_num(lm.range_m), bearing_deg=_num(math.degrees(lm.bearing_rad)),
        kappa_us=_num(p[2]), n_readings=int(lm.n_readings),
        cov=[[_num(v) for v in row] for row in np.asarray(lm.cov, dtype=float).tolist()],
        status=lm.status.value, reason=lm.reason, tier=lm.tier, rms=_num(lm.rms_us),
        ref_t_s=_num(lm.ref_t_s),
        ref_pose={"x_m": _num(lm.ref_pose[0]), "y_m": _num(lm.ref_pose[1]),
                  "yaw_deg": _num(math.degrees(lm.ref_pose[2]))},
        sensors=list(lm.sensors),
    )
    for key in ("strength_db", "bearing_sd_deg", "range_sd_m", "kappa_sd_us", "kind_basis",
                "tier_basis", "n_noecho", "n_spikes"):
        if key in lm.extra:
            v = lm.extra[key]
            d[key] = _num(float(v)) if isinstance(v, (int, float)) and not isinstance(
                v, bool) and key not in ("n_noecho", "n_spikes") else v
    return d


def run(args: argparse.Namespace) -> int:
    module = ModuleParams()
    if args.speed_of_sound is not None:
        module = ModuleParams(c_mps=args.speed_of_sound)
    elif args.temperature is not None:
        module = ModuleParams(c_mps=float(speed_of_sound_mps(args.temperature)))
    config = FitConfig(module=module, detection=not args.no_detection_model)
    sd = args.odometry_sd
    if sd is not None and not (math.isfinite(sd) and sd >= 0.0):
        print(f"sonarloc fit: --odometry-sd must be a non-negative number, got {sd}",
              file=sys.stderr)
        return 2
    segmenter = None
    if args.max_travel is not None:
        try:
            segmenter = SegmenterConfig(max_travel_m=args.max_travel)
        except ValueError as exc:     # (the config's own check of the value)
            print(f"sonarloc fit: --max-travel: {exc}", file=sys.stderr)
            return 2
    scan = read_scan_csv(args.scan)
    report = fit_scan(scan, config, segmenter, odometry_sd_deg_per_m=sd)
    landmarks = [lm for lm in report.landmarks if lm.ok or not args.only_ok]
    if args.json:
        st = report.stats
        sys.stdout.write(json.dumps(
            {"landmarks": [landmark_to_json(lm) for lm in landmarks],
             "readings": {"total": st.readings, "echoes": st.echoes, "no_echo": st.no_echo,
                          "bad": st.bad, "spikes": st.spikes, "segments": st.segments}},
            allow_nan=False) + "\n")
        return 0
    print(f"{len(landmarks)} landmark(s) from {report.stats.readings} readings "
          f"({report.stats.echoes} echoes, {report.stats.spikes} spike echoes dropped)")
    print(f"{'kind':5} {'range_m':>8} {'bearing':>8} {'kappa_us':>8} {'sd_deg':>7} {'n':>4} "
          f"{'tier':6} status")
    for lm in landmarks:
        sd = lm.extra.get("bearing_sd_deg", float("nan"))
        sd_f = float(sd) if isinstance(sd, (int, float)) else float("nan")
        print(f"{lm.kind:5} {lm.range_m:8.4f} {math.degrees(lm.bearing_rad):8.2f} "
              f"{lm.kappa_us:8.3f} {sd_f:7.2f} {lm.n_readings:4d} {lm.tier:6} {lm.status.value}"
              + (f" ({lm.reason})" if lm.reason else ""))
    return 0

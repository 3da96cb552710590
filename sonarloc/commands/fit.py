"""Landmarks from TOF readings: `sonarloc fit SCAN.csv [--json | --jsonl]`.

Reads a scan CSV (one row per ping with the transducer pose; FORMATS.md section 1),
segments it into one U-shaped TOF curve per landmark pass, fits each with Kuc's
forward model (range, bearing, reflecting strength kappa) and prints the landmarks
(FORMATS.md section 2 with --json, a line each with --jsonl; a table otherwise). The
file is read and fitted a block of lines at a time (--block-rows) and the landmarks are
written as they come: memory is bounded by a block, whatever the file's size.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from sonarloc.errors import LogFormatError
from sonarloc.fit.landmarks import OnlineFitter
from sonarloc.fit.lsq import FitConfig
from sonarloc.fit.result import Landmark
from sonarloc.fit.segment import SegmenterConfig, SegmenterStats
from sonarloc.io.scancsv import BLOCK_ROWS, ScanReadings, TimeoutWatch, iter_scan_csv
from sonarloc.physics.sound import check_air_speed_of_sound, speed_of_sound_mps
from sonarloc.physics.tof import ModuleParams


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scan", metavar="SCAN.csv", help="scan CSV (FORMATS.md section 1)")
    form = parser.add_mutually_exclusive_group()
    form.add_argument("--json", action="store_true",
                      help="print one JSON object {\"landmarks\": [...]} (FORMATS.md section 2)")
    form.add_argument("--jsonl", action="store_true",
                      help="print one line per landmark as it is fitted (the objects of "
                           "--json's list), then a line {\"readings\": {...}}")
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
    parser.add_argument("--max-tof", type=float, metavar="US", default=None,
                        help="a TOF at or above this is no echo (a module that reports "
                             "its timeout as a reading, e.g. 62000); counted as `timeouts`")
    parser.add_argument("--block-rows", type=int, metavar="N", default=BLOCK_ROWS,
                        help="lines of the CSV read and fitted at a time: memory is bounded "
                             f"by a block whatever the file's size (default {BLOCK_ROWS})")


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
    # Bad values name the option, and the shell reports them like any bad input
    # ("sonarloc fit: error: ...", exit 2).
    module = ModuleParams()
    try:
        if args.speed_of_sound is not None:
            module = ModuleParams(c_mps=check_air_speed_of_sound(args.speed_of_sound,
                                                                 "the speed of sound"))
        elif args.temperature is not None:
            module = ModuleParams(c_mps=float(speed_of_sound_mps(args.temperature)))
    except ValueError as exc:     # (the module's own check of the speed of sound)
        option = "--speed-of-sound" if args.speed_of_sound is not None else "--temperature"
        raise ValueError(f"{option}: {exc}") from None
    config = FitConfig(module=module, detection=not args.no_detection_model)
    sd = args.odometry_sd
    if sd is not None and not (math.isfinite(sd) and sd >= 0.0):
        raise ValueError(f"--odometry-sd must be a non-negative number, got {sd}")
    segmenter = None
    if args.max_travel is not None:
        try:
            segmenter = SegmenterConfig(max_travel_m=args.max_travel)
        except ValueError as exc:     # (the config's own check of the value)
            raise ValueError(f"--max-travel: {exc}") from None
    if args.block_rows < 1:
        raise ValueError(f"--block-rows must be a positive integer, got {args.block_rows}")
    max_tof = args.max_tof
    if max_tof is not None and not (math.isfinite(max_tof) and max_tof > 0.0):
        raise ValueError(f"--max-tof must be a positive number of microseconds, got {max_tof}")
    fitter = OnlineFitter(config, segmenter, odometry_sd_deg_per_m=sd)
    watch, timeouts = TimeoutWatch(), 0
    out = _JsonOut() if args.json else _JsonLinesOut() if args.jsonl else _TableOut()
    keep = (lambda lm: lm.ok) if args.only_ok else (lambda lm: True)
    # one block behind the reader (memory bounded by two blocks), so the last one is
    # fitted with the segments the end of the file closes, in one batch: a file of one
    # block is fitted as fit_scan fits it
    pending: ScanReadings | None = None
    error: LogFormatError | None = None
    try:
        for block in iter_scan_csv(args.scan, args.block_rows):
            if max_tof is not None:
                block, n = block.timeouts_as_no_echo(max_tof)
                timeouts += n
            watch.push(block.tof_us)
            if pending is not None:
                out.write([lm for lm in fitter.push_block(pending) if keep(lm)])
            pending = block
    except LogFormatError as err:
        if pending is None:   # in the first block: the command's usual one-line error
            raise
        error = err           # later: what was read before its block, then the error
    assert pending is not None   # (iter_scan_csv yields at least one block)
    out.write([lm for lm in fitter.push_block(pending, flush=True) if keep(lm)])
    out.close(fitter.stats, error=None if error is None else str(error),
              extra={} if max_tof is None else {"timeouts": timeouts})
    advice = watch.advice(fitter.stats.echoes)
    if advice is not None:
        print(f"sonarloc fit: note: {advice}", file=sys.stderr)
    if error is not None:
        print(f"sonarloc fit: error: {error}", file=sys.stderr)
        return 2
    return 0


class _JsonOut:
    """FORMATS.md section 2 written as landmarks come: byte for byte the one JSON object
    of ``json.dumps({"landmarks": [...], "readings": {...}})``."""

    def __init__(self) -> None:
        self.started = False

    def write(self, landmarks: list[Landmark]) -> None:
        for lm in landmarks:
            sys.stdout.write((", " if self.started else '{"landmarks": [')
                             + json.dumps(landmark_to_json(lm), allow_nan=False))
            self.started = True

    def close(self, st: SegmenterStats, error: str | None = None,
              extra: dict[str, int] | None = None) -> None:
        if not self.started:
            sys.stdout.write('{"landmarks": [')
        sys.stdout.write("], " + json.dumps(self._tail(st, error, extra),
                                            allow_nan=False)[1:] + "\n")

    @staticmethod
    def _tail(st: SegmenterStats, error: str | None, extra: dict[str, int] | None
              ) -> dict[str, Any]:
        """What follows the landmarks: the readings' counts (and ``extra`` ones: the
        ``timeouts`` of --max-tof), and the error if any."""
        tail: dict[str, Any] = {"readings": {
            "total": st.readings, "echoes": st.echoes, "no_echo": st.no_echo, "bad": st.bad,
            "spikes": st.spikes, "segments": st.segments, **(extra or {})}}
        if error is not None:
            tail["error"] = error
        return tail


class _JsonLinesOut(_JsonOut):
    """JSON Lines: a landmark's object per line as it comes, the counts (and an error)
    on the last line (for a consumer that reads a big file's landmarks as a stream)."""

    def write(self, landmarks: list[Landmark]) -> None:
        for lm in landmarks:
            sys.stdout.write(json.dumps(landmark_to_json(lm), allow_nan=False) + "\n")

    def close(self, st: SegmenterStats, error: str | None = None,
              extra: dict[str, int] | None = None) -> None:
        sys.stdout.write(json.dumps(self._tail(st, error, extra), allow_nan=False) + "\n")


class _TableOut:
    """A table, a row per landmark as they come, the counts last."""

    def __init__(self) -> None:
        self.started = False
        self.n = 0

    def write(self, landmarks: list[Landmark]) -> None:
        if landmarks and not self.started:
            print(f"{'kind':5} {'range_m':>8} {'bearing':>8} {'kappa_us':>8} {'sd_deg':>7} "
                  f"{'n':>4} {'tier':6} status")
            self.started = True
        for lm in landmarks:
            sd = lm.extra.get("bearing_sd_deg", float("nan"))
            sd_f = float(sd) if isinstance(sd, (int, float)) else float("nan")
            print(f"{lm.kind:5} {lm.range_m:8.4f} {math.degrees(lm.bearing_rad):8.2f} "
                  f"{lm.kappa_us:8.3f} {sd_f:7.2f} {lm.n_readings:4d} {lm.tier:6} "
                  f"{lm.status.value}" + (f" ({lm.reason})" if lm.reason else ""))
        self.n += len(landmarks)

    def close(self, st: SegmenterStats, error: str | None = None,
              extra: dict[str, int] | None = None) -> None:
        print(f"{self.n} landmark(s) from {st.readings} readings ({st.echoes} echoes, "
              f"{st.spikes} spike echoes dropped"
              + "".join(f", {v} {k}" for k, v in (extra or {}).items()) + ")"
              + (f"; stopped at a bad line: {error}" if error else ""))

"""Simulate a robot with a sonar rig in a map and write the log (FORMATS.md section 4).

The robot drives the map's default route (a LineString with kind "route") for
--duration seconds, or stands still at --at X,Y,YAW_DEG. Default duration: one lap
of the route when driving, one pan sweep for a still pan rig, 10 s for a still ring.
With --scan-csv the readings are also written as a scan CSV (FORMATS.md section 1)
with the transducer poses in the map frame.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections import Counter

from sonarloc.commands._args import accept_negative_values, parse_pose, refuse_overwrite
from sonarloc.io.logfile import LogWriter
from sonarloc.io.scancsv import write_scan_csv
from sonarloc.maps.geojson import load_map
from sonarloc.physics.tiers import Tier
from sonarloc.world.rig import parse_pan_schedule, rig_by_name
from sonarloc.world.simulate import PingTruth, scan_from_pings, simulate_records


def add_arguments(parser: argparse.ArgumentParser) -> None:
    accept_negative_values(parser)
    parser.add_argument("--map", required=True, metavar="MAP", help="map GeoJSON")
    parser.add_argument("--out", required=True, metavar="LOG", help="log JSONL to write")
    parser.add_argument("--rig", default="ring16", metavar="ring16|pan|RIG.json",
                        help="sonar rig (default ring16)")
    parser.add_argument("--at", metavar="X,Y,YAW_DEG",
                        help="keep the robot still at this pose in the map frame")
    parser.add_argument("--duration", metavar="S", help="simulated seconds")
    parser.add_argument("--pan", metavar="START:STOP:STEP",
                        help="pan angles in degrees (pan rig; default -40:40:0.3)")
    parser.add_argument("--repeat", metavar="N", help="pings per pan angle (default 1)")
    parser.add_argument("--tier", default="auto", metavar="gauss|piston|waveform|auto",
                        help="sonar model tier (default auto)")
    parser.add_argument("--seed", default="0", metavar="N", help="random seed (default 0)")
    parser.add_argument("--scan-csv", metavar="FILE",
                        help="also write the readings as a scan CSV (poses in the map frame)")


def _duration(text: str | None) -> float | None:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--duration must be a number of seconds, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise ValueError(f"--duration must be a non-negative number of seconds, got {text!r}")
    return value


def _int(name: str, text: str | None, minimum: int) -> int | None:
    if text is None:
        return None
    try:
        value = int(text)
    except ValueError:
        raise ValueError(f"{name} must be an integer, got {text!r}") from None
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {text!r}")
    return value


def run(args: argparse.Namespace) -> int:
    refuse_overwrite({"--out": args.out, "--scan-csv": args.scan_csv},
                     {"--map": args.map, "--rig": args.rig})
    at = parse_pose(args.at) if args.at is not None else None
    duration = _duration(args.duration)
    pan = parse_pan_schedule(args.pan) if args.pan is not None else None
    repeat = _int("--repeat", args.repeat, 1)
    seed = _int("--seed", args.seed, 0)
    try:
        tier = Tier.parse(args.tier)
    except ValueError:
        raise ValueError(f"--tier must be gauss, piston, waveform or auto, got {args.tier!r}") \
            from None
    rig = rig_by_name(args.rig, pan, repeat)
    world_map = load_map(args.map)

    pings: list[PingTruth] = []
    keep = pings.append if args.scan_csv else None
    tiers: Counter[int] = Counter()
    n_ping = n_echo = n_rec = 0

    def count(p: PingTruth) -> None:
        nonlocal n_ping, n_echo
        n_ping += 1
        n_echo += not math.isnan(p.tof_us)
        tiers[p.tier] += 1
        if keep is not None:
            keep(p)

    records = simulate_records(world_map, rig, duration_s=duration, at=at, tier=tier,
                               seed=seed or 0, on_ping=count)
    try:
        with LogWriter(args.out) as writer:
            for rec in records:
                writer.write(rec)
                n_rec += 1
    except NotImplementedError as err:
        raise ValueError(f"--tier {args.tier}: {err}") from None
    if args.scan_csv:
        write_scan_csv(args.scan_csv, scan_from_pings(pings, "map").readings)
    used = ", ".join(f"{Tier(t).label} {n}" for t, n in sorted(tiers.items()) if t >= 0)
    print(f"wrote {n_rec} records to {args.out}: {n_ping} pings, {n_echo} echoes"
          + (f" (tiers: {used})" if used else ""), file=sys.stderr)
    if n_ping and not n_echo:
        print(f"warning: no ping had an echo: nothing of the map was in range"
              f"{_outside(at, world_map.bounds)}", file=sys.stderr)
    return 0


def _outside(at: tuple[float, float, float] | None,
             bounds: tuple[float, float, float, float]) -> str:
    """Why a still robot saw nothing, if its pose is off the map."""
    if at is None or (bounds[0] <= at[0] <= bounds[2] and bounds[1] <= at[1] <= bounds[3]):
        return ""
    return (f" (--at {at[0]:g},{at[1]:g} is outside the map, which spans x {bounds[0]:g}"
            f"..{bounds[2]:g} m, y {bounds[1]:g}..{bounds[3]:g} m)")

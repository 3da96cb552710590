"""Run a simulated sonar module that speaks the device protocol (docs/PROTOCOL.md).

Its readings come from the simulator (--map, with the options of `sonarloc simulate`)
or from a recorded log (--log), paced in real time (--rate for faster or slower).
Transports: --pty (default; prints the pseudo-terminal's path), --listen HOST:PORT
(TCP, speaks the serial protocol; port 0 picks a free one; one host at a time, as a
ser2net bridge: another is told "Port already in use" and closed), --can INTERFACE:CHANNEL
(python-can; the virtual interface only reaches buses of the same process), or
--candump FILE.log (writes a candump log as fast as it can). The first line on
stdout is the source to give `sonarloc record` or a driver. Unless --no-wait, the
module waits for the host's Start command (every sonarloc driver sends it).
--sent-log records exactly what was sent, in the log format.
"""

from __future__ import annotations

import argparse
import itertools
import math
import signal
import sys
from collections.abc import Iterator
from types import FrameType

from sonarloc.commands._args import refuse_overwrite
from sonarloc.io.drivers.sim import (
    CanBusTransport,
    CandumpTransport,
    PtyTransport,
    SimModule,
    TcpTransport,
    Transport,
)
from sonarloc.io.logfile import LogStats, Record, iter_log


def add_arguments(parser: argparse.ArgumentParser) -> None:
    src = parser.add_mutually_exclusive_group(required=True)
    src.add_argument("--map", metavar="MAP", help="simulate this map (GeoJSON)")
    src.add_argument("--log", metavar="LOG", help="replay this log (JSONL) instead")
    tr = parser.add_mutually_exclusive_group()
    tr.add_argument("--pty", action="store_true", help="serve on a pseudo-terminal (default)")
    tr.add_argument("--listen", metavar="HOST:PORT", help="serve on TCP (e.g. 127.0.0.1:0)")
    tr.add_argument("--can", metavar="INTERFACE:CHANNEL", help="serve on a python-can bus")
    tr.add_argument("--candump", metavar="FILE.log", help="write a candump log")
    parser.add_argument("--sent-log", metavar="LOG", help="write what was sent (log JSONL)")
    parser.add_argument("--duration", metavar="S", type=float,
                        help="seconds of stream (simulated) time")
    parser.add_argument("--rate", metavar="R", type=float,
                        help="pace R times real time (default 1; --candump: as fast as possible)")
    parser.add_argument("--no-wait", action="store_true",
                        help="stream at once instead of waiting for the host's Start")
    parser.add_argument("--link", metavar="PATH",
                        help="with --pty: also make PATH a symlink to the terminal")
    parser.add_argument("--linger", metavar="S", type=float, default=1.0,
                        help="keep the transport open S seconds after the stream ends "
                             "(default 1)")
    sim = parser.add_argument_group("simulator (with --map)")
    sim.add_argument("--rig", default="ring16", metavar="ring16|pan|RIG.json",
                     help="sonar rig (default ring16)")
    sim.add_argument("--at", metavar="X,Y,YAW_DEG", help="keep the robot still at this pose")
    sim.add_argument("--pan", metavar="START:STOP:STEP", help="pan angles (pan rig)")
    sim.add_argument("--repeat", type=int, metavar="N", help="pings per pan angle")
    sim.add_argument("--tier", default="auto", metavar="gauss|piston|waveform|auto",
                     help="sonar model tier (default auto)")
    sim.add_argument("--seed", type=int, default=0, metavar="N", help="random seed (default 0)")


def _host_port(text: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    try:
        number = int(port)
    except ValueError:
        number = -1
    if not sep or not host or not 0 <= number <= 65535:
        raise ValueError(f"--listen must be HOST:PORT, got {text!r}")
    return host, number


def _transport(args: argparse.Namespace) -> Transport:
    if args.listen:
        return TcpTransport(*_host_port(args.listen))
    if args.can:
        interface, sep, channel = args.can.partition(":")
        if not (interface and sep and channel):
            raise ValueError(f"--can must be INTERFACE:CHANNEL, got {args.can!r}")
        if interface == "virtual":  # a `sonarloc record` in another process hears nothing
            print(f"sonarloc serve-sim: note: python-can's virtual bus reaches only this "
                  f"process, where no host runs: nothing will read {args.can} (and no Start "
                  f"will come); for another process use a real or virtual kernel bus, e.g. "
                  f"--can socketcan:vcan0, or --pty / --listen", file=sys.stderr, flush=True)
        return CanBusTransport(interface, channel)
    if args.candump:
        return CandumpTransport(args.candump)
    return PtyTransport(args.link)


def _records(args: argparse.Namespace, log_stats: LogStats) -> Iterator[Record]:
    if args.log:  # opened now: a missing log fails before the module is announced
        log = iter_log(args.log, log_stats)
        first = next(log, None)
        return itertools.chain([first] if first is not None else [], log)
    from sonarloc.commands._args import parse_pose
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import parse_pan_schedule, rig_by_name
    from sonarloc.world.simulate import simulate_records

    pan = parse_pan_schedule(args.pan) if args.pan is not None else None
    rig = rig_by_name(args.rig, pan, args.repeat)
    at = parse_pose(args.at) if args.at is not None else None
    return simulate_records(load_map(args.map), rig, duration_s=args.duration, at=at,
                            tier=args.tier, seed=args.seed)


def run(args: argparse.Namespace) -> int:
    for name in ("duration", "linger"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and v >= 0):
            raise ValueError(f"--{name} must be a non-negative number of seconds, got {v!r}")
    if args.rate is not None and not (math.isfinite(args.rate) and args.rate > 0):
        raise ValueError(f"--rate must be a positive number, got {args.rate!r}")
    if args.link and (args.listen or args.can or args.candump):
        raise ValueError("--link goes with --pty only")
    refuse_overwrite({"--candump": args.candump, "--sent-log": args.sent_log},
                     {"--map": args.map, "--log": args.log, "--rig": args.rig})
    rate = args.rate if args.rate is not None else (None if args.candump else 1.0)
    log_stats = LogStats()
    records = _records(args, log_stats)
    transport = _transport(args)
    sim = SimModule(records, transport, rate=rate, duration_s=args.duration,
                    sent_log=args.sent_log, wait_for_start=False if args.no_wait else None)

    def stop(signum: int, frame: FrameType | None) -> None:
        sim.stop()

    old = signal.signal(signal.SIGTERM, stop)
    try:
        print(sim.url, flush=True)
        print(f"serving the sonar module on {sim.url}"
              + ("" if args.no_wait or not transport.accepts_commands
                 else " (waiting for a host's Start)"), file=sys.stderr, flush=True)
        try:
            sim.run()
            if args.linger:
                sim.sleep(args.linger)  # let the host read what is still in flight
        except KeyboardInterrupt:
            pass
        except NotImplementedError as err:  # e.g. a physics tier not built yet
            raise ValueError(f"--tier {args.tier}: {err}") from None
    finally:
        signal.signal(signal.SIGTERM, old)
        sim.close()
    s = sim.stats
    print(f"sent {s.records} records ({s.messages} messages, {s.lost} lost, "
          f"rig {s.rigs_sent} times, {s.commands} commands"
          + (f", {s.unsendable} unsendable (first: {s.first_unsendable})" if s.unsendable
             else "")
          + (f", {sim.pacer.jumps} time jumps not waited for" if sim.pacer.jumps
             and sim.rate is not None else "") + ")"
          + (f"; log: {log_stats.summary()}" if args.log else "")
          + (f"; refused {transport.refused} host{'s' * (transport.refused > 1)} while "
             f"another was connected" if isinstance(transport, TcpTransport)
             and transport.refused else ""), file=sys.stderr)
    return 0

"""Record readings from a sonar device, bus or file into a log (FORMATS.md section 4).

SOURCE is a serial device or pyserial URL (/dev/ttyUSB0, socket://127.0.0.1:PORT,
loop://), can:INTERFACE:CHANNEL, candump:FILE.log, sim:LOG.jsonl, or a real-device
driver (pioneer:/dev/ttyS0, maxbotix:/dev/ttyUSB0). The rig record is written first
(readings that arrive before it are held back). Recording stops after --duration
seconds, at the end of a file, on Ctrl-C, or after --timeout seconds of silence.
The decoder's counters (good frames, CRC failures, skipped bytes, sequence gaps,
...) are printed at the end.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from collections import Counter
from types import FrameType
from typing import Any

from sonarloc.commands._args import refuse_overwrite
from sonarloc.errors import DeviceTimeoutError, LogFormatError
from sonarloc.io.drivers import Driver, open_driver, parse_source
from sonarloc.io.logfile import LogWriter, Record, RigRecord

HOLD_MAX = 100_000  # readings held back while waiting for the rig
_DEVICE = {"serial": "the sonarloc module", "can": "the sonarloc module",
           "pioneer": "a Pioneer robot", "maxbotix": "a MaxBotix sensor"}
FLUSH_S = 0.5  # the log on disk lags the device by at most this (a robot's power may fail)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("source", metavar="SOURCE", help="device, URL, bus or file to read")
    parser.add_argument("--out", required=True, metavar="LOG", help="log JSONL to write")
    parser.add_argument("--duration", type=float, metavar="S",
                        help="stop after S seconds (wall clock)")
    parser.add_argument("--timeout", type=float, default=5.0, metavar="S",
                        help="stop after S seconds without data (default 5)")
    parser.add_argument("--baud", type=int, metavar="N", help="serial line speed")
    parser.add_argument("--no-start", action="store_true",
                        help="do not send Start/RequestRig to the module")
    parser.add_argument("--option", action="append", default=[], metavar="KEY=VALUE",
                        help="driver option, e.g. unit=cm or mount=0.1,0,90 (maxbotix: "
                             "X_M,Y_M,YAW_DEG in base_link), rig=RIG.json or range_conv=0.268 "
                             "(pioneer), rate=1 (candump), wake_s=none (no wake-up: serial, "
                             "can); none sets an option to None; repeatable")


def _value(text: str) -> Any:
    """An --option value: a bool, ``none`` (None: an option's "off", e.g. ``wake_s=none``
    for no wake-up), an int, a float, numbers separated by commas as a tuple
    (``mount=0.1,0,90``), else the text."""
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    if "," in text:
        try:
            return tuple(float(part) for part in text.split(","))
        except ValueError:
            pass
    return text


def driver_options(args: argparse.Namespace) -> dict[str, Any]:
    name, _ = parse_source(args.source)
    opts: dict[str, Any] = {}
    for item in args.option:
        key, sep, value = item.partition("=")
        if not sep or not key.isidentifier():
            raise ValueError(f"--option must be KEY=VALUE, got {item!r}")
        opts[key] = _value(value)
    if args.baud is not None:
        if name not in ("serial", "pioneer", "maxbotix"):
            raise ValueError(f"--baud applies to serial sources, not {name}")
        opts["baudrate"] = args.baud
    if args.no_start:
        if name not in ("serial", "can"):
            raise ValueError(f"--no-start applies to the module protocol, not {name}")
        opts["start"] = False
    return opts


def _silence(driver: Driver, timeout: float) -> str:
    """The error of a source that gave no reading: bytes that never formed a frame
    are another trouble than no bytes at all."""
    s = driver.decoder_stats
    what = _DEVICE.get(driver.scheme, "the device")
    if s.bytes_in and not s.frames:
        return (f"{driver.source}: no readings within {timeout:g} s: {s.bytes_in} bytes came "
                f"but no packet of {what} in them (wrong --baud?) ({driver.summary()})")
    foreign = s.unknown + s.bad_length + s.error_frames
    if foreign and not s.frames:
        return (f"{driver.source}: no readings within {timeout:g} s: {foreign} frames came "
                f"but none of {what} ({driver.summary()})")
    return f"{driver.source}: no data within {timeout:g} s ({driver.summary()})"


def run(args: argparse.Namespace) -> int:
    refuse_overwrite({"--out": args.out}, {"SOURCE": args.source})
    for name in ("duration", "timeout"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"--{name} must be a positive number of seconds, got {v!r}")
    opts = driver_options(args)
    try:
        driver = open_driver(args.source, **opts)
    except TypeError as err:  # an option the driver does not take
        raise ValueError(f"bad --option for {args.source}: {err}") from None
    stop = False

    def on_term(signum: int, frame: FrameType | None) -> None:
        nonlocal stop
        stop = True

    old = signal.signal(signal.SIGTERM, on_term)
    counts: Counter[str] = Counter()
    held: list[Record] = []
    hold = True  # readings are held back until the rig comes (at most HOLD_MAX)
    have_rig = False
    rig_changes: list[float] = []  # times of rigs other than the first
    note = ""
    # --out is opened at the first reading or odometry, not before: a device that sends
    # nothing (wrong port, wrong baud, refused) leaves an earlier file of that name as it
    # was, where it was emptied (or left holding a rig line) and the recording lost
    writer: LogWriter | None = None
    head: list[Record] = []  # the rig, if it came before any reading

    def opened() -> LogWriter:
        """--out, opened (with the records waiting for it) if it was not yet."""
        nonlocal writer
        if writer is None:
            writer = LogWriter(args.out)
            for r in head:
                writer.write(r)
        return writer

    def write(rec: Record) -> None:
        counts[rec.type] += 1
        if writer is None and isinstance(rec, RigRecord):
            head.append(rec)
        else:
            opened().write(rec)

    def release() -> None:
        """Write the readings held back, in the order they came."""
        nonlocal held
        for r in held:
            write(r)
        held = []

    def take(rec: Record) -> None:
        nonlocal have_rig, hold
        if isinstance(rec, RigRecord):
            if have_rig:  # a changed rig mid-log is not representable; keep the first
                rig_changes.append(rec.t_s)  # (the driver drops unchanged repeats)
                return
            have_rig = True
            write(rec)
            release()
            return
        if not have_rig and hold:
            if len(held) < HOLD_MAX:
                held.append(rec)
                return
            hold = False  # no rig after so many: write them, in the order of time
            release()
        write(rec)

    t_end = None if args.duration is None else time.monotonic() + args.duration
    try:
        with driver:
            last_data = flushed = time.monotonic()
            try:
                while not stop:
                    now = time.monotonic()
                    if t_end is not None and now >= t_end:
                        break
                    if now - flushed >= FLUSH_S:
                        if writer is not None:
                            writer.flush()
                        flushed = now
                    try:  # short reads, so SIGTERM and --duration are noticed quickly
                        rec = driver.read(timeout=0.2)
                    except DeviceTimeoutError:
                        if time.monotonic() - last_data < args.timeout:
                            continue
                        if counts["odom"] + counts["tof"] + len(held) == 0:  # a rig at most
                            raise DeviceTimeoutError(_silence(driver, args.timeout)) from None
                        note = f"; stopped after {args.timeout:g} s without data"
                        break
                    last_data = time.monotonic()
                    if rec is None:
                        if driver.end_reason:  # a live source that ended by itself: why
                            note = f"; {driver.end_reason}"
                        break
                    take(rec)
            except KeyboardInterrupt:
                pass
            # what the device delivered is kept: the records still queued, and those the
            # decoder recovers when the driver closes (good packets behind a false header)
            driver.close()
            while (rec := driver.read(timeout=0)) is not None:
                take(rec)
            release()  # no rig ever came
            opened()  # (the source ended without a reading: a log of what came)
    finally:
        signal.signal(signal.SIGTERM, old)
        if writer is not None:
            writer.close()
    if counts["odom"] + counts["tof"] == 0 and driver.stats.malformed_lines:
        hint = " (candump logs are written by `candump -L`)" if driver.scheme == "candump" else ""
        raise LogFormatError(f"{driver.source}: no readings in it{hint}: {driver.summary()}")
    n = sum(counts.values())
    kinds = ", ".join(f"{k} {v}" for k, v in sorted(counts.items()))
    print(f"recorded {n} records ({kinds or 'none'}) to {args.out}{note}", file=sys.stderr)
    if not have_rig:
        print("warning: the source sent no rig description", file=sys.stderr)
    if rig_changes:
        k = len(rig_changes)
        print(f"warning: the rig changed at t_s {rig_changes[0]:g} ({k} time{'s' * (k > 1)}); "
              f"the log keeps the first rig, which may not fit the readings after that",
              file=sys.stderr)
    print(f"{driver.source}: {driver.summary()}", file=sys.stderr)
    return 0

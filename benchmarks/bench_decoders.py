"""Decoder throughput (frames/s) against the rate a 16-transducer ring produces.

The stream is a simulated drive (room map, ring16 rig: 4 firing groups in 30 ms
slots, odometry at 20 Hz), encoded once as serial packets and once as CAN frames.
Each decoder is timed on the whole stream, median of repeated runs; the baseline is
the frame rate the ring itself puts on the wire (measured from the same stream), so
the ratio says how many such rings one core could decode. Rows: the serial decoder
on clean bytes in 64-byte reads (what a serial port delivers) and on a damaged
stream (1 % of packets with a flipped bit, garbage before 10 %), the CAN decoder
(cantools, DBC), each with and without the conversion to log records, and the
Pioneer SIP decoder for comparison.

Run: ``python benchmarks/bench_decoders.py [--quick]``; writes benchmarks/results/decoders.md.
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import can  # noqa: E402

from benchmarks._machine import SHARED, load_average, machine_line  # noqa: E402
from sonarloc.io.logfile import Record  # noqa: E402
from sonarloc.io.protocol.canbus import CanDecoder, CanEncoder  # noqa: E402
from sonarloc.io.protocol.framing import SerialDecoder, SerialEncoder  # noqa: E402
from sonarloc.io.protocol.messages import Message  # noqa: E402
from sonarloc.io.protocol.records import RecordAssembler, messages_from_record  # noqa: E402
from sonarloc.io.protocol.sip import ArcosDecoder, StandardSip  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "decoders.md"
CHUNK = 64


def drive_records(duration_s: float) -> tuple[list[Record], str]:
    """A simulated ring16 drive in the room map (or a synthetic ring if the world is absent)."""
    try:
        from sonarloc.maps import load_map
        from sonarloc.world.rig import ring16
        from sonarloc.world.simulate import simulate_records

        recs = list(simulate_records(load_map(ROOT / "maps" / "room.geojson"), ring16(),
                                     duration_s=duration_s, seed=1))
        return recs, "simulate_records (room map, ring16, odometry 20 Hz)"
    except ImportError:  # pragma: no cover - the world stage missing
        from sonarloc.io.logfile import OdomRecord, RigRecord, SensorMount, TofRecord

        out: list[Record] = [RigRecord(tuple(SensorMount(i, 0.2, 0.0, 22.5 * i)
                                             for i in range(16)))]
        for k in range(int(duration_s / 0.03)):
            t = 0.03 * k
            out += [TofRecord(t, 4 * (k % 4) + j, 5000.0 + k % 97) for j in range(4)]
            if k % 2 == 0:
                out.append(OdomRecord(t, 0.1 * t, 0.0, t))
        return out, "synthetic ring16 (4 groups of 4 every 30 ms, odometry 17 Hz)"


def median_time(fn: Callable[[], object], repeats: int) -> float:
    """Median CPU time of this process per call (other load on a shared machine does not
    count; the decoders are single-threaded and do no I/O)."""
    times = []
    for _ in range(repeats):
        t = time.process_time()
        fn()
        times.append(time.process_time() - t)
    return statistics.median(times)


def damaged(packets: list[bytes], rng: random.Random) -> bytes:
    out = bytearray()
    for p in packets:
        if rng.random() < 0.10:
            out += bytes(rng.randrange(256) for _ in range(rng.randrange(1, 20)))
        if rng.random() < 0.01:
            b = bytearray(p)
            b[rng.randrange(2, len(b))] ^= 1 << rng.randrange(8)
            p = bytes(b)
        out += p
    return bytes(out)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="shorter stream, fewer repeats")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args(argv)
    duration = 20.0 if args.quick else 120.0
    repeats = 3 if args.quick else 15

    load = load_average()
    recs, what = drive_records(duration)
    span = max(r.t_s for r in recs) - min(r.t_s for r in recs)
    msgs: list[Message] = [m for r in recs for m in messages_from_record(r)]
    enc = SerialEncoder()
    packets = [enc.encode(m) for m in msgs]
    wire = b"".join(packets)
    chunks = [wire[i:i + CHUNK] for i in range(0, len(wire), CHUNK)]
    bad = damaged(packets, random.Random(1))
    bad_chunks = [bad[i:i + CHUNK] for i in range(0, len(bad), CHUNK)]
    cenc = CanEncoder()
    frames: list[can.Message] = [f for m in msgs for f in cenc.encode(m)]
    n_tof = sum(r.type == "tof" for r in recs)
    sips = [StandardSip(True, k & 0x7FFF, 0, 0, 0, 0, 120, 0, 0, 1, 0,
                        tuple((j, 500 + j) for j in range(8))).encode()
            for k in range(len(packets) // 9)]
    sip_wire = b"".join(sips)
    sip_chunks = [sip_wire[i:i + CHUNK] for i in range(0, len(sip_wire), CHUNK)]

    def serial(ch: list[bytes], assemble: bool) -> Callable[[], object]:
        def run() -> object:
            dec, asm = SerialDecoder(), RecordAssembler()
            n = 0
            for c in ch:
                for m in dec.feed(c):
                    n += len(asm.push(m)) if assemble else 1
            return n
        return run

    def canbus(assemble: bool) -> Callable[[], object]:
        def run() -> object:
            dec, asm = CanDecoder(), RecordAssembler()
            n = 0
            for f in frames:
                for m in dec.feed(f):
                    n += len(asm.push(m)) if assemble else 1
            return n
        return run

    def sip() -> object:
        dec = ArcosDecoder()
        return sum(len(dec.feed(c)) for c in sip_chunks)

    # what the ring puts on the wire, per second of stream time
    serial_rate = len(packets) / span
    can_rate = len(frames) / span
    rows = [
        ("serial, clean, 64-byte reads", len(packets), serial(chunks, False), serial_rate),
        ("serial + records", len(packets), serial(chunks, True), serial_rate),
        ("serial, damaged (1 % flips, 10 % garbage)", len(packets), serial(bad_chunks, False),
         serial_rate),
        ("CAN (cantools, DBC)", len(frames), canbus(False), can_rate),
        ("CAN + records", len(frames), canbus(True), can_rate),
        ("Pioneer SIP (8 sonar per packet)", len(sips), sip, 10.0),  # one SIP per 100 ms
    ]
    lines = [
        "# Decoder throughput against a 16-transducer ring",
        "",
        f"Stream: {what}, {span:.0f} s simulated: {n_tof} pings ({n_tof / span:.0f}/s), "
        f"{len(packets)} serial packets ({serial_rate:.0f}/s, {len(wire) / span / 1000:.1f} kB/s"
        f" = {len(wire) * 10 / span / 115200:.0%} of a 115200-baud line), {len(frames)} CAN "
        f"frames ({can_rate:.0f}/s). Each decoder decodes the whole stream; median of "
        f"{repeats} runs of process CPU time. *ring ratio* = decoded frames/s over the "
        "frames/s the ring produces "
        "on that wire (how many such rings one core keeps up with); for the Pioneer row, the "
        "robot's 10 SIPs/s.",
        "",
        "| decoder | frames | median CPU time (s) | frames per CPU second "
        "| ring rate (frames/s) | ring ratio |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for name, n, fn, base in rows:
        t = median_time(fn, repeats)
        rate = n / t
        lines.append(f"| {name} | {n} | {t:.3f} | {rate:,.0f} | {base:.0f} | {rate / base:,.0f}x |")
        print(lines[-1], flush=True)
    lines += ["", machine_line(f"python-can {can.__version__}", f"{repeats} repeats",
                               SHARED, quick=args.quick,
                               load=load)]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    print(f"wrote {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

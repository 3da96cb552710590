"""Read a sonar module over a serial line: readings, odometry and the link's health.

With a DEVICE (``/dev/ttyUSB0``, ``socket://HOST:PORT``, ``can:socketcan:can0``,
``pioneer:/dev/ttyS0``, ``maxbotix:/dev/ttyUSB1``, ...) it reads that device with the
driver registered for it. Without one, it starts a simulated module on a
pseudo-terminal (the room, a ring of 16 transducers, streaming in real time) and reads
it exactly as it would read the hardware: the serial driver opens the pty's path.

    python examples/read_serial_sonar.py [DEVICE] [--duration 3] [--out LOG.jsonl]
"""

from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path

from sonarloc.io.drivers import open_driver
from sonarloc.io.logfile import LogWriter, OdomRecord, RigRecord, TofRecord

ROOM = Path(__file__).resolve().parents[1] / "maps" / "room.geojson"


def _simulated_module(stack: contextlib.ExitStack) -> str:
    """A simulated module on a pseudo-terminal; returns the path a host opens."""
    from sonarloc.io.drivers.sim import SimModule
    from sonarloc.maps.geojson import load_map
    from sonarloc.world.rig import ring16
    from sonarloc.world.simulate import simulate_records

    records = simulate_records(load_map(ROOM), ring16(), duration_s=600.0, seed=0)
    module = stack.enter_context(SimModule.on_pty(records, rate=1.0))
    print(f"simulated module on {module.url} (no DEVICE given)")
    return module.url


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("device", nargs="?", help="device path or source (default: a "
                                                  "simulated module on a pty)")
    parser.add_argument("--duration", type=float, default=3.0,
                        help="seconds to read (default %(default)s)")
    parser.add_argument("--out", help="also record everything into a log JSONL")
    parser.add_argument("--quiet", action="store_true", help="only the summary")
    args = parser.parse_args(argv)

    with contextlib.ExitStack() as stack:
        source = args.device or _simulated_module(stack)
        writer = stack.enter_context(LogWriter(args.out)) if args.out else None
        drv = stack.enter_context(open_driver(source))
        c_mps = 343.0
        n_tof = n_echo = 0
        t0 = time.monotonic()
        for rec in drv.records(timeout=2.0, duration_s=args.duration):
            if writer is not None:
                writer.write(rec)
            if isinstance(rec, RigRecord):
                c_mps = rec.speed_of_sound_mps
                print(f"rig: {len(rec.sensors)} transducers, c = {c_mps:.2f} m/s")
            elif isinstance(rec, TofRecord):
                n_tof += 1
                n_echo += rec.tof_us is not None
                if not args.quiet and n_tof <= 40:
                    what = ("no echo" if rec.tof_us is None else
                            f"{rec.tof_us:8.0f} us = {rec.tof_us * 0.5e-6 * c_mps:6.3f} m")
                    print(f"t={rec.t_s:8.3f} s  sensor {rec.sensor:2d}  {what}")
            elif isinstance(rec, OdomRecord) and not args.quiet and n_tof <= 40:
                print(f"t={rec.t_s:8.3f} s  odom ({rec.x_m:.3f}, {rec.y_m:.3f}, "
                      f"{rec.yaw_deg:.1f} deg)")
        elapsed = time.monotonic() - t0
        print(f"{n_tof} readings ({n_echo} echoes) in {elapsed:.1f} s from {drv.source}")
        print(f"link: {drv.summary()}")
    return 0 if n_tof else 1


if __name__ == "__main__":
    raise SystemExit(main())

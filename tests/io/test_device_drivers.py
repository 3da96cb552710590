"""Real-device drivers against simulated devices on real pseudo-terminals, and a CAN bus
carrying junk next to the module's frames."""

from __future__ import annotations

import dataclasses
import io
import math
import os
import random
import select
import threading
import time
import tty

import can
import pytest
from io_streams import drain, ring_stream

from sonarloc.errors import DeviceError, DeviceTimeoutError
from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.sim import SimModule
from sonarloc.io.logfile import LogWriter, OdomRecord, RigRecord, TofRecord, iter_log
from sonarloc.io.protocol.maxbotix import encode_range
from sonarloc.io.protocol.sip import (
    CLOSE,
    OPEN,
    PULSE,
    SONAR,
    SYNC0,
    SYNC1,
    SYNC2,
    ArcosDecoder,
    SipConverter,
    StandardSip,
    frame,
)


class Pty:
    """A pseudo-terminal pair; the test plays the device on the master side."""

    def __init__(self) -> None:
        self.master, slave = os.openpty()
        tty.setraw(slave)
        self.path = os.ttyname(slave)
        os.close(slave)

    def close(self) -> None:
        os.close(self.master)


class FakePioneer(threading.Thread):
    """A Pioneer on a pty: answers the SYNC handshake, then sends a SIP every 10 ms
    while driving in a circle (crossing the 15-bit XPOS wrap), with sonar readings."""

    def __init__(self, pty: Pty, n_sips: int = 60):
        super().__init__(daemon=True)
        self.pty, self.n_sips = pty, n_sips
        self.commands: list[int] = []
        self.stop = threading.Event()
        self.sent: list[StandardSip] = []

    def sip(self, k: int) -> StandardSip:
        x = 32700 + 20 * k  # mm; wraps past 32767 in the low 15 bits
        sonars = ((k % 16, 400 + 10 * k), ((k + 8) % 16, 5000))  # second one: no echo
        return StandardSip(True, x & 0x7FFF, 100 + k, (k * 37) % 4096 - 2048, 200, 210, 120,
                           0, 0, 1, 0, sonars, b"\x00" * 8)

    def run(self) -> None:
        dec = ArcosDecoder(parse_sip=False)
        opened, k = False, 0
        while not self.stop.is_set():
            ready, _, _ = select.select([self.pty.master], [], [], 0.01)
            if ready:
                try:
                    data = os.read(self.pty.master, 256)
                except OSError:
                    data = b""
                for p in dec.feed(data):
                    self.commands.append(p.type)
                    if p.type in (SYNC0, SYNC1) and not opened and p.data == b"":
                        if p.type == SYNC1 and SYNC2 in self.commands:
                            opened = True  # after SYNC2, command 1 is OPEN
                        else:
                            os.write(self.pty.master, frame(bytes([p.type])))
                    elif p.type == SYNC2:
                        os.write(self.pty.master, frame(b"\x02Pioneer\0P3DX\0sonarloc\0"))
                    elif p.type == CLOSE:
                        opened = False
            if opened and k < self.n_sips:
                s = self.sip(k)
                os.write(self.pty.master, s.encode())
                self.sent.append(s)
                k += 1
                time.sleep(0.005)


def test_pioneer_handshake_sips_and_watchdog() -> None:
    pty = Pty()
    robot = FakePioneer(pty)
    robot.start()
    try:
        with open_driver(f"pioneer:{pty.path}", pulse_s=0.05, backoff_s=(0.02, 0.1)) as drv:
            got = []
            while len(got) < 1 + 3 * robot.n_sips:
                got.append(drv.read(3.0))
            info = drv.robot_info
            time.sleep(0.15)
        time.sleep(0.2)
    finally:
        robot.stop.set()
        robot.join()
        pty.close()
    assert info == ("Pioneer", "P3DX", "sonarloc")
    assert robot.commands[:4] == [SYNC0, SYNC1, SYNC2, OPEN]
    assert SONAR in robot.commands and PULSE in robot.commands and robot.commands[-1] == CLOSE
    assert isinstance(got[0], RigRecord) and len(got[0].sensors) == 16
    odom = [r for r in got if isinstance(r, OdomRecord)]
    tof = [r for r in got if isinstance(r, TofRecord)]
    assert len(odom) == robot.n_sips and len(tof) == 2 * robot.n_sips
    # x keeps growing by 20 mm per SIP across the 15-bit wrap (32767 -> 0)
    xs = [r.x_m for r in odom]
    assert xs[0] == pytest.approx(-0.068) and all(
        b - a == pytest.approx(0.020) for a, b in zip(xs, xs[1:], strict=False))
    assert odom[1].yaw_deg == pytest.approx(((37 - 2048) * 360 / 4096 + 180) % 360 - 180)
    assert tof[0].tof_us == pytest.approx(2 * 0.400 / 343.0 * 1e6) and tof[1].tof_us is None
    assert drv.decoder.stats.crc_errors == 0


def test_pioneer_without_robot_times_out_in_handshake() -> None:
    pty = Pty()
    try:
        with pytest.raises(DeviceError, match="no answer to SYNC0"):
            open_driver(f"pioneer:{pty.path}", handshake_timeout_s=0.1)
    finally:
        pty.close()


def test_sip_converter_units() -> None:
    conv = SipConverter(range_conv=0.268, max_range_mm=3000, speed_of_sound_mps=340.0)
    s = StandardSip(False, 0x7FF0, 5, 1024, 0, 0, 0, 0, 0, 0, 0, ((3, 1000), (4, 20000)))
    odom, t1, t2 = conv.records(s, 1.5)
    assert odom == OdomRecord(1.5, -0.016, 0.005, 90.0)
    assert t1 == TofRecord(1.5, 3, pytest.approx(2 * 0.268 / 340.0 * 1e6))
    assert t2.tof_us is None


def test_maxbotix_ascii_on_a_pty() -> None:
    pty = Pty()
    try:
        with open_driver(f"maxbotix:{pty.path}", sensor=2, mount=(0.1, 0.0, 0.0)) as drv:
            rig = drv.read(1.0)
            os.write(pty.master, b"\x00" + encode_range(1234) + b"R99" + encode_range(5000)
                     + b"junk" + encode_range(300))
            got = [drv.read(1.0) for _ in range(3)]
            stats = drv.decoder.stats
    finally:
        pty.close()
    assert isinstance(rig, RigRecord) and rig.sensors[0].id == 2 and rig.sensors[0].x_m == 0.1
    assert got[0].tof_us == pytest.approx(2 * 1.234 / 343.0 * 1e6) and got[0].sensor == 2
    assert got[1].tof_us is None  # 5000 mm: nothing in range
    assert got[2].tof_us == pytest.approx(2 * 0.3 / 343.0 * 1e6)
    assert stats.frames == 3 and stats.bytes_skipped == 1 + 3 + 4


def test_maxbotix_inches() -> None:
    pty = Pty()
    try:
        with open_driver(f"maxbotix:{pty.path}", unit="in") as drv:
            drv.read(1.0)
            os.write(pty.master, encode_range(100, 3))
            rec = drv.read(1.0)
    finally:
        pty.close()
    assert rec.tof_us == pytest.approx(2 * 2.54 / 343.0 * 1e6)
    with pytest.raises(ValueError, match="unit"):
        open_driver("maxbotix:loop://", unit="furlong")


def test_can_bus_with_junk_frames_next_to_the_module() -> None:
    """Error frames, unknown ids and wrong lengths on the bus are skipped and counted."""
    channel = f"junk-{random.random()}"
    sent = io.StringIO()
    stream = list(ring_stream(duration_s=1.0))
    n_err, n_unknown, n_short = 7, 11, 5
    with SimModule.on_can(stream, channel=channel, rate=10.0, sent_log=LogWriter(sent)) as sim, \
            open_driver(f"can:virtual:{channel}") as drv, \
            can.Bus(interface="virtual", channel=channel) as other:
        for k in range(max(n_err, n_unknown, n_short)):
            if k < n_err:
                other.send(can.Message(is_error_frame=True))
            if k < n_unknown:
                other.send(can.Message(arbitration_id=0x7E0 + k, data=b"\x01\x02",
                                       is_extended_id=False))
            if k < n_short:
                other.send(can.Message(arbitration_id=0x131, data=b"\x01", is_extended_id=False))
            time.sleep(0.01)
        got = drain(sim, drv)
        c = drv.counters()
    assert got == list(iter_log(io.StringIO(sent.getvalue())))
    assert (c["error_frames"], c["unknown"], c["bad_length"]) == (n_err, n_unknown, n_short)
    assert c["seq_gaps"] == 0 and c["incomplete"] == 0


def test_sim_driver_equals_what_a_module_sends(tmp_path) -> None:
    log = tmp_path / "drive.jsonl"
    stream = list(ring_stream(duration_s=0.5, pan=True))
    with LogWriter(log) as w:
        w.write_all(stream)
    sent = io.StringIO()
    with SimModule.on_pty(iter_log(log), rate=20.0, sent_log=LogWriter(sent)) as sim, \
            open_driver(sim.url) as drv:
        over_pty = drain(sim, drv)
    with open_driver(f"sim:{log}") as sim_drv:
        direct = list(sim_drv.records(timeout=1.0))
    assert direct == over_pty == list(iter_log(io.StringIO(sent.getvalue())))
    assert math.isclose(direct[-1].t_s, 0.5)


def test_maxbotix_mount_from_the_record_command_line() -> None:
    # PROTOCOL.md: one sensor at the origin "unless a mount is given"; from `sonarloc
    # record` that is --option mount=X,Y,YAW_DEG (it failed: "could not convert string
    # to float: '.'"), and a wrong one is named.
    import argparse

    from sonarloc.commands.record import add_arguments, driver_options

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["maxbotix:loop://", "--out", "x.jsonl", "--option",
                              "mount=0.1,-0.05,90", "--option", "sensor=3"])
    opts = driver_options(args)
    assert opts == {"mount": (0.1, -0.05, 90.0), "sensor": 3}
    with open_driver(args.source, **opts) as drv:
        rig = drv.read(1.0)
    assert isinstance(rig, RigRecord) and rig.sensors[0].id == 3
    assert (rig.sensors[0].x_m, rig.sensors[0].y_m, rig.sensors[0].yaw_deg) == (0.1, -0.05, 90.0)
    with pytest.raises(ValueError, match="`mount` must be x_m, y_m, yaw_deg"):
        open_driver("maxbotix:loop://", mount=(0.1, 0.0))


def test_record_option_none_turns_an_option_off() -> None:
    # PROTOCOL.md: `wake_s=None` turns the wake-up off; from `sonarloc record` the value
    # came through as the text 'none' and the driver refused it ("`wake_s` must be a
    # positive number of seconds or None, got 'none'").
    import argparse

    from sonarloc.commands.record import add_arguments, driver_options

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["loop://", "--out", "x.jsonl", "--option", "wake_s=none",
                              "--option", "start=False"])
    opts = driver_options(args)
    assert opts == {"wake_s": None, "start": False}
    with open_driver(args.source, **opts) as drv:
        assert drv.wake_s is None


def test_pioneer_rig_and_converter_from_the_record_command_line(tmp_path) -> None:
    # `--option rig=RIG.json` crashed `sonarloc record` with a traceback (the path went
    # through as the rig), and the converter's settings (RangeConvFactor of a P2, ...)
    # had no command-line form: both are options of their own now.
    import argparse
    import json

    from sonarloc.commands.record import add_arguments, driver_options

    rig_file = tmp_path / "rig.json"
    rig_file.write_text(json.dumps({"sensors": [{"id": 0, "x_m": 0.15, "y_m": 0.0,
                                                 "yaw_deg": 0.0},
                                                {"id": 1, "x_m": -0.15, "y_m": 0.0,
                                                 "yaw_deg": 180.0}]}))
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    args = parser.parse_args(["pioneer:loop://", "--out", "x.jsonl", "--option",
                              f"rig={rig_file}", "--option", "range_conv=0.268", "--option",
                              "speed_of_sound_mps=340", "--option", "handshake=false"])
    with open_driver(args.source, **driver_options(args)) as drv:
        rig = drv.read(1.0)
        conv = drv.converter
    assert isinstance(rig, RigRecord) and [s.x_m for s in rig.sensors] == [0.15, -0.15]
    assert rig.speed_of_sound_mps == 340.0 == conv.c  # the c that made the TOFs
    assert conv.range_conv == 0.268
    with pytest.raises(ValueError, match="`rig` must be a rig JSON file"):
        open_driver("pioneer:loop://", rig=5, handshake=False)


@pytest.mark.parametrize(("unit", "good", "short"), [("mm", b"R1234\r", b"R124\r"),
                                                     ("cm", b"R123\r", b"R1234\r")])
def test_maxbotix_frame_with_a_byte_lost_is_not_a_range(unit, good, short) -> None:
    # Line noise that drops one digit of "R1234\r" (1234 mm) left "R124\r", read as an
    # obstacle at 124 mm: the decoder took 3 or 4 digits whatever the sensor sends.
    pty = Pty()
    try:
        with open_driver(f"maxbotix:{pty.path}", unit=unit) as drv:
            drv.read(1.0)  # the rig
            os.write(pty.master, good + short + good)
            got = [drv.read(1.0) for _ in range(2)]
            with pytest.raises(DeviceTimeoutError):
                drv.read(0.2)
            stats = drv.decoder.stats
    finally:
        pty.close()
    assert got[0] == dataclasses.replace(got[1], t_s=got[0].t_s)
    assert (stats.frames, stats.bad_length) == (2, 1)

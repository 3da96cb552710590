"""Drivers end to end: a simulated module on a pty, a TCP socket and a virtual CAN bus,
read back with the same driver code a robot uses."""

from __future__ import annotations

import io
import os
import random
import socket
import subprocess
import sys
import threading
import time
import tty

import pytest
import serial
from io_streams import device_records, drain, ring_stream

from sonarloc.errors import DeviceError, DeviceTimeoutError
from sonarloc.io.drivers import BACKENDS, driver_class, open_driver, parse_source
from sonarloc.io.drivers.serial import SerialDriver
from sonarloc.io.drivers.sim import PtyTransport, SimModule
from sonarloc.io.logfile import LogWriter, OdomRecord, RigRecord, TofRecord, iter_log
from sonarloc.io.protocol.framing import ACK, REQUEST_RIG, START, SerialEncoder
from sonarloc.io.protocol.messages import Ack, Echo, RigInfo, RigMount, Start, Stop
from sonarloc.io.protocol.records import messages_from_record


def read_until_done(sim: SimModule, drv) -> list:
    return drain(sim, drv)


def sent_records(buf: io.StringIO) -> list:
    return list(iter_log(io.StringIO(buf.getvalue())))


# -- registry ---------------------------------------------------------------------------
def test_sources_resolve_to_drivers() -> None:
    assert parse_source("/dev/ttyUSB0") == ("serial", ("/dev/ttyUSB0",))
    assert parse_source("loop://") == ("serial", ("loop://",))
    assert parse_source("socket://127.0.0.1:9") == ("serial", ("socket://127.0.0.1:9",))
    assert parse_source("serial:/dev/ttyS1") == ("serial", ("/dev/ttyS1",))
    assert parse_source("can:socketcan:vcan0") == ("can", ("socketcan", "vcan0"))
    assert parse_source("candump:x.log") == ("candump", ("x.log",))
    assert parse_source("maxbotix:socket://127.0.0.1:5") == ("maxbotix", ("socket://127.0.0.1:5",))
    assert parse_source("COM3") == ("serial", ("COM3",))
    with pytest.raises(ValueError, match="can:INTERFACE:CHANNEL"):
        parse_source("can:virtual")
    # a mistyped scheme is named as such (pyserial said "could not open port maxbotics:...")
    with pytest.raises(ValueError, match="unknown source scheme 'maxbotics'.*maxbotix"):
        parse_source("maxbotics:/dev/ttyUSB0")
    assert parse_source("/dev/serial/by-path/pci-0000:00:14.0-usb-0:1") == (
        "serial", ("/dev/serial/by-path/pci-0000:00:14.0-usb-0:1",))  # colons in a path
    with pytest.raises(ValueError, match="unknown driver"):
        driver_class("nope")
    for name in BACKENDS:
        assert driver_class(name).scheme == name


def test_drivers_are_imported_lazily() -> None:
    code = ("import sys, sonarloc.io.drivers as d; "
            "print(sorted(m for m in ('can', 'cantools', 'serial', 'sonarloc.io.drivers.pioneer')"
            " if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env={**os.environ, "PYTHONPATH": os.getcwd()})
    assert out.stdout.strip() == "[]"


def test_open_errors_are_device_errors(tmp_path) -> None:
    with pytest.raises(DeviceError, match="cannot open"):
        open_driver(str(tmp_path / "no-such-tty"))
    with pytest.raises(DeviceError, match="cannot open"):
        open_driver(f"candump:{tmp_path / 'missing.log'}")
    with pytest.raises(DeviceError, match="cannot open"):
        open_driver("can:no-such-interface:x")


def test_a_second_reader_of_one_tty_is_refused() -> None:
    """Two readers of one tty would each get part of the bytes (gaps, CRC errors in both):
    the second open fails naming the port, the first keeps every record."""
    stream = list(ring_stream(duration_s=0.5))
    with SimModule.on_pty(stream, rate=10.0) as sim, open_driver(sim.url) as drv:
        with pytest.raises(DeviceError, match=f"cannot open {sim.url}.*lock"):
            open_driver(sim.url)
        got = read_until_done(sim, drv)
        c = drv.counters()
    assert sum(isinstance(r, TofRecord) for r in got) == sum(r.type == "tof" for r in stream)
    assert (c["crc_errors"], c["bytes_skipped"], c["seq_gaps"]) == (0, 0, 0)


# -- end to end over three transports ----------------------------------------------------
TRANSPORTS = {
    "pty": lambda recs, **kw: SimModule.on_pty(recs, **kw),
    "tcp": lambda recs, **kw: SimModule.on_tcp(recs, **kw),
    "can": lambda recs, **kw: SimModule.on_can(recs, channel=f"e2e-{random.random()}", **kw),
}


@pytest.mark.parametrize("transport", TRANSPORTS)
@pytest.mark.parametrize("pan", [False, True])
def test_module_to_driver_end_to_end(transport: str, pan: bool) -> None:
    stream = list(ring_stream(duration_s=1.0, pan=pan))
    sent = io.StringIO()
    with TRANSPORTS[transport](stream, rate=10.0, sent_log=LogWriter(sent)) as sim, \
            open_driver(sim.url) as drv:
        got = read_until_done(sim, drv)
        acks = list(drv.acks)
    expect = sent_records(sent)
    assert got == expect
    assert isinstance(got[0], RigRecord) and len(got[0].sensors) == 16
    n_dev = sum(r.type in ("odom", "tof") for r in stream)
    assert sum(isinstance(r, (OdomRecord, TofRecord)) for r in got) == n_dev
    assert any(r.tof_us is None for r in got if isinstance(r, TofRecord))
    assert all((r.pan_deg is not None) == pan for r in got if isinstance(r, TofRecord))
    c = drv.counters()
    assert (c["crc_errors"], c["bytes_skipped"], c["seq_gaps"], c["unknown"]) == (0, 0, 0, 0)
    assert c["incomplete"] == 0 and c["dropped"] == 0
    assert sim.stats.lost == 0 and sim.stats.commands >= 2
    assert {a.command for a in acks} >= {START, REQUEST_RIG}
    assert all(a.status == 0 for a in acks)


def test_callback_mode_delivers_on_the_reader_thread() -> None:
    stream = list(ring_stream(duration_s=0.3))
    seen = []
    with SimModule.on_tcp(stream, rate=10.0) as sim, \
            open_driver(sim.url, on_record=seen.append) as drv:
        assert sim.wait(5.0)
        time.sleep(0.3)
        with pytest.raises(DeviceTimeoutError):
            drv.read(timeout=0.05)  # nothing is queued in callback mode
    assert len(seen) == 1 + sum(r.type in ("odom", "tof") for r in stream)


def test_stop_pauses_and_start_resumes() -> None:
    stream = list(ring_stream(duration_s=2.0))
    with SimModule.on_tcp(stream, rate=4.0) as sim, open_driver(sim.url) as drv:
        assert drv.read(2.0) is not None
        drv.send(Stop())
        deadline = time.monotonic() + 5.0
        while not any(a.command == 0x81 for a in drv.acks) and time.monotonic() < deadline:
            time.sleep(0.01)
        while True:  # drain what was in flight
            try:
                drv.read(0.2)
            except DeviceTimeoutError:
                break
        with pytest.raises(DeviceTimeoutError):
            drv.read(0.3)
        drv.send(Start())
        assert isinstance(drv.read(2.0), (RigRecord, OdomRecord, TofRecord))
        sim.stop()


def test_timeout_when_module_waits_for_start() -> None:
    with SimModule.on_pty(list(ring_stream(0.2))) as sim, \
            open_driver(sim.url, start=False) as drv:
        with pytest.raises(DeviceTimeoutError, match="no record within"):
            drv.read(timeout=0.2)
        assert sim.stats.records == 0


# -- loss, damage, reconnects ----------------------------------------------------------------
def test_tcp_disconnect_and_reconnect_mid_stream() -> None:
    stream = list(ring_stream(duration_s=3.0))
    sent = io.StringIO()
    with SimModule.on_tcp(stream, rate=3.0, sent_log=LogWriter(sent)) as sim, \
            open_driver(sim.url, backoff_s=(0.02, 0.1)) as drv:
        got = [drv.read(2.0) for _ in range(50)]
        sim.transport.drop_client()  # pull the cable
        got += read_until_done(sim, drv)
        counters = drv.counters()
    expect = sent_records(sent)
    assert counters["reconnects"] >= 1 and counters["disconnects"] >= 1
    it = iter(expect)
    assert all(any(g == e for e in it) for g in got)  # an in-order subsequence of what was sent
    assert got[-1] == expect[-1]  # the stream continued to the end after the reconnect
    # packets sent while no host was connected show up as a sequence gap
    assert counters["frames_lost"] >= sim.stats.lost > 0
    assert counters["crc_errors"] == 0


def test_pty_unplug_and_replug(tmp_path) -> None:
    link = tmp_path / "ttySONAR0"
    stream = list(ring_stream(duration_s=3.0))
    with SimModule.on_pty(stream, link=link, rate=3.0) as sim, \
            open_driver(str(link), backoff_s=(0.02, 0.1)) as drv:
        first = [drv.read(2.0) for _ in range(30)]
        sim.transport.replug()
        rest = read_until_done(sim, drv)
        assert drv.stats.reconnects >= 1
    assert isinstance(first[0], RigRecord)
    times = [r.t_s for r in first + rest if not isinstance(r, RigRecord)]
    assert times == sorted(times) and times[-1] == pytest.approx(3.0, abs=0.01)


def test_a_pty_that_hung_up_is_not_reopened() -> None:
    # The module's terminal closes; the kernel gives /dev/pts/N to the next pty opened on
    # the machine (another test's module, someone's shell). The driver reopened the path,
    # sent Start to it and recorded its data (a CLI test failed ~1 run in 10 on a busy host).
    stream = list(ring_stream(duration_s=0.3))
    with SimModule.on_pty(stream, rate=None) as sim, \
            open_driver(sim.url, backoff_s=(0.01, 0.02)) as drv:
        path = sim.url
        got = drain(sim, drv, quiet_s=0.2)
        sim.close()  # hangs the terminal up
        master, slave = os.openpty()  # most likely /dev/pts/N again
        try:
            while (rec := drv.read(timeout=5.0)) is not None:  # ended, not a timeout
                got.append(rec)
        finally:
            os.close(slave)
            os.close(master)
        counters = drv.counters()
    assert path.startswith("/dev/pts/")
    assert len(got) == len(device_records(stream))
    assert counters["disconnects"] == 1 and counters["reconnects"] == 0


def test_damaged_byte_stream_through_a_pty() -> None:
    """Good packets, bit flips and garbage written to a real pty: exact counters."""
    rng = random.Random(7)
    enc = SerialEncoder()
    recs = list(ring_stream(duration_s=2.0))
    packets = [enc.encode(m) for r in recs for m in messages_from_record(r)]
    rig_len = 17  # RigInfo + 16 RigMounts come first and stay intact
    corrupt = set(rng.sample(range(rig_len, len(packets)), 40))
    wire, garbage, lost_bytes = bytearray(), 0, 0
    for k, p in enumerate(packets):
        if rng.random() < 0.1:
            junk = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 30)))
            wire += junk
            garbage += len(junk)
        if k in corrupt:
            p = bytearray(p)
            p[rng.randrange(2, len(p))] ^= 1 << rng.randrange(8)
            lost_bytes += len(p)
        wire += p
    master, slave = os.openpty()
    tty.setraw(slave)
    path = os.ttyname(slave)
    try:
        with SerialDriver(path, start=False, reconnect=False) as drv:
            pos = 0
            while pos < len(wire):
                step = rng.randrange(1, 300)
                os.write(master, wire[pos:pos + step])
                pos += step
                time.sleep(0.0005)
            got = []
            while True:
                try:
                    got.append(drv.read(0.3))
                except DeviceTimeoutError:
                    break
            s = drv.decoder.stats
    finally:
        os.close(slave)
        os.close(master)
    runs = sum(1 for k in corrupt if k - 1 not in corrupt)
    assert s.frames == len(packets) - len(corrupt)
    assert s.seq_gaps == runs and s.frames_lost == len(corrupt)
    assert s.bytes_skipped == garbage + lost_bytes
    assert s.crc_errors >= len(corrupt)
    assert len([r for r in got if not isinstance(r, RigRecord)]) == len(packets) - rig_len \
        - len(corrupt)


def test_loop_url_and_raw_writes() -> None:
    with open_driver("loop://", start=False) as drv:
        drv.send(RigInfo(0, 34300, 1))
        drv.send(RigMount(7, 1000, -500, 4500))
        drv.write(b"\x00junk\xfa")
        drv.send(Echo(7, 2_000_000, 3000))
        got = [drv.read(1.0), drv.read(1.0)]
        assert got[0] == RigRecord(((got[0].sensors[0]),), 343.0, 0.0)
        assert got[0].sensors[0].x_m == 0.1 and got[0].sensors[0].yaw_deg == 45.0
        assert got[1] == TofRecord(2.0, 7, 6000.0)
        assert drv.decoder.stats.bytes_skipped == 6


def test_ack_is_sent_for_each_command() -> None:
    with SimModule.on_pty(list(ring_stream(0.2))) as sim, \
            open_driver(sim.url, start=False) as drv:
        drv.send(Stop())
        deadline = time.monotonic() + 2.0
        while not drv.acks and time.monotonic() < deadline:
            time.sleep(0.01)
        assert drv.acks == [Ack(0x81, 0, 0)]
        assert ACK == 0x40


def test_a_failing_callback_is_reported_not_swallowed() -> None:
    def boom(rec) -> None:
        raise RuntimeError("caller bug")

    with open_driver("loop://", start=False, on_record=boom) as drv:
        drv.send(Echo(1, 2, 3))
        with pytest.raises(DeviceError, match="caller bug"):
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                try:
                    drv.read(0.05)
                except DeviceTimeoutError:
                    continue
        assert drv.stats.callback_errors == 1


def test_pty_close_waits_for_the_host_to_read() -> None:
    """Closing the module's pty hangs the terminal up and Linux drops what the host has not
    read yet: close() waits (bounded) until the host has read every byte written."""
    tr = PtyTransport()
    host = serial.Serial(tr.url, timeout=2.0)   # the host's side, as the serial driver opens it
    try:
        payload = bytes(range(256)) * 12   # fits the terminal's buffer: no write waits
        assert tr._write(payload)
        t0 = time.monotonic()
        closer = threading.Thread(target=tr.close)
        closer.start()
        time.sleep(0.3)            # a slow host: the module is closing meanwhile
        assert closer.is_alive()   # still waiting for the host
        got = host.read(len(payload))
        closer.join(5.0)
        assert got == payload
        assert not closer.is_alive() and time.monotonic() - t0 < PtyTransport.DRAIN_WAIT_S
    finally:
        host.close()
        tr.close()


def test_pty_close_without_a_reading_host_gives_up() -> None:
    tr = PtyTransport()
    tr.DRAIN_WAIT_S = 0.2
    host = serial.Serial(tr.url, timeout=0.1)   # opened, never read
    try:
        assert tr._write(b"x" * 100)
        t0 = time.monotonic()
        tr.close()
        assert 0.15 < time.monotonic() - t0 < 2.0
    finally:
        host.close()


def test_pty_close_does_not_wait_for_a_host_that_closed() -> None:
    """A host that read part of the stream and closed the port (``record --duration``)
    reads nothing more: close() does not wait for it (it waited the whole
    DRAIN_WAIT_S, 5 s, at the end of every such run), nor for a host that never came."""
    tr = PtyTransport()
    tr.DRAIN_WAIT_S = 3600.0   # were it waited for, the join below would time out
    host = serial.Serial(tr.url, timeout=0.5)
    try:
        assert tr._host_attached()
        assert tr._write(b"x" * 100)
        assert host.read(10) == b"x" * 10
    finally:
        host.close()
    assert not tr._host_attached()
    closer = threading.Thread(target=tr.close, daemon=True)
    closer.start()
    closer.join(30.0)
    assert not closer.is_alive()
    never = PtyTransport()
    never.DRAIN_WAIT_S = 3600.0
    assert not never._host_attached()
    closer = threading.Thread(target=never.close, daemon=True)
    closer.start()
    closer.join(30.0)
    assert not closer.is_alive()


def test_pty_link_never_replaces_a_file(tmp_path, run_cli) -> None:
    # `serve-sim --pty --link notes.txt` replaced the user's file by a symlink to the
    # terminal, and deleted it when the module stopped.
    keep = tmp_path / "notes.txt"
    keep.write_text("mine\n")
    with pytest.raises(DeviceError, match="exists and is not a symlink"):
        PtyTransport(keep)
    proc = run_cli("serve-sim", "--log", str(keep), "--pty", "--link", str(keep))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "exists and is not a symlink" in proc.stderr
    assert keep.read_text() == "mine\n"
    with pytest.raises(DeviceError, match="cannot link"):
        PtyTransport(tmp_path / "no" / "dir" / "tty")
    stale = tmp_path / "ttySONAR"  # a link left behind by a module killed earlier
    stale.symlink_to("/dev/pts/999999")
    tr = PtyTransport(stale)
    try:
        assert os.readlink(stale) == tr.slave_path
    finally:
        tr.close()
    assert not stale.exists() and not stale.is_symlink()


class _ChunkCounter(SerialDriver):
    """A SerialDriver that notes the size of every read its port loop hands on."""

    def __init__(self, url: str, **kwargs) -> None:
        super().__init__(url, **kwargs)
        self.chunks: list[int] = []

    def _on_bytes(self, data: bytes) -> None:
        self.chunks.append(len(data))
        super()._on_bytes(data)


def test_socket_url_reads_what_is_waiting_not_a_byte_per_call() -> None:
    # pyserial's socket:// says in_waiting 1 for any amount waiting, and the reader took
    # one byte per read (~20 us of CPU a byte). 20 kB with junk and a damaged packet in it,
    # all waiting in the socket: a few reads, and every byte and packet accounted for.
    enc = SerialEncoder()
    recs = [r for r in ring_stream(duration_s=4.0) if r.type in ("rig", "odom", "tof")]
    packets = [enc.encode(m) for r in recs for m in messages_from_record(r)]
    bad = bytearray(packets[500])
    bad[-1] ^= 0x40  # CRC fails: its bytes are skipped, the decoder resyncs on the next
    wire = b"".join(packets[:500]) + b"\xfa\xfb\x07junk" + bytes(bad) + b"".join(packets[501:])
    server = socket.create_server(("127.0.0.1", 0))
    try:
        with _ChunkCounter(f"socket://127.0.0.1:{server.getsockname()[1]}", start=False,
                           reconnect=False) as drv:
            conn, _ = server.accept()
            with conn:
                conn.sendall(wire)
                got = []
                while len(got) < len(recs) - 1:  # all but the damaged packet's reading
                    got.append(drv.read(2.0))
                with pytest.raises(DeviceTimeoutError):
                    drv.read(0.1)
            s = drv.decoder.stats
    finally:
        server.close()
    assert s.bytes_in == len(wire) == s.bytes_framed + s.bytes_skipped
    assert s.frames == len(packets) - 1 and s.crc_errors >= 1
    assert len(drv.chunks) <= len(wire) // 1000  # 4 kB reads: ~5 of them, not 19 500

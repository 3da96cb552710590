"""A module on TCP (behind a ser2net-like bridge) has one host: a second host is refused
at once and told why, and the first keeps every record."""

from __future__ import annotations

import io
import select
import socket
import subprocess
import threading
import time

import pytest
from io_streams import device_records, drain, ring_stream

from sonarloc.errors import DeviceError
from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.port import SocketPort, refusal_text
from sonarloc.io.drivers.sim import SimModule, TcpTransport
from sonarloc.io.logfile import LogWriter, iter_log


def test_a_second_host_is_refused_and_the_first_keeps_every_record() -> None:
    # Before: the newest connection took the module over; two hosts reconnecting took it
    # from each other in turn (two `record`s of 921 readings kept 599 and 322).
    stream = list(ring_stream(duration_s=1.0))
    sent = io.StringIO()
    with SimModule.on_tcp(stream, rate=2.0, sent_log=LogWriter(sent)) as sim, \
            open_driver(sim.url, backoff_s=(0.02, 0.1)) as first:
        got = [first.read(2.0)]  # the first host is streaming
        with open_driver(sim.url, backoff_s=(0.02, 0.1)) as second:
            t0 = time.monotonic()
            with pytest.raises(DeviceError, match="refused the connection: 'Port already "
                                                  "in use' .*another host"):
                second.read(2.0)
            assert time.monotonic() - t0 < 1.0
            assert second.stats.reconnects == 0
        got += drain(sim, first, quiet_s=0.1)
        assert first.stats.disconnects == 0
        assert isinstance(sim.transport, TcpTransport)
        assert sim.transport.refused == 1 and sim.transport.clients == 1
    want = list(iter_log(io.StringIO(sent.getvalue())))
    assert len(want) == len(device_records(stream))
    assert got == want  # every record the module sent, the rig first


def test_record_refused_by_a_busy_module_exits_with_one_line(cli_command, tmp_path) -> None:
    stream = list(ring_stream(duration_s=1.0))
    with SimModule.on_tcp(stream, rate=1.0) as sim, open_driver(sim.url) as first:
        assert first.read(2.0) is not None
        argv, env = cli_command("record", sim.url, "--out", str(tmp_path / "second.jsonl"),
                                "--timeout", "1", "--duration", "3")
        proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=30)
        assert first.stats.disconnects == 0
        sim.stop()
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1, proc.stderr
    assert proc.stderr.startswith(f"sonarloc record: error: {sim.url}: the other end refused "
                                  f"the connection: 'Port already in use'")


def test_a_socket_port_keeps_what_the_other_end_sent_at_once() -> None:
    # pyserial's socket:// open discards what has arrived by then: a bridge that answers
    # at once had its refusal lost (7 of 40 connections here), the host saw a bare hang-up
    # and reconnected until its timeout.
    server = socket.create_server(("127.0.0.1", 0))
    url = f"socket://127.0.0.1:{server.getsockname()[1]}"
    n = 60

    def bridge() -> None:
        for _ in range(n):
            conn, _ = server.accept()
            conn.sendall(TcpTransport.BUSY)
            conn.close()

    thread = threading.Thread(target=bridge)
    thread.start()
    ports, got = [], []
    try:
        for _ in range(n):
            port = SocketPort(None, timeout=0)
            port.port = url
            port.open()
            ports.append(port)
            select.select([port.fileno()], [], [], 2.0)
            got.append(port.read(4096))  # the line (EOF comes with the next read)
    finally:
        thread.join(5.0)
        server.close()
        for p in ports:
            p.close()
    assert got == [TcpTransport.BUSY] * n


def test_socket_port_closes_without_pyserial_s_sleep(monkeypatch) -> None:
    """pyserial's socket:// close sleeps 0.3 s "in case of quick reconnects"; the driver
    reconnects with its own back-off, so SocketPort closes at once (each host's stop,
    each test's teardown) and still closes the connection: the server sees EOF."""
    import serial.urlhandler.protocol_socket as pyserial_socket

    slept: list[float] = []
    monkeypatch.setattr(pyserial_socket.time, "sleep", slept.append)
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = SocketPort(None, timeout=0)
        port.port = f"socket://127.0.0.1:{server.getsockname()[1]}"
        port.open()
        conn, _ = server.accept()
        with conn:
            port.close()
            assert not port.is_open and slept == []
            conn.settimeout(2.0)
            assert conn.recv(10) == b""   # the connection is closed, not just forgotten
        port.close()   # twice: nothing happens


def test_refusal_text() -> None:
    assert refusal_text(b"Port already in use\r\n") == "Port already in use"
    assert refusal_text(b"") is None and refusal_text(b"\r\n") is None
    assert refusal_text(b"\xfa\xfb\x05\x10") is None  # a frame's start, not text
    assert refusal_text(b"two\r\nlines\r\n") is None

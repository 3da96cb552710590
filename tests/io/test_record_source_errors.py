"""`sonarloc record` on a line that carries bytes but no readings (a wrong line speed,
the wrong device): the error says so instead of "no data"."""

from __future__ import annotations

import os
import random
import subprocess
import time

import pytest


@pytest.mark.parametrize("source", ["serial", "maxbotix"])
def test_noise_on_the_line_is_not_called_no_data(record_on_pty, tmp_path, source) -> None:
    # A baud mismatch turns every byte into noise. Before: "no data within 0.6 s
    # (... skipped 5200 B ...)" for the module, and for a MaxBotix (whose rig is known
    # beforehand) exit 0 with a log of the rig alone.
    out = tmp_path / "rec.jsonl"
    rng = random.Random(5)
    with record_on_pty("--out", str(out), "--timeout", "0.6",
                       scheme="" if source == "serial" else f"{source}:") as (proc, master):
        if source == "serial":
            os.read(master, 100)  # its Start: the port is open
        else:
            time.sleep(0.4)
        end = time.monotonic() + 10.0
        while proc.poll() is None and time.monotonic() < end:
            # never an "R" (a MaxBotix frame) nor 0xFA 0xFB (a packet's start)
            os.write(master, bytes(rng.choice(b"\x00\x13\x7f\x80\xaa\xfe 0123456789\r")
                                   for _ in range(100)))
            time.sleep(0.01)
        _, err = proc.communicate(timeout=10)
    assert proc.returncode == 2, err
    assert err.count("\n") == 1
    assert "no readings within 0.6 s" in err and "bytes came but no packet" in err
    assert "wrong --baud?" in err
    assert ("the sonarloc module" if source == "serial" else "a MaxBotix sensor") in err


def test_an_unplugged_module_is_named_in_the_summary(cli_command, tmp_path) -> None:
    # The module's terminal goes away mid-stream: `record` stops after --timeout and said
    # only "stopped after 0.5 s without data", as if the module had fallen silent.
    from io_streams import ring_stream

    from sonarloc.io.drivers.sim import SimModule

    out = tmp_path / "rec.jsonl"
    sim = SimModule.on_pty(list(ring_stream(duration_s=30.0)), rate=1.0).start()
    try:
        argv, env = cli_command("record", sim.url, "--out", str(out), "--timeout", "0.5")
        proc = subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, text=True)
        try:
            end = time.monotonic() + 10.0
            while sim.stats.records < 20 and time.monotonic() < end:
                time.sleep(0.01)
        finally:
            sim.close()  # unplugged
        try:
            _, err = proc.communicate(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    finally:
        sim.close()
    assert proc.returncode == 0, err
    # a terminal that hung up is not reopened (its number goes to the next pty opened):
    # the recording ends there, with the disconnect in the summary
    assert "disconnects 1" in err and "reconnects" not in err
    assert "stopped after" not in err
    # and says so (before: only "disconnects 1" in the summary)
    recorded = next(line for line in err.splitlines() if line.startswith("recorded "))
    assert recorded.endswith(f"; the terminal {sim.url} hung up; a /dev/pts/ path is not "
                             f"reopened (its number goes to the next terminal opened; use "
                             f"serve-sim --link, or a stable link to the device)")


def test_a_changed_rig_is_warned_about(record_on_pty, tmp_path) -> None:
    # A module reconfigured (or another module plugged in) mid-recording sends another
    # rig: the log keeps the first (one rig per log), and said nothing about it.
    from io_streams import ring_rig

    from sonarloc.io.logfile import RigRecord, SensorMount, TofRecord
    from sonarloc.io.protocol.framing import SerialEncoder
    from sonarloc.io.protocol.records import messages_from_record

    enc = SerialEncoder()
    other = RigRecord((SensorMount(0, 0.1, 0.0, 0.0),), t_s=0.2)
    recs = [ring_rig(), TofRecord(0.1, 3, 1000.0), other, TofRecord(0.3, 0, 1200.0)]
    wire = b"".join(enc.encode(m) for r in recs for m in messages_from_record(r))
    out = tmp_path / "rec.jsonl"
    with record_on_pty("--out", str(out), "--timeout", "0.4") as (proc, master):
        os.read(master, 100)  # its Start: the port is open
        os.write(master, wire)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert "warning: the rig changed at t_s 0.2 (1 time)" in err
    assert out.read_text().count('"type":"rig"') == 1

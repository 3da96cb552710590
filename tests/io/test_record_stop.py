"""`sonarloc record` stopped by the user (Ctrl-C, SIGTERM, --duration), by silence
(--timeout) or by trouble (a full disk): the log holds every record the device delivered
up to then, and stays valid."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time

import pytest
from io_streams import ring_stream

from sonarloc.io.logfile import LogStats, TofRecord, iter_log
from sonarloc.io.protocol.framing import SerialEncoder
from sonarloc.io.protocol.records import messages_from_record


def _summary_counts(stderr: str) -> tuple[int, int]:
    """(records written, records the driver delivered) from record's last lines."""
    written = re.search(r"recorded (\d+) records", stderr)
    delivered = re.search(r"; (\d+) records", stderr)
    assert written and delivered, stderr
    return int(written.group(1)), int(delivered.group(1))


@pytest.mark.parametrize("how", ["timeout", "duration", "sigint", "sigterm"])
def test_readings_behind_a_false_header_are_recorded_when_recording_stops(
        record_on_pty, tmp_path, how) -> None:
    # A module that falls quiet right after a false header (line noise "FA FB FF") leaves
    # its last good packets waiting for 255 bytes that never come; the driver recovers
    # them when it closes (PROTOCOL.md: flush), but `record` had stopped reading by then
    # and dropped them (and any reading still queued when Ctrl-C came).
    enc = SerialEncoder()
    stream = [r for r in ring_stream(duration_s=0.2) if r.type in ("rig", "odom", "tof")]
    last = [TofRecord(0.3, 1, 1000.0), TofRecord(0.305, 2, None), TofRecord(0.31, 3, 2222.0)]
    wire = b"".join(enc.encode(m) for r in stream for m in messages_from_record(r))
    wire += b"\xfa\xfb\xff" + b"".join(enc.encode(m) for r in last
                                      for m in messages_from_record(r))
    out = tmp_path / "rec.jsonl"
    extra = {"timeout": ["--timeout", "0.3"], "duration": ["--duration", "0.6"]}
    with record_on_pty("--out", str(out), *extra.get(how, [])) as (proc, master):
        os.read(master, 100)  # its Start: the port is open (opening flushes its input)
        os.write(master, wire)
        if how.startswith("sig"):
            time.sleep(0.5)  # it reads all of it, then waits for more
            proc.send_signal(signal.SIGINT if how == "sigint" else signal.SIGTERM)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    recs = list(iter_log(out, LogStats(), strict=True))
    assert recs[-3:] == last
    assert len(recs) == len(stream) + 3
    assert _summary_counts(err) == (len(recs), len(recs))


def test_full_disk_keeps_a_valid_log_and_names_the_file(run_cli, cli_command, tmp_path) -> None:
    # Before: "sonarloc record: error: [Errno 27] File too large" (which file?) and a log
    # cut in the middle of a line (the text buffer's last flush, 8 KiB at a time).
    import resource

    from sonarloc.io.drivers.sim import SimModule

    dump, full, cut = tmp_path / "sonar.log", tmp_path / "full.jsonl", tmp_path / "cut.jsonl"
    sim = SimModule.to_candump(ring_stream(duration_s=2.0), dump)
    sim.run()
    sim.close()
    run_cli("record", f"candump:{dump}", "--out", str(full), check=True)
    limit = 10_000
    assert full.stat().st_size > 2 * limit

    def small_disk() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    argv, env = cli_command("record", f"candump:{dump}", "--out", str(cut))
    proc = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=60,
                          preexec_fn=small_disk)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and str(cut) in proc.stderr
    assert "File too large" in proc.stderr
    text = cut.read_text()
    assert text.endswith("\n") and limit - 300 < len(text) <= limit
    assert full.read_text().startswith(text)  # whole lines, the first ones
    list(iter_log(cut, strict=True))


def test_a_killed_recorder_leaves_the_log_of_all_but_the_last_half_second(
        cli_command, tmp_path) -> None:
    # The robot's power fails (SIGKILL): no buffer is flushed at exit, so what is on disk
    # is what `record` wrote before. A slow stream (about 3 kB/s) must not sit for
    # seconds in a write buffer.
    from sonarloc.io.drivers.sim import SimModule

    out = tmp_path / "rec.jsonl"
    stream = list(ring_stream(duration_s=20.0, dt_s=0.02))
    with SimModule.on_tcp(stream, rate=1.0) as sim:
        argv, env = cli_command("record", sim.url, "--out", str(out))
        proc = subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, text=True)
        try:
            end = time.monotonic() + 10.0
            while sim.stats.records == 0 and time.monotonic() < end:
                time.sleep(0.01)
            time.sleep(1.2)
            sent_t = sim._t_now  # the stream time of the last record sent
            proc.kill()
            proc.communicate(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    recs = list(iter_log(out, strict=True))
    assert recs and recs[0].type == "rig"
    assert recs[-1].t_s > sent_t - 0.5 - 0.2


def test_a_source_without_rig_keeps_time_order_past_the_hold_limit(tmp_path, monkeypatch,
                                                                    capsys) -> None:
    # Readings are held back until the rig comes; past HOLD_MAX of them they were written
    # at once, and the held ones only at the end: the log went back in time.
    import argparse

    from sonarloc.commands import record
    from sonarloc.io.logfile import LogWriter

    log, out = tmp_path / "in.jsonl", tmp_path / "rec.jsonl"
    with LogWriter(log) as w:
        w.write_all(r for r in ring_stream(duration_s=1.0) if r.type in ("odom", "tof"))
    monkeypatch.setattr(record, "HOLD_MAX", 50)
    args = argparse.Namespace(source=f"sim:{log}", out=str(out), duration=None, timeout=5.0,
                              baud=None, no_start=False, option=[])
    assert record.run(args) == 0
    stats = LogStats()
    recs = list(iter_log(out, stats))
    assert len(recs) > 100 and stats.time_backwards_count == 0
    assert "no rig description" in capsys.readouterr().err


def test_a_device_that_sends_nothing_leaves_an_earlier_log_as_it_was(record_on_pty,
                                                                        tmp_path) -> None:
    # `record /dev/ttyUSB0 --out run1.jsonl` on the wrong port (or a module that answers
    # nothing) used to empty run1.jsonl before saying "no data": the earlier recording
    # was lost. --out is now opened at the first reading or odometry.
    out = tmp_path / "run1.jsonl"
    out.write_text('{"type":"odom","t_s":0.0,"x_m":0.0,"y_m":0.0,"yaw_deg":0.0}\n')
    before = out.read_bytes()
    with record_on_pty("--out", str(out), "--timeout", "0.3") as (proc, master):
        os.read(master, 100)  # its Start: the port is open
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 2 and "no data within 0.3 s" in err, err
    assert out.read_bytes() == before
    # a rig alone is not a recording either
    enc = SerialEncoder()
    rig = next(r for r in ring_stream(duration_s=0.1) if r.type == "rig")
    with record_on_pty("--out", str(out), "--timeout", "0.3") as (proc, master):
        os.read(master, 100)
        os.write(master, b"".join(enc.encode(m) for m in messages_from_record(rig)))
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 2, err
    assert out.read_bytes() == before

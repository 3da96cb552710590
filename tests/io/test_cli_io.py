"""`sonarloc serve-sim` and `sonarloc record` as a user runs them: two processes talking
over a pty, TCP on 127.0.0.1, or a candump file."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from io_streams import ring_stream

from sonarloc.io.logfile import LogWriter

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ROOM = os.path.join(REPO, "maps", "room.geojson")


def serve(*args: str) -> tuple[subprocess.Popen[str], str]:
    env = {**os.environ, "PYTHONPATH": REPO}
    proc = subprocess.Popen([sys.executable, "-m", "sonarloc", "serve-sim", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    assert proc.stdout is not None
    url = proc.stdout.readline().strip()
    return proc, url


def finish(proc: subprocess.Popen[str]) -> str:
    try:
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    return err


@pytest.mark.skipif(not os.path.exists(ROOM), reason="needs maps/room.geojson")
def test_serve_sim_map_over_tcp_and_record(run_cli, tmp_path) -> None:
    sent, out = tmp_path / "sent.jsonl", tmp_path / "rec.jsonl"
    proc, url = serve("--map", ROOM, "--listen", "127.0.0.1:0", "--duration", "4",
                      "--rate", "8", "--sent-log", str(sent), "--linger", "0.2")
    assert url.startswith("socket://127.0.0.1:")
    rec = run_cli("record", url, "--out", str(out), "--timeout", "5", check=True)
    err = finish(proc)
    assert out.read_text() == sent.read_text()
    assert '"type":"rig"' in out.read_text().splitlines()[0]
    assert "good " in rec.stderr and "crc 0" in rec.stderr and "gaps 0" in rec.stderr
    assert "sent " in err and "0 lost" in err


def test_serve_sim_log_over_pty_and_record(run_cli, tmp_path) -> None:
    log, sent, out = tmp_path / "in.jsonl", tmp_path / "sent.jsonl", tmp_path / "rec.jsonl"
    with LogWriter(log) as w:
        w.write_all(ring_stream(duration_s=1.0, pan=True))
    # the module lingers 3 s after its last record, and closing its terminal waits until
    # the host has read what is in flight (PtyTransport.DRAIN_WAIT_S): a host slowed down
    # by a loaded machine lost the last records before that wait was there
    proc, url = serve("--log", str(log), "--pty", "--rate", "5", "--sent-log", str(sent),
                      "--linger", "3.0")
    assert url.startswith("/dev/")
    run_cli("record", url, "--out", str(out), "--timeout", "5", check=True)
    finish(proc)
    assert out.read_text() == sent.read_text()
    assert len(out.read_text().splitlines()) == 1 + 201 + 51


@pytest.mark.skipif(not os.path.exists(ROOM), reason="needs maps/room.geojson")
def test_serve_sim_candump_and_record(run_cli, tmp_path) -> None:
    dump, sent, out = tmp_path / "s.log", tmp_path / "sent.jsonl", tmp_path / "rec.jsonl"
    run_cli("serve-sim", "--map", ROOM, "--candump", str(dump), "--duration", "3",
            "--sent-log", str(sent), check=True)
    rec = run_cli("record", f"candump:{dump}", "--out", str(out), check=True)
    assert out.read_text() == sent.read_text()
    assert "recorded" in rec.stderr and "malformed" not in rec.stderr


def test_bad_input_exits_2_with_one_line(run_cli, tmp_path) -> None:
    cases = [
        ("record", str(tmp_path / "no-tty"), "--out", str(tmp_path / "o.jsonl")),
        ("record", "can:virtual", "--out", str(tmp_path / "o.jsonl")),
        ("record", "loop://", "--out", str(tmp_path / "o.jsonl"), "--option", "nonsense"),
        ("record", f"candump:{tmp_path}/x.log", "--out", str(tmp_path / "o.jsonl")),
        ("record", "loop://", "--out", str(tmp_path / "o.jsonl"), "--timeout", "0.2"),
        ("serve-sim", "--log", str(tmp_path / "missing.jsonl"), "--listen", "nohost"),
        ("serve-sim", "--log", str(tmp_path / "missing.jsonl"), "--candump", "x.log",
         "--duration", "-1"),
    ]
    for args in cases:
        proc = run_cli(*args)
        assert proc.returncode == 2, (args, proc.stderr)
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "error" in lines[0], (args, proc.stderr)
    proc = run_cli("serve-sim", "--listen", "127.0.0.1:0")  # neither --map nor --log
    assert proc.returncode == 2


def test_record_duration_and_serve_sim_sigterm(run_cli, tmp_path) -> None:
    log, sent, out = tmp_path / "in.jsonl", tmp_path / "sent.jsonl", tmp_path / "rec.jsonl"
    with LogWriter(log) as w:
        w.write_all(ring_stream(duration_s=30.0))
    proc, url = serve("--log", str(log), "--listen", "127.0.0.1:0", "--rate", "1",
                      "--sent-log", str(sent))
    try:
        rec = run_cli("record", url, "--out", str(out), "--duration", "0.8", check=True)
    finally:
        proc.terminate()  # SIGTERM: the module stops cleanly and flushes its sent log
    err = finish(proc)
    lines = out.read_text().splitlines()
    assert '"type":"rig"' in lines[0] and len(lines) > 20
    assert "sent " in err
    sent_lines = sent.read_text().splitlines()
    assert sent_lines[:len(lines)] == lines  # what was recorded is what was sent, in order
    assert "recorded" in rec.stderr


@pytest.mark.skipif(not os.path.exists(ROOM), reason="needs maps/room.geojson")
def test_serve_sim_on_a_virtual_can_bus_says_no_other_process_hears_it(run_cli) -> None:
    # `serve-sim --can virtual:x` then `record can:virtual:x` in another shell hears
    # nothing (python-can's virtual bus is in-process), and without --no-wait the module
    # waits forever for a Start: the command says so and names what works instead.
    proc = run_cli("serve-sim", "--map", ROOM, "--can", "virtual:x", "--no-wait",
                   "--duration", "0.2", "--linger", "0")
    assert proc.returncode == 0 and proc.stdout.splitlines()[0] == "can:virtual:x"
    assert "reaches only this process" in proc.stderr and "socketcan:vcan0" in proc.stderr


def test_serve_sim_with_a_missing_log_announces_nothing(run_cli, tmp_path) -> None:
    # It printed the source to open (stdout's first line, what scripts read) and
    # "serving the sonar module on ...", and only then failed on the missing log.
    proc = run_cli("serve-sim", "--log", str(tmp_path / "none.jsonl"), "--listen",
                   "127.0.0.1:0", "--no-wait")
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and "cannot open log" in proc.stderr

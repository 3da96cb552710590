"""candump logs: written by the simulated module with python-can's writer, read back with
python-can's reader; a damaged log is read to the end with every problem counted."""

from __future__ import annotations

import dataclasses
import io
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from io_streams import drain, ring_stream

from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.base import Pacer
from sonarloc.io.drivers.candump import CandumpDriver
from sonarloc.io.drivers.sim import SimModule
from sonarloc.io.logfile import LogWriter, TofRecord, iter_log


def write_candump(path, pan: bool = False, duration_s: float = 1.0) -> list:
    sent = io.StringIO()
    sim = SimModule.to_candump(ring_stream(duration_s=duration_s, pan=pan), path,
                               sent_log=LogWriter(sent))
    sim.run()
    sim.close()
    return list(iter_log(io.StringIO(sent.getvalue())))


def read_all(source: str, **kw) -> tuple[list, CandumpDriver]:
    drv = open_driver(source, **kw)
    with drv:
        out = list(drv.records(timeout=5.0))
    assert isinstance(drv, CandumpDriver)
    return out, drv


def test_candump_round_trip(tmp_path) -> None:
    path = tmp_path / "sonar.log"
    sent = write_candump(path, pan=True)
    got, drv = read_all(f"candump:{path}")
    assert got == sent
    assert drv.counters()["malformed_lines"] == 0 and drv.decoder.stats.incomplete == 0
    first = path.read_text().splitlines()[0]
    assert first.startswith("(0.000000) can0 130#")  # RIG_INFO, in candump -L format


def test_paced_replay_follows_the_timestamps(tmp_path) -> None:
    import time

    path = tmp_path / "sonar.log"
    write_candump(path, duration_s=0.5)
    t = time.monotonic()
    got, _ = read_all(f"candump:{path}", rate=5.0)
    assert time.monotonic() - t >= 0.5 / 5.0 * 0.9
    assert got[-1].t_s == 0.5


def test_corrupted_candump_is_read_to_the_end(tmp_path) -> None:
    rng = random.Random(3)
    path = tmp_path / "sonar.log"
    sent = write_candump(path, duration_s=2.0)
    lines = path.read_text().splitlines()
    echo_lines = [i for i, ln in enumerate(lines) if " 110#" in ln]
    damaged = sorted(rng.sample(echo_lines, 60))
    kinds = {}
    out = []
    for i, ln in enumerate(lines):
        if i in damaged:
            kind = len(kinds) % 6
            kinds[i] = kind
            stamp, chan, frame, rx = ln.split()
            if kind == 0:
                ln = ln.replace("110#", "11G#")  # bad hex id
            elif kind == 1:
                ln = ln[: len(ln) // 2]  # truncated line
            elif kind == 2:
                ln = "\x00\x17binary junk\xff"  # noise
            elif kind == 3:
                ln = f"{stamp} {chan} 110#{frame[4:12]} {rx}"  # DLC 4 instead of 8
            elif kind == 4:
                ln = f"{stamp} {chan} 7AB#{frame[4:]} {rx}"  # an id not in the DBC
            else:
                ln = f"{stamp} {chan} 20000080#0000000000000000"  # error frame
        out.append(ln)
    out.insert(5, "")  # blank lines are fine
    path.write_text("\n".join(out) + "\n", encoding="latin-1")
    got, drv = read_all(f"candump:{path}")

    lost = {lines[i] for i in damaged}
    # every undamaged reading is there, in order; the 60 damaged ones are missing
    expect_tof = [r for r in sent if isinstance(r, TofRecord)]
    got_tof = [r for r in got if isinstance(r, TofRecord)]
    assert len(got_tof) == len(expect_tof) - 60
    assert [r for r in got if not isinstance(r, TofRecord)] == \
        [r for r in sent if not isinstance(r, TofRecord)]
    n = {k: sum(1 for v in kinds.values() if v == k) for k in range(6)}
    c = drv.counters()
    assert c["malformed_lines"] == n[0] + n[1] + n[2]
    assert c["bad_length"] == n[3]
    assert c["unknown"] == n[4]
    assert c["error_frames"] == n[5]
    assert c["seq_gaps"] > 0 and c["frames_lost"] == 60  # the 4-bit echo counter saw them go
    assert all(lineno >= 1 for lineno, _ in drv.malformed)
    assert len(lost) == 60


@settings(max_examples=60, deadline=None)
@given(st.lists(st.text(max_size=60), max_size=30))
def test_any_text_no_exception(tmp_path_factory, text_lines) -> None:
    path = tmp_path_factory.mktemp("fuzz") / "junk.log"
    path.write_text("\n".join(text_lines), encoding="utf-8", errors="surrogatepass")
    got, drv = read_all(f"candump:{path}")
    assert drv.stats.malformed_lines <= len(path.read_text(errors="replace").splitlines())


def test_other_python_can_formats(tmp_path) -> None:
    import can

    from sonarloc.io.protocol.canbus import CanEncoder
    from sonarloc.io.protocol.records import messages_from_record

    recs = list(ring_stream(duration_s=0.2))
    enc = CanEncoder()
    path = tmp_path / "sonar.asc"
    with can.Logger(str(path)) as logger:
        t = 0.0
        for r in recs:
            for m in messages_from_record(r):
                for f in enc.encode(m):
                    f.timestamp = t = t + 0.001
                    logger.on_message_received(f)
    got, _ = read_all(f"candump:{path}")
    assert len(got) == 1 + sum(r.type in ("odom", "tof") for r in recs)


def test_record_names_the_first_bad_line_of_a_candump(tmp_path, run_cli) -> None:
    # FORMATS.md: a bad file names the line. `record` said only "malformed lines 2".
    path, out = tmp_path / "sonar.log", tmp_path / "rec.jsonl"
    write_candump(path, duration_s=0.3)
    lines = path.read_text().splitlines()
    lines[30] = "garbage in the log"
    lines[40] = lines[40].replace("#", "#ZZ")
    path.write_text("\n".join(lines) + "\n")
    proc = run_cli("record", f"candump:{path}", "--out", str(out), check=True)
    assert "malformed lines 2 (first: line 31: " in proc.stderr
    assert iter_log(out) is not None and sum(1 for _ in iter_log(out)) > 50


@pytest.mark.parametrize("kind", ["candump", "sim"])
def test_paced_replay_across_a_time_jump_keeps_to_the_read_timeout(tmp_path, kind) -> None:
    # A log whose clock jumps ahead (4 s here, an hour in the field) replayed with a rate:
    # read(timeout) slept through the whole jump, so `record --option rate=1` ignored
    # --duration and SIGTERM for as long.
    import time

    from sonarloc.errors import DeviceTimeoutError

    stream = list(ring_stream(duration_s=0.2))
    jump = 4.0
    late = [dataclasses.replace(r, t_s=r.t_s + jump) for r in ring_stream(duration_s=0.2)
            if r.type in ("odom", "tof")]
    path = tmp_path / ("sonar.log" if kind == "candump" else "sonar.jsonl")
    if kind == "candump":
        sim = SimModule.to_candump(stream + late, path)
        sim.run()
        sim.close()
    else:
        with LogWriter(path) as w:
            w.write_all(stream + late)
    n_before = sum(r.type in ("rig", "odom", "tof") for r in stream)
    with open_driver(f"{kind}:{path}", rate=20.0) as drv:
        got = [drv.read(timeout=1.0) for _ in range(n_before)]
        t = time.monotonic()
        with pytest.raises(DeviceTimeoutError):
            drv.read(timeout=0.05)
        assert time.monotonic() - t < 0.15  # not the 0.2 s the jump takes at rate 20
        with pytest.raises(DeviceTimeoutError):
            drv.read(timeout=0.05)
        got += list(drv.records(timeout=1.0))  # nothing lost: the rest comes when due
    assert [r.t_s for r in got if r.type != "rig"] == \
        pytest.approx([r.t_s for r in stream + late if r.type in ("odom", "tof")], abs=1e-6)


def _spiked(jump_s: float) -> list:
    """0.2 s of a ring stream, its clock jumping ``jump_s`` ahead, 0.2 s more."""
    stream = list(ring_stream(duration_s=0.2))
    return stream + [dataclasses.replace(r, t_s=r.t_s + jump_s)
                     for r in ring_stream(duration_s=0.2) if r.type in ("odom", "tof")]


@pytest.mark.parametrize("kind", ["candump", "sim"])
def test_paced_replay_does_not_wait_for_a_long_jump(tmp_path, kind) -> None:
    # A recording whose clock jumps 10 min ahead (a spike, a recorder paused): replayed at
    # rate 1, the rest of the file came 10 min later. Steps over MAX_PACED_STEP_S (5 s)
    # are not waited for; they are counted, and the times are passed on unchanged. (The
    # module protocol's 32-bit microsecond clock carries jumps up to 35 min.)
    recs = _spiked(600.0)
    path = tmp_path / ("sonar.log" if kind == "candump" else "sonar.jsonl")
    if kind == "candump":
        sim = SimModule.to_candump(recs, path)
        sim.run()
        sim.close()
    else:
        with LogWriter(path) as w:
            w.write_all(recs)
    with open_driver(f"{kind}:{path}", rate=1.0) as drv:
        got = list(drv.records(timeout=3.0))
        assert drv.counters()["time_jumps"] == 1
        assert "time jumps 1 (not waited for)" in drv.summary()
    assert [r.t_s for r in got if r.type != "rig"] == \
        pytest.approx([r.t_s for r in recs if r.type in ("odom", "tof")], abs=1e-6)


def test_serve_sim_does_not_wait_for_a_long_jump() -> None:
    # The module side (`serve-sim --log`) paces the same way; its --duration counts the
    # time it paced, so the readings after the jump are still sent.
    recs = _spiked(600.0)
    with SimModule.on_tcp(recs, rate=1.0, duration_s=1.0) as sim, \
            open_driver(sim.url) as drv:
        got = drain(sim, drv, quiet_s=0.5, limit_s=20.0)
    assert sim.pacer.jumps == 1 and sim.wait(0)
    assert len([r for r in got if r.type in ("odom", "tof")]) == \
        len([r for r in recs if r.type in ("odom", "tof")])


def test_pacer_steps() -> None:
    p = Pacer(rate=10.0, max_step_s=5.0)
    assert p.due(50.0, now=100.0) == 100.0
    assert p.due(51.0, now=0.0) == pytest.approx(100.1)
    assert p.due(51.0, now=0.0) == pytest.approx(100.1)   # asked again: the same
    assert p.due(50.999, now=0.0) == pytest.approx(100.1)  # slightly back: at once
    assert p.jumps == 0
    assert p.due(900.0, now=0.0) == pytest.approx(100.1) and p.jumps == 1   # ahead
    assert p.due(53.0, now=0.0) == pytest.approx(100.1) and p.jumps == 2    # and back
    assert p.due(float("nan"), now=0.0) == pytest.approx(100.1) and p.jumps == 3
    assert p.due(54.0, now=0.0) == pytest.approx(100.1) and p.jumps == 4    # after NaN
    assert p.due(55.0, now=0.0) == pytest.approx(100.2)
    p.shift(2.0)
    assert p.due(55.0, now=0.0) == pytest.approx(102.2)
    assert p.elapsed_s == pytest.approx(2.0)
    with pytest.raises(ValueError, match="`rate` must be positive"):
        Pacer(rate=0.0)
    with pytest.raises(ValueError, match="`max_step_s` must be positive"):
        Pacer(rate=1.0, max_step_s=0.0)


def test_a_file_of_no_candump_lines_is_an_error(tmp_path, run_cli) -> None:
    # `candump can0 > x.log` (without -L) writes another format: every line was skipped,
    # and record exited 0 with an empty log.
    path, out = tmp_path / "plain.log", tmp_path / "rec.jsonl"
    path.write_text("  can0  130   [7]  00 00 00 00 FC 85 10\n"
                    "  can0  131   [7]  00 D0 07 00 00 00 00\n")
    proc = run_cli("record", f"candump:{path}", "--out", str(out))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
    assert "no readings" in proc.stderr and "malformed lines 2 (first: line 1: " in proc.stderr
    assert "candump -L" in proc.stderr

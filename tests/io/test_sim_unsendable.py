"""A replayed log with records the wire cannot carry (a negative TOF, a sensor id beyond
255, odometry beyond the CAN range): they are skipped and counted, the rest is sent."""

from __future__ import annotations

import io
import random

import pytest
from io_streams import drain, ring_stream

from sonarloc.io.drivers import open_driver
from sonarloc.io.drivers.sim import SimModule
from sonarloc.io.logfile import LogWriter, OdomRecord, TofRecord, iter_log

BAD = [TofRecord(0.0501, 0, -5.0), TofRecord(0.0502, 300, 1000.0),
       OdomRecord(0.0503, 1e6, 0.0, 0.0)]  # 1000 km: beyond i32 0.1 mm
FAR = OdomRecord(0.0504, 1e5, 0.0, 0.0)  # 100 km: fits the serial Odom, not CAN's 13.4 km


def _stream() -> list:
    good = list(ring_stream(duration_s=0.2))
    k = next(i for i, r in enumerate(good) if r.t_s > 0.05)
    return good[:k] + BAD + [FAR] + good[k:]


@pytest.mark.parametrize("link", ["pty", "can"])
def test_module_skips_and_counts_what_the_wire_cannot_carry(link) -> None:
    # Before: the first such record ended the stream ("serve-sim: error: `tof_us` must be
    # non-negative, got -5.0"), and every reading after it was lost.
    stream = _stream()
    sent = io.StringIO()
    if link == "pty":
        sim = SimModule.on_pty(stream, rate=20.0, sent_log=LogWriter(sent))
    else:
        sim = SimModule.on_can(stream, channel=f"bad-{random.random()}", rate=20.0,
                               sent_log=LogWriter(sent))
    with sim, open_driver(sim.url) as drv:
        got = drain(sim, drv, quiet_s=0.3)
    assert sim.error is None
    bad = BAD + ([FAR] if link == "can" else [])
    good = [r for r in stream if r.type in ("odom", "tof") and r not in bad]
    assert sum(r.type in ("odom", "tof") for r in got) == len(good)
    assert got == list(iter_log(io.StringIO(sent.getvalue())))
    assert sim.stats.unsendable == len(bad)
    assert sim.stats.first_unsendable.startswith("tof at t_s 0.0501: `tof_us` must be non-neg")


def test_sim_driver_skips_and_counts_what_the_wire_cannot_carry(tmp_path) -> None:
    log = tmp_path / "in.jsonl"
    stream = _stream()
    with LogWriter(log) as w:
        w.write_all(stream)
    with open_driver(f"sim:{log}") as drv:
        got = list(drv.records(timeout=1.0))
    good = [r for r in stream if r.type in ("odom", "tof") and r not in BAD]
    assert sum(r.type in ("odom", "tof") for r in got) == len(good)
    assert "unsendable 3 (first: tof at t_s 0.0501: `tof_us` must be non-negative" in drv.summary()


def test_serve_sim_reports_what_it_skipped(run_cli, tmp_path) -> None:
    log, dump = tmp_path / "in.jsonl", tmp_path / "out.log"
    with LogWriter(log) as w:
        w.write_all(_stream())
    proc = run_cli("serve-sim", "--log", str(log), "--candump", str(dump), check=True)
    assert "4 unsendable (first: tof at t_s 0.0501: `tof_us` must be non-negative" in proc.stderr


def test_sim_driver_names_the_bad_lines_of_its_log(tmp_path, run_cli) -> None:
    # `record sim:LOG` said "good 4 ...; 3 records" of a log with a malformed line, a
    # record of unknown type and time going backwards (serve-sim --log named them).
    log, out = tmp_path / "in.jsonl", tmp_path / "rec.jsonl"
    log.write_text('{"type":"rig","sensors":[{"id":0,"x_m":0,"y_m":0,"yaw_deg":0}]}\n'
                   'not json\n'
                   '{"type":"tof","t_s":0.1,"sensor":0,"tof_us":1000.0}\n'
                   '{"type":"tof","t_s":0.05,"sensor":0,"tof_us":1000.0}\n'
                   '{"type":"bogus"}\n')
    proc = run_cli("record", f"sim:{log}", "--out", str(out), check=True)
    assert "malformed lines 1" in proc.stderr
    assert "1 malformed (first: line 2: " in proc.stderr
    assert "1 of unknown type (bogus: 1)" in proc.stderr
    assert "time went backwards 1 times (first: line 4" in proc.stderr

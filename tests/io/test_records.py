"""Between log records and protocol messages: quantization, clock unwrap, rig assembly."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from io_strategies import odom_records, rig_records, tof_records

from sonarloc.io.logfile import InitRecord, OdomRecord, RigRecord, SensorMount, TofRecord
from sonarloc.io.protocol.framing import SerialDecoder, SerialEncoder
from sonarloc.io.protocol.messages import Echo, RigMount
from sonarloc.io.protocol.records import (
    ModuleClock,
    RecordAssembler,
    messages_from_record,
    wrap_mdeg,
)

FAST = settings(max_examples=150, deadline=None)


def through(recs):
    asm = RecordAssembler()
    # flush: a reading whose time jumped by more than 1 s is held until the stream ends
    return [r for rec in recs for m in messages_from_record(rec) for r in asm.push(m)] \
        + asm.flush()


def test_quantization_of_a_reading() -> None:
    (m,) = messages_from_record(TofRecord(1.25, 3, 8522.67, 12.345))
    assert m == Echo(3, 1_250_000, 4261, False, 1234)
    assert through([TofRecord(1.25, 3, 8522.67, 12.345)]) == [TofRecord(1.25, 3, 8522.0, 12.34)]
    assert through([TofRecord(0.5, 1, None)]) == [TofRecord(0.5, 1, None)]
    assert through([TofRecord(0.5, 1, 200_000.0)]) == [TofRecord(0.5, 1, None)]  # counter overflow
    with pytest.raises(ValueError, match="tof_us"):
        messages_from_record(TofRecord(0.5, 1, -3.0))


def test_heading_wraps_to_half_open_interval() -> None:
    assert wrap_mdeg(190.0) == -170000
    assert wrap_mdeg(-180.0) == 180000 and wrap_mdeg(180.0) == 180000
    assert through([OdomRecord(2.0, 1.23456, -0.5, 370.0)]) == [OdomRecord(2.0, 1.2346, -0.5, 10.0)]


def test_init_and_truth_are_not_device_messages() -> None:
    assert messages_from_record(InitRecord(0, 0, 0, 0, 0.1, 1.0)) == []


@FAST
@given(st.lists(st.one_of(tof_records(), odom_records()), max_size=30))
def test_quantization_is_idempotent_and_ordered(recs) -> None:
    recs.sort(key=lambda r: r.t_s)
    once = through(recs)
    assert len(once) == len(recs)
    assert through(once) == once
    for a, b in zip(recs, once, strict=True):
        assert type(a) is type(b) and abs(a.t_s - b.t_s) <= 0.5e-6


@FAST
@given(rig_records())
def test_rig_round_trip_and_repeats_dropped(rig: RigRecord) -> None:
    asm = RecordAssembler()
    msgs = messages_from_record(rig)
    first = [r for m in msgs for r in asm.push(m)]
    assert len(first) == 1
    got = first[0]
    assert isinstance(got, RigRecord)
    assert [s.id for s in got.sensors] == [s.id for s in rig.sensors]
    for a, b in zip(rig.sensors, got.sensors, strict=True):
        assert abs(a.x_m - b.x_m) <= 0.5e-4 and abs(a.y_m - b.y_m) <= 0.5e-4
        assert abs((a.yaw_deg - b.yaw_deg + 180) % 360 - 180) <= 0.005 + 1e-9
    assert [r for m in msgs for r in asm.push(m)] == []  # the same rig again
    assert asm.stats.rig_repeats == 1


def test_rig_mount_without_info_is_orphan() -> None:
    asm = RecordAssembler()
    assert asm.push(RigMount(0, 1, 2, 3)) == []
    assert asm.stats.orphan_mounts == 1


def test_rig_mount_beyond_range_is_refused() -> None:
    with pytest.raises(ValueError, match="RigMount.x_dmm"):
        messages_from_record(RigRecord((SensorMount(0, 4.0, 0.0, 0.0),)))


def test_clock_unwraps_across_the_32_bit_wrap() -> None:
    clk = ModuleClock()
    assert clk.unwrap(0xFFFF_FF00) == 0xFFFF_FF00
    assert clk.unwrap(0x10) == (1 << 32) + 0x10
    assert clk.unwrap(0xFFFF_FFF0) == 0xFFFF_FFF0  # slightly out of order, before the wrap
    assert clk.unwrap(0x20) == (1 << 32) + 0x20


def test_records_survive_the_serial_wire_across_a_clock_wrap() -> None:
    recs = [TofRecord(4294.0 + 0.25 * k, k % 4, 6000.0 + 2 * k) for k in range(12)]
    enc = SerialEncoder()
    wire = b"".join(enc.encode(m) for r in recs for m in messages_from_record(r))
    asm = RecordAssembler()
    got = [r for m in SerialDecoder().feed(wire) for r in asm.push(m)]
    assert got == recs

"""CAN frames from the DBC: round trips, pairs, counters, and frames of any kind."""

from __future__ import annotations

import can
import cantools
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from io_strategies import messages

from sonarloc.io.protocol.canbus import (
    ECHO,
    ECHO_PAN,
    ODOM_POS,
    ODOM_YAW,
    CanDecoder,
    CanEncoder,
    dbc_path,
    load_dbc,
)
from sonarloc.io.protocol.messages import Echo, Odom, Start

FAST = settings(max_examples=150, deadline=None)


def test_dbc_ships_with_the_package_and_loads_in_cantools() -> None:
    db = cantools.database.load_file(dbc_path())
    names = {m.name: (m.frame_id, m.length) for m in db.messages}
    assert names["ECHO"] == (0x110, 8) and names["ODOM_POS"] == (0x120, 8)
    assert all(not m.is_extended_frame and m.length <= 8 for m in db.messages)
    assert load_dbc().get_message_by_name("RIG_MOUNT").length == 7


def test_physical_units_in_the_dbc() -> None:
    # a third-party tool decoding with scaling sees SI-ish units: 2 us counts, 0.01 deg
    enc = CanEncoder()
    pan, echo = enc.encode(Echo(5, 123456, 4261, False, -1750))
    db = load_dbc()
    assert db.decode_message(echo.arbitration_id, echo.data)["tof_us"] == 8522
    assert db.decode_message(pan.arbitration_id, pan.data)["pan_deg"] == pytest.approx(-17.5)
    pos, yaw = enc.encode(Odom(1, 15000, -20000, 90500))
    assert db.decode_message(pos.arbitration_id, pos.data)["x_m"] == pytest.approx(1.5)
    assert db.decode_message(yaw.arbitration_id, yaw.data)["yaw_deg"] == pytest.approx(90.5)


@FAST
@given(st.lists(messages(can=True), max_size=25))
def test_round_trip(msgs: list) -> None:
    enc, dec = CanEncoder(), CanDecoder()
    out = [m for f in (f for msg in msgs for f in enc.encode(msg)) for m in dec.feed(f)]
    assert out == msgs
    s = dec.stats
    assert (s.incomplete, s.seq_gaps, s.unknown, s.bad_length) == (0, 0, 0, 0)
    assert dec.pending == 0


frames = st.builds(
    lambda fid, data, err, rtr, ext: can.Message(
        arbitration_id=fid, data=None if rtr else data, is_error_frame=err, is_remote_frame=rtr,
        is_extended_id=ext, dlc=len(data), check=False),
    st.one_of(st.sampled_from([0x100, 0x101, 0x102, 0x110, 0x111, 0x120, 0x121, 0x130, 0x131,
                               0x140]), st.integers(0, 0x7FF)),
    st.binary(max_size=8), st.booleans(), st.booleans(), st.booleans())


@FAST
@given(st.lists(frames, max_size=60))
def test_any_frames_no_exception_and_every_frame_counted(fs: list[can.Message]) -> None:
    dec = CanDecoder()
    for f in fs:
        dec.feed(f)
    s = dec.stats
    assert s.frames + s.error_frames + s.unknown + s.bad_length + s.bad_value == len(fs)
    assert dec.pending <= 257


def test_pairs_missing_a_half_are_counted_incomplete() -> None:
    enc, dec = CanEncoder(), CanDecoder()
    pan, echo = enc.encode(Echo(1, 10, 20, False, 300))
    assert dec.feed(echo) == []  # the angle was lost: the reading is dropped
    pos, yaw = enc.encode(Odom(1, 2, 3, 4))
    assert dec.feed(yaw) == []
    assert dec.stats.incomplete == 2
    assert dec.feed(pos) == [] and dec.feed(yaw) == [Odom(1, 2, 3, 4)]
    # an angle for sensor 1 whose echo never came, then a new complete pair
    dec.feed(pan)
    pan2, echo2 = enc.encode(Echo(1, 30, 40, False, -5))
    assert dec.feed(pan2) == [] and dec.feed(echo2) == [Echo(1, 30, 40, False, -5)]
    assert dec.stats.incomplete == 3


def test_counters_give_gaps() -> None:
    enc, dec = CanEncoder(), CanDecoder()
    fs = [enc.encode(Echo(0, k, k))[0] for k in range(40)]
    for k, f in enumerate(fs):
        if k not in (5, 6, 20):
            dec.feed(f)
    assert (dec.stats.seq_gaps, dec.stats.frames_lost) == (2, 3)


def test_error_remote_extended_and_wrong_length() -> None:
    dec = CanDecoder()
    good = CanEncoder().encode(Start())[0]
    dec.feed(can.Message(is_error_frame=True))
    dec.feed(can.Message(arbitration_id=ECHO, is_remote_frame=True, dlc=8))
    dec.feed(can.Message(arbitration_id=ECHO, is_extended_id=True, data=bytes(8)))
    dec.feed(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=bytes(8)))
    dec.feed(can.Message(arbitration_id=ECHO, is_extended_id=False, data=bytes(7)))
    dec.feed(can.Message(arbitration_id=0x100, is_extended_id=False, data=b"\x07"))  # bad code
    assert dec.feed(good) == [Start()]
    s = dec.stats
    assert (s.error_frames, s.unknown, s.bad_length, s.bad_value, s.frames) == (1, 3, 1, 1, 1)


def test_odometry_beyond_can_range_is_refused() -> None:
    with pytest.raises(ValueError, match="Odom.x_dmm"):
        CanEncoder().encode(Odom(0, 1 << 28, 0, 0))
    with pytest.raises(ValueError, match="Odom.yaw_mdeg"):
        CanEncoder().encode(Odom(0, 0, 0, 1 << 24))


def test_frame_ids_used_by_the_codec_match_the_dbc() -> None:
    db = load_dbc()
    for name, fid in (("ECHO", ECHO), ("ECHO_PAN", ECHO_PAN), ("ODOM_POS", ODOM_POS),
                      ("ODOM_YAW", ODOM_YAW)):
        assert db.get_message_by_name(name).frame_id == fid


junk_frames = st.one_of(
    st.just(can.Message(is_error_frame=True)),
    st.builds(lambda i, d: can.Message(arbitration_id=i, data=d, is_extended_id=False),
              st.integers(0x141, 0x7FF), st.binary(max_size=8)),  # ids not in the DBC
    st.builds(lambda i, d: can.Message(arbitration_id=i, data=d, is_extended_id=True),
              st.integers(0, 0x1FFFFFFF), st.binary(max_size=8)),
    st.builds(lambda i: can.Message(arbitration_id=i, is_remote_frame=True, dlc=8,
                                    is_extended_id=False), st.sampled_from([0x110, 0x120])),
    st.builds(lambda i, n: can.Message(arbitration_id=i, data=bytes(n), is_extended_id=False),
              st.sampled_from([0x110, 0x111, 0x120, 0x121]), st.integers(0, 7)),  # too short
)


@FAST
@given(st.lists(st.tuples(st.lists(junk_frames, max_size=3), messages(can=True)), max_size=20),
       st.lists(junk_frames, max_size=3))
def test_messages_among_junk_frames_all_recovered(pieces, tail) -> None:
    enc, dec = CanEncoder(), CanDecoder()
    stream = []
    for junk, msg in pieces:
        frames = enc.encode(msg)
        stream += junk[:1] + frames[:1] + junk[1:] + frames[1:]  # junk inside pairs too
    stream += tail
    out = [m for f in stream for m in dec.feed(f)]
    assert out == [m for _, m in pieces]
    s = dec.stats
    n_junk = sum(len(j) for j, _ in pieces) + len(tail)
    assert s.error_frames + s.unknown + s.bad_length == n_junk
    assert s.incomplete == 0 and s.seq_gaps == 0

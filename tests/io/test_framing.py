"""Serial framing: CRC, round trips, resync after garbage, counters, bounded memory."""

from __future__ import annotations

import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from io_strategies import messages

from sonarloc.io.protocol.framing import (
    ECHO,
    MAX_PACKET,
    SerialDecoder,
    SerialEncoder,
    crc16,
    encode_packet,
    encode_raw,
)
from sonarloc.io.protocol.messages import Echo, Firing, Odom, RigInfo

FAST = settings(max_examples=150, deadline=None)


def crc16_reference(data: bytes) -> int:
    """Bit-by-bit CRC-16/CCITT-FALSE, written from the algorithm's definition."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else crc << 1
            crc &= 0xFFFF
    return crc


def test_crc_check_value() -> None:
    assert crc16(b"123456789") == 0x29B1  # the catalogued check value of CRC-16/CCITT-FALSE
    assert crc16_reference(b"123456789") == 0x29B1


@FAST
@given(st.binary(max_size=300))
def test_crc_matches_bitwise_reference(data: bytes) -> None:
    assert crc16(data) == crc16_reference(data)


def test_wire_format_of_an_echo() -> None:
    # Echo of sensor 3, ping at 1000 us, TOF 4261 counts (8522 us), seq 7 (docs/PROTOCOL.md)
    pkt = encode_packet(Echo(3, 1000, 4261), seq=7)
    body = bytes([15, 0x10, 7, 0, 3, 0, 0xA5, 0x10, 0, 0, 0xE8, 0x03, 0, 0])
    crc = crc16_reference(body)
    assert pkt == b"\xfa\xfb" + body + bytes([crc >> 8, crc & 0xFF])
    assert pkt.hex(" ").upper().endswith("E8 03 00 00 3C 62")  # as printed in PROTOCOL.md


@FAST
@given(st.lists(messages(), max_size=20), st.integers(0, 0xFFFF))
def test_round_trip(msgs: list, first_seq: int) -> None:
    enc = SerialEncoder(first_seq)
    dec = SerialDecoder()
    frames = dec.feed_frames(b"".join(enc.encode(m) for m in msgs))
    assert [f.message for f in frames] == msgs
    assert [f.seq for f in frames] == [(first_seq + k) & 0xFFFF for k in range(len(msgs))]
    assert dec.stats.seq_gaps == 0 and dec.stats.crc_errors == 0 and dec.pending == 0


def _check_accounting(dec: SerialDecoder) -> None:
    s = dec.stats
    assert s.bytes_in == s.bytes_framed + s.bytes_skipped + dec.pending
    assert dec.pending < MAX_PACKET


@FAST
@given(st.lists(st.binary(max_size=600), max_size=8))
def test_any_bytes_no_exception_bounded(chunks: list[bytes]) -> None:
    dec = SerialDecoder()
    for chunk in chunks:
        dec.feed(chunk)
        _check_accounting(dec)
    dec.flush()
    _check_accounting(dec)
    assert dec.pending == 0


sync_heavy_garbage = st.lists(
    st.one_of(st.binary(max_size=40), st.just(b"\xfa\xfb"), st.just(b"\xfa"),
              st.builds(lambda n: b"\xfa\xfb" + bytes([n]), st.integers(0, 255))),
    max_size=6).map(b"".join)


@FAST
@given(st.lists(st.tuples(sync_heavy_garbage, messages()), min_size=1, max_size=15),
       sync_heavy_garbage, st.randoms(use_true_random=False))
def test_packets_in_garbage_all_recovered(pieces, tail, rnd: random.Random) -> None:
    enc = SerialEncoder()
    stream = b"".join(g + enc.encode(m) for g, m in pieces) + tail
    sent = [m for _, m in pieces]
    dec = SerialDecoder()
    got = []
    pos = 0
    while pos < len(stream):  # random chunking, as a serial port delivers it
        step = rnd.randint(1, 64)
        got += dec.feed(stream[pos:pos + step])
        _check_accounting(dec)
        pos += step
    got += [f.message for f in dec.flush()]
    assert got == sent
    assert dec.stats.frames == len(sent)
    assert dec.stats.seq_gaps == 0
    assert dec.stats.bytes_framed == sum(len(encode_packet(m, 0)) for m in sent)
    _check_accounting(dec)


def test_flush_recovers_packet_behind_a_false_header() -> None:
    good = encode_packet(Echo(1, 5, 6), 0)
    dec = SerialDecoder()
    # a false header announcing 255 bytes swallows the good packet until the stream ends
    assert dec.feed(b"\xfa\xfb\xff" + good) == []
    assert [f.message for f in dec.flush()] == [Echo(1, 5, 6)]
    assert dec.stats.bytes_skipped == 3 and dec.pending == 0


def test_corruption_counts_crc_errors_and_gaps() -> None:
    rng = random.Random(5)
    enc = SerialEncoder()
    packets = [enc.encode(Echo(k % 16, 1000 * k, 2000 + k)) for k in range(1000)]
    corrupt = set(rng.sample(range(1, 999), 50))
    stream = bytearray()
    for k, p in enumerate(packets):
        p = bytearray(p)
        if k in corrupt:
            p[rng.randrange(3, len(p))] ^= 1 << rng.randrange(8)  # one flipped bit past the sync
        stream += p
    dec = SerialDecoder()
    got = dec.feed(bytes(stream)) + [f.message for f in dec.flush()]
    assert len(got) == 1000 - len(corrupt)
    assert [m.ping_time_us // 1000 for m in got] == [k for k in range(1000) if k not in corrupt]
    assert dec.stats.crc_errors >= len(corrupt)  # a flipped length byte may add false candidates
    runs = sum(1 for k in sorted(corrupt) if k - 1 not in corrupt)
    assert dec.stats.seq_gaps == runs
    assert dec.stats.frames_lost == len(corrupt)
    _check_accounting(dec)


def test_sequence_wrap_is_not_a_gap_and_restart_is_counted() -> None:
    dec = SerialDecoder()
    dec.feed(encode_packet(Echo(0, 0, 0), 0xFFFE) + encode_packet(Echo(0, 0, 0), 0xFFFF)
             + encode_packet(Echo(0, 0, 0), 0))
    assert dec.stats.seq_gaps == 0
    dec.feed(encode_packet(Echo(0, 0, 0), 0))  # sender restarted
    assert dec.stats.seq_backwards == 1 and dec.stats.seq_gaps == 0


def test_unknown_type_short_payload_and_extension() -> None:
    dec = SerialDecoder()
    payload = encode_packet(Echo(2, 3, 4), 0)[6:-2]
    msgs = dec.feed(encode_raw(0x7E, 0, b"xyz")              # unknown type
                    + encode_raw(ECHO, 1, payload[:-1])        # too short
                    + encode_raw(ECHO, 2, payload + b"\x99\x98")  # newer firmware: longer
                    + encode_raw(0x83, 3, bytes([5, 2, 50, 0, 1, 0, 0, 0])))  # group 5 of 2
    assert msgs == [Echo(2, 3, 4)]
    s = dec.stats
    assert (s.unknown, s.bad_length, s.bad_value, s.frames) == (1, 1, 1, 1)
    assert s.unknown_ids == {0x7E: 1}
    assert s.crc_errors == 0 and s.seq_gaps == 0


def test_message_field_ranges_are_checked() -> None:
    with pytest.raises(ValueError, match="Echo.tof_counts"):
        Echo(0, 0, 70000)
    with pytest.raises(ValueError, match="Odom.time_us"):
        Odom(-1, 0, 0, 0)
    with pytest.raises(ValueError, match="RigInfo.n_sensors"):
        RigInfo(0, 34300, 0)
    with pytest.raises(ValueError, match="group"):
        Firing(3, 2, 10, 0)

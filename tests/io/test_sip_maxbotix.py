"""Real-device formats: Pioneer ARCOS packets and MaxBotix ASCII ranges."""

from __future__ import annotations

import random

from hypothesis import given, settings
from hypothesis import strategies as st

from sonarloc.io.protocol.maxbotix import MaxbotixDecoder, encode_range
from sonarloc.io.protocol.sip import (
    ENABLE,
    OPEN,
    SONAR,
    SYNC0,
    SYNC1,
    SYNC2,
    ArcosDecoder,
    ArcosPacket,
    StandardSip,
    client_command,
    frame,
    sip_checksum,
)

FAST = settings(max_examples=150, deadline=None)


def test_handshake_packets_from_the_manual() -> None:
    # the SYNC packets as printed in the Pioneer operations manuals
    assert client_command(SYNC0) == bytes.fromhex("FAFB03000000")
    assert client_command(SYNC1) == bytes.fromhex("FAFB03010001")
    assert client_command(SYNC2) == bytes.fromhex("FAFB03020002")
    assert client_command(OPEN) == client_command(SYNC1)


def test_checksum_pairs_high_byte_first_and_xors_an_odd_byte() -> None:
    assert sip_checksum(bytes([0x04, 0x3B, 0x01, 0x00])) == 0x043B + 0x0100
    assert sip_checksum(bytes([0x1C, 0x3B, 0x01])) == 0x1C3B ^ 0x01
    assert sip_checksum(bytes([0xFF, 0xFF, 0x00, 0x02])) == 0x0001  # 16-bit wrap
    assert client_command(ENABLE, 1) == bytes.fromhex("FAFB06043B0100053B")
    assert client_command(SONAR, -1)[3:6] == bytes([SONAR, 0x1B, 0x01])


sips = st.builds(
    StandardSip, st.booleans(), st.integers(0, 0xFFFF), st.integers(0, 0xFFFF),
    st.integers(-0x8000, 0x7FFF), st.integers(-0x8000, 0x7FFF), st.integers(-0x8000, 0x7FFF),
    st.integers(0, 255), st.integers(0, 0xFFFF), st.integers(-0x8000, 0x7FFF),
    st.integers(0, 0xFFFF), st.integers(0, 255),
    st.lists(st.tuples(st.integers(0, 31), st.integers(0, 0xFFFF)), max_size=32).map(tuple),
    st.binary(max_size=12))


@FAST
@given(st.lists(st.tuples(st.binary(max_size=30), sips), min_size=1, max_size=8),
       st.binary(max_size=30), st.randoms(use_true_random=False))
def test_sips_in_garbage_all_recovered(pieces, tail, rnd: random.Random) -> None:
    stream = b"".join(g + s.encode() for g, s in pieces) + tail
    dec = ArcosDecoder()
    got: list = []
    pos = 0
    while pos < len(stream):
        step = rnd.randint(1, 50)
        got += dec.feed(stream[pos:pos + step])
        pos += step
    got += dec.flush()
    sips_got = [p for p in got if isinstance(p, StandardSip)]
    assert sips_got == [s for _, s in pieces]
    s = dec.stats
    assert s.bytes_in == s.bytes_framed + s.bytes_skipped and dec.pending == 0


@FAST
@given(st.lists(st.binary(max_size=400), max_size=6))
def test_arcos_any_bytes(chunks) -> None:
    dec = ArcosDecoder()
    for c in chunks:
        dec.feed(c)
        assert dec.pending < 258
    dec.flush()
    s = dec.stats
    assert s.bytes_in == s.bytes_framed + s.bytes_skipped


def test_short_sip_and_other_packets() -> None:
    dec = ArcosDecoder()
    short = frame(bytes([0x32, 1, 2, 3]))
    config = frame(bytes([0x20]) + b"Pioneer\0")
    out = dec.feed(short + config)
    assert out == [ArcosPacket(0x20, b"Pioneer\0")]
    assert dec.stats.bad_length == 1 and dec.stats.frames == 1


def test_client_side_decoder_sees_commands() -> None:
    dec = ArcosDecoder(parse_sip=False)
    out = dec.feed(client_command(SYNC0) + client_command(SONAR, 1))
    assert out == [ArcosPacket(SYNC0, b""), ArcosPacket(SONAR, bytes([0x3B, 1, 0]))]


def test_maxbotix_frames() -> None:
    dec = MaxbotixDecoder()
    assert dec.feed(b"R0300\rR12") == [300]
    assert dec.feed(b"34\rR5000\r") == [1234, 5000]
    assert dec.feed(b"R12\rR123456\rxxR045\r") == [45]
    s = dec.stats
    assert (s.frames, s.bad_length) == (4, 2)
    assert encode_range(45, 3) == b"R045\r"


@FAST
@given(st.lists(st.tuples(st.binary(max_size=12), st.integers(0, 9999)), max_size=20),
       st.binary(max_size=10), st.randoms(use_true_random=False))
def test_maxbotix_ranges_in_garbage(pieces, tail, rnd: random.Random) -> None:
    # garbage must not itself end in a partial frame that would swallow the next "R"
    stream = b"".join(g.replace(b"R", b"r") + b"\r" + encode_range(v) for g, v in pieces) + tail
    dec = MaxbotixDecoder()
    got: list[int] = []
    pos = 0
    while pos < len(stream):
        step = rnd.randint(1, 7)
        got += dec.feed(stream[pos:pos + step])
        assert dec.pending <= 6
        pos += step
    got += dec.flush()
    expect = [v for _, v in pieces]
    assert got[:len(expect)] == expect
    s = dec.stats
    assert s.bytes_in == s.bytes_framed + s.bytes_skipped

"""Serial framing of the module protocol: ARCOS-style packets with a CRC-16.

A packet (docs/PROTOCOL.md section 2)::

    0xFA 0xFB | N | TYPE | SEQ (u16 LE) | PAYLOAD (N - 5 bytes) | CRC (u16, high byte first)

``N`` counts the bytes after itself (type, sequence, payload, CRC), so 5 <= N <= 255.
The CRC is CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no bit
reflection, no final XOR; check value 0x29B1 for ``b"123456789"``) over
``N, TYPE, SEQ, PAYLOAD``. Payload fields are little-endian. A receiver ignores
payload bytes past the fields it knows (newer firmware may append fields) and
counts shorter payloads as ``bad_length``.

:class:`SerialDecoder` is pure: bytes in, messages out (like pyserial's
``Packetizer.data_received``). Its buffer never holds more than one maximal packet
between calls. After a failed CRC it advances by one byte only, so a good packet
that starts inside a false one is still found.
"""

from __future__ import annotations

import binascii
import struct
from collections.abc import Callable
from typing import NamedTuple

from sonarloc.io.protocol.messages import (
    Ack,
    DecoderStats,
    Echo,
    Firing,
    Message,
    Odom,
    RequestRig,
    RigInfo,
    RigMount,
    SeqTracker,
    Settings,
    Start,
    Stop,
)

SYNC = b"\xfa\xfb"
HEADER_LEN = 3  # sync + N
MIN_N = 5  # type + seq + crc
MAX_N = 0xFF
MAX_PACKET = HEADER_LEN + MAX_N
MAX_PAYLOAD = MAX_N - MIN_N

CRC_INIT = 0xFFFF

# type codes
ECHO, ODOM, RIG_INFO, RIG_MOUNT, ACK = 0x10, 0x20, 0x30, 0x31, 0x40
START, STOP, REQUEST_RIG, FIRING, SETTINGS = 0x80, 0x81, 0x82, 0x83, 0x84

FLAG_NO_ECHO = 0x01
FLAG_PAN_VALID = 0x02

_ECHO = struct.Struct("<BBHhI")
_ODOM = struct.Struct("<Iiii")
_RIG_INFO = struct.Struct("<IHB")
_RIG_MOUNT = struct.Struct("<Bhhh")
_ACK = struct.Struct("<BHB")
_FIRING = struct.Struct("<BBHI")
_SETTINGS = struct.Struct("<BbHH")
_HEAD = struct.Struct("<BBBBH")  # sync0 sync1 N type seq


def crc16(data: bytes | bytearray | memoryview, init: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (``binascii.crc_hqx`` with initial value 0xFFFF).

    Examples
    --------
    >>> hex(crc16(b"123456789"))
    '0x29b1'
    """
    return binascii.crc_hqx(data, init)


def type_code(msg: Message) -> int:
    """The serial type code of a message."""
    code = _TYPE_OF.get(type(msg))
    if code is None:
        raise ValueError(f"not a protocol message: {msg!r}")
    return code


def encode_payload(msg: Message) -> tuple[int, bytes]:
    """(type code, payload bytes) of a message."""
    if isinstance(msg, Echo):
        flags = (FLAG_NO_ECHO if msg.no_echo else 0) | (
            FLAG_PAN_VALID if msg.pan_cdeg is not None else 0)
        return ECHO, _ECHO.pack(msg.sensor, flags, 0 if msg.no_echo else msg.tof_counts,
                                msg.pan_cdeg or 0, msg.ping_time_us)
    if isinstance(msg, Odom):
        return ODOM, _ODOM.pack(msg.time_us, msg.x_dmm, msg.y_dmm, msg.yaw_mdeg)
    if isinstance(msg, RigInfo):
        return RIG_INFO, _RIG_INFO.pack(msg.time_us, msg.c_cmps, msg.n_sensors)
    if isinstance(msg, RigMount):
        return RIG_MOUNT, _RIG_MOUNT.pack(msg.sensor, msg.x_dmm, msg.y_dmm, msg.yaw_cdeg)
    if isinstance(msg, Ack):
        return ACK, _ACK.pack(msg.command, msg.command_seq, msg.status)
    if isinstance(msg, Firing):
        return FIRING, _FIRING.pack(msg.group, msg.n_groups, msg.period_ms, msg.mask)
    if isinstance(msg, Settings):
        return SETTINGS, _SETTINGS.pack(msg.sensor, msg.gain_db, msg.threshold_mv,
                                        msg.blanking_us)
    return type_code(msg), b""


def encode_raw(type_: int, seq: int, payload: bytes) -> bytes:
    """A packet of any type code and payload (for tests and forward-compatible senders)."""
    if not 0 <= type_ <= 0xFF:
        raise ValueError(f"`type_` must be in [0, 255], got {type_}")
    if not 0 <= seq <= 0xFFFF:
        raise ValueError(f"`seq` must be in [0, 65535], got {seq}")
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload must be at most {MAX_PAYLOAD} bytes, got {len(payload)}")
    body = struct.pack("<BBH", len(payload) + MIN_N, type_, seq) + payload
    crc = crc16(body)
    return SYNC + body + bytes((crc >> 8, crc & 0xFF))


def encode_packet(msg: Message, seq: int) -> bytes:
    """One framed packet carrying ``msg`` with sequence number ``seq`` (0..65535)."""
    code, payload = encode_payload(msg)
    return encode_raw(code, seq, payload)


class SerialEncoder:
    """Frames messages with a running 16-bit sequence number (one per sender)."""

    def __init__(self, first_seq: int = 0):
        self.seq = first_seq & 0xFFFF

    def encode(self, msg: Message) -> bytes:
        out = encode_packet(msg, self.seq)
        self.seq = (self.seq + 1) & 0xFFFF
        return out


def _echo(p: bytes) -> Echo:
    sensor, flags, counts, pan, t = _ECHO.unpack_from(p)
    return Echo(sensor, t, counts, bool(flags & FLAG_NO_ECHO),
                pan if flags & FLAG_PAN_VALID else None)


def _parsers() -> dict[int, tuple[int, Callable[[bytes], Message]]]:
    return {
        ECHO: (_ECHO.size, _echo),
        ODOM: (_ODOM.size, lambda p: Odom(*_ODOM.unpack_from(p))),
        RIG_INFO: (_RIG_INFO.size, lambda p: RigInfo(*_RIG_INFO.unpack_from(p))),
        RIG_MOUNT: (_RIG_MOUNT.size, lambda p: RigMount(*_RIG_MOUNT.unpack_from(p))),
        ACK: (_ACK.size, lambda p: Ack(*_ACK.unpack_from(p))),
        START: (0, lambda p: Start()),
        STOP: (0, lambda p: Stop()),
        REQUEST_RIG: (0, lambda p: RequestRig()),
        FIRING: (_FIRING.size, lambda p: Firing(*_FIRING.unpack_from(p))),
        SETTINGS: (_SETTINGS.size, lambda p: Settings(*_SETTINGS.unpack_from(p))),
    }


_PARSERS = _parsers()
_TYPE_OF: dict[type, int] = {Echo: ECHO, Odom: ODOM, RigInfo: RIG_INFO, RigMount: RIG_MOUNT,
                             Ack: ACK, Start: START, Stop: STOP, RequestRig: REQUEST_RIG,
                             Firing: FIRING, Settings: SETTINGS}


def cut_packets(buf: bytearray, stats: DecoderStats, *, final: bool, min_count: int,
                checksum_ok: Callable[[bytearray, int, int], bool]) -> list[bytes]:
    """Cut the complete, checksum-valid ``0xFA 0xFB | COUNT | ... | CHECKSUM`` packets
    off the front of ``buf`` (the ARCOS framing shared by this protocol and Pioneer SIP).

    Parameters
    ----------
    buf : the receive buffer; consumed bytes are deleted from it. At most one partial
        packet (or a lone trailing 0xFA) stays behind unless ``final``.
    stats : counters; updated: ``crc_errors``, ``bytes_framed``, ``bytes_skipped``.
    final : end of stream: give up on a packet that cannot complete.
    min_count : smallest valid COUNT; a smaller one is a false sync.
    checksum_ok : ``checksum_ok(buf, start, end)`` for the packet ``buf[start:end]``
        (``end`` past its two checksum bytes).

    Returns
    -------
    The bytes after COUNT up to the checksum of each good packet, in stream order.
    After a bad checksum the scan advances one byte only, so a good packet starting
    inside a false one is still found.
    """
    out: list[bytes] = []
    n, pos, skipped = len(buf), 0, 0
    while True:
        i = buf.find(SYNC, pos)
        if i < 0:
            keep = 1 if (not final and n > pos and buf[n - 1] == SYNC[0]) else 0
            skipped += n - keep - pos
            pos = n - keep
            break
        skipped += i - pos
        pos = i
        if n - pos < HEADER_LEN:
            if final:
                skipped += n - pos
                pos = n
            break
        count = buf[pos + 2]
        if count < min_count:
            skipped += 1
            pos += 1
            continue
        end = pos + HEADER_LEN + count
        if end > n:
            if final:  # this packet will never complete: resync past its sync
                skipped += 1
                pos += 1
                continue
            break
        if not checksum_ok(buf, pos, end):
            stats.crc_errors += 1
            skipped += 1
            pos += 1
            continue
        out.append(bytes(buf[pos + HEADER_LEN:end - 2]))
        stats.bytes_framed += end - pos
        pos = end
    stats.bytes_skipped += skipped
    if pos:
        del buf[:pos]
    return out


def _crc_ok(buf: bytearray, start: int, end: int) -> bool:
    return binascii.crc_hqx(buf[start + 2:end - 2], CRC_INIT) == (buf[end - 2] << 8 | buf[end - 1])


class SerialFrame(NamedTuple):
    """A good packet: its sequence number, type code and decoded message."""

    seq: int
    type: int
    message: Message


class SerialDecoder:
    """Bytes in, messages out, with bounded memory, resync and counters.

    Feed any chunking of the stream to :meth:`feed`; call :meth:`flush` at the end of
    a stream (EOF, disconnect) to give up on a packet that will never complete and
    recover any good packets behind it. Invariant, checked by the tests:
    ``bytes_in == bytes_framed + bytes_skipped + pending``.
    """

    def __init__(self) -> None:
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._seq = SeqTracker(0x10000)

    @property
    def pending(self) -> int:
        """Bytes held back waiting for the rest of a packet (at most ``MAX_PACKET - 1``)."""
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        """Decode as much of the stream as possible; returns the messages, in order."""
        return [f.message for f in self.feed_frames(data)]

    def feed_frames(self, data: bytes | bytearray | memoryview) -> list[SerialFrame]:
        """Like :meth:`feed` but keeps each message's sequence number and type code."""
        self.stats.bytes_in += len(data)
        self._buf += data
        return self._scan(final=False)

    def flush(self) -> list[SerialFrame]:
        """End of stream: drop any incomplete packet, keep good packets behind it."""
        return self._scan(final=True)

    def reset_sequence(self) -> None:
        """Forget the last sequence number (a new connection to a restarted sender)."""
        self._seq.reset()

    def _scan(self, final: bool) -> list[SerialFrame]:
        stats = self.stats
        out: list[SerialFrame] = []
        for body in cut_packets(self._buf, stats, final=final, min_count=MIN_N,
                                checksum_ok=_crc_ok):
            type_, seq, payload = body[0], body[1] | body[2] << 8, body[3:]
            self._seq.see(seq, stats)
            parser = _PARSERS.get(type_)
            if parser is None:
                stats.note_unknown(type_)
                continue
            size, parse = parser
            if len(payload) < size:
                stats.bad_length += 1
                continue
            try:
                msg = parse(payload)
            except ValueError:  # e.g. a firing group beyond the group count
                stats.bad_value += 1
                continue
            stats.frames += 1
            out.append(SerialFrame(seq, type_, msg))
        return out

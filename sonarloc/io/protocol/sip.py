"""Pioneer ARCOS packets: the standard server information packet (SIP) and client commands.

Written from the published ARCOS/P2OS packet description (Pioneer operations
manuals): every packet is ::

    0xFA 0xFB | COUNT | DATA (COUNT - 2 bytes) | CHECKSUM (2 bytes, high byte first)

``COUNT`` is the number of bytes after itself, checksum included. The checksum is
the 16-bit sum of the data taken as big-endian byte pairs, with a trailing odd byte
XORed into the low byte. Integer fields are little-endian.

The standard SIP (type 0x32 stopped, 0x33 moving), the robot sends it every
100 ms after OPEN::

    TYPE u8 | XPOS u16 | YPOS u16 | THPOS i16 | LVEL i16 | RVEL i16 | BATTERY u8 |
    STALL_BUMPERS u16 | CONTROL i16 | FLAGS u16 | COMPASS u8 | SONAR_COUNT u8 |
    SONAR_COUNT x (NUMBER u8, RANGE u16) | further fields (grip, I/O, ...)

``XPOS``/``YPOS`` are wheel-encoder positions in mm whose low 15 bits wrap;
``THPOS`` is in 2 pi / 4096 rad units; sonar ranges are in mm (times the robot's
RangeConvFactor). Client commands: ``COMMAND u8 [ARGTYPE u8, ARG u16]`` with
argument type 0x3B (positive integer), 0x1B (negative integer, magnitude sent)
or 0x2B (string).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from sonarloc.io.protocol.messages import DecoderStats

SYNC = b"\xfa\xfb"
MIN_COUNT = 3  # one data byte + checksum
MAX_PACKET = 3 + 0xFF

SIP_STOPPED, SIP_MOVING = 0x32, 0x33

# client commands
SYNC0, SYNC1, SYNC2 = 0, 1, 2
PULSE, OPEN, CLOSE, ENABLE, SONAR = 0, 1, 2, 4, 28
ARG_INT, ARG_NINT, ARG_STR = 0x3B, 0x1B, 0x2B

_FIXED = struct.Struct("<HHhhhBHhHBB")
_SONAR = struct.Struct("<BH")


def sip_checksum(data: bytes | bytearray | memoryview) -> int:
    """The ARCOS 16-bit checksum of the data bytes (after COUNT, before the checksum)."""
    n = len(data)
    c = 0
    for i in range(0, n - 1, 2):
        c = (c + (data[i] << 8 | data[i + 1])) & 0xFFFF
    if n & 1:
        c ^= data[n - 1]
    return c


def frame(data: bytes) -> bytes:
    """An ARCOS packet around ``data``."""
    if not 1 <= len(data) <= 0xFF - 2:
        raise ValueError(f"ARCOS packet data must be 1..253 bytes, got {len(data)}")
    c = sip_checksum(data)
    return SYNC + bytes((len(data) + 2,)) + data + bytes((c >> 8, c & 0xFF))


def client_command(command: int, arg: int | str | None = None) -> bytes:
    """A client command packet (e.g. ``client_command(OPEN)``, ``client_command(SONAR, 1)``)."""
    if not 0 <= command <= 0xFF:
        raise ValueError(f"`command` must be in [0, 255], got {command}")
    if arg is None:
        return frame(bytes((command,)))
    if isinstance(arg, str):
        raw = arg.encode("ascii")
        return frame(bytes((command, ARG_STR, len(raw))) + raw)
    if not -0xFFFF <= arg <= 0xFFFF:
        raise ValueError(f"`arg` must fit 16 bits, got {arg}")
    return frame(bytes((command, ARG_INT if arg >= 0 else ARG_NINT)) + struct.pack("<H", abs(arg)))


@dataclass(frozen=True)
class StandardSip:
    """The fields of a standard SIP, raw (robot units)."""

    moving: bool
    xpos: int
    ypos: int
    thpos: int
    lvel: int
    rvel: int
    battery: int
    stall_bumpers: int
    control: int
    flags: int
    compass: int
    sonars: tuple[tuple[int, int], ...]  # (number, range)
    tail: bytes = b""  # fields after the sonar readings, uninterpreted

    def encode(self) -> bytes:
        """The packet (for simulated robots and tests)."""
        body = bytes((SIP_MOVING if self.moving else SIP_STOPPED,)) + _FIXED.pack(
            self.xpos & 0xFFFF, self.ypos & 0xFFFF, self.thpos, self.lvel, self.rvel,
            self.battery, self.stall_bumpers, self.control, self.flags, self.compass,
            len(self.sonars))
        body += b"".join(_SONAR.pack(n, r) for n, r in self.sonars) + self.tail
        return frame(body)


@dataclass(frozen=True)
class ArcosPacket:
    """Any other good ARCOS packet: its type (first data byte) and the rest."""

    type: int
    data: bytes


def parse_standard_sip(data: bytes) -> StandardSip | None:
    """Fields of a standard SIP from its data bytes (type first); None if too short."""
    if len(data) < 1 + _FIXED.size:
        return None
    (x, y, th, lv, rv, batt, sb, ctrl, flags, compass, count) = _FIXED.unpack_from(data, 1)
    start = 1 + _FIXED.size
    end = start + count * _SONAR.size
    if len(data) < end:
        return None
    sonars = tuple(_SONAR.unpack_from(data, start + k * _SONAR.size) for k in range(count))
    return StandardSip(data[0] == SIP_MOVING, x, y, th, lv, rv, batt, sb, ctrl, flags,
                       compass, sonars, bytes(data[end:]))


class ArcosDecoder:
    """Bytes in, packets out (StandardSip or ArcosPacket), with the same counters and
    resync rules as :class:`~sonarloc.io.protocol.framing.SerialDecoder`.

    Parameters
    ----------
    parse_sip : decode packets of type 0x32/0x33 as :class:`StandardSip` (robot -> client
        stream); False decodes every packet as :class:`ArcosPacket` (client -> robot).
    """

    def __init__(self, parse_sip: bool = True) -> None:
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._parse_sip = parse_sip

    @property
    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[StandardSip | ArcosPacket]:
        self.stats.bytes_in += len(data)
        self._buf += data
        return self._scan(final=False)

    def flush(self) -> list[StandardSip | ArcosPacket]:
        return self._scan(final=True)

    def _scan(self, final: bool) -> list[StandardSip | ArcosPacket]:
        buf, stats = self._buf, self.stats
        out: list[StandardSip | ArcosPacket] = []
        n, pos, skipped = len(buf), 0, 0
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                keep = 1 if (not final and n > pos and buf[n - 1] == 0xFA) else 0
                skipped += n - keep - pos
                pos = n - keep
                break
            skipped += i - pos
            pos = i
            if n - pos < 3:
                if final:
                    skipped += n - pos
                    pos = n
                break
            count = buf[pos + 2]
            if count < MIN_COUNT:
                skipped += 1
                pos += 1
                continue
            end = pos + 3 + count
            if end > n:
                if final:
                    skipped += 1
                    pos += 1
                    continue
                break
            data = bytes(buf[pos + 3:end - 2])
            if sip_checksum(data) != (buf[end - 2] << 8 | buf[end - 1]):
                stats.crc_errors += 1
                skipped += 1
                pos += 1
                continue
            stats.bytes_framed += end - pos
            pos = end
            if self._parse_sip and data[0] in (SIP_STOPPED, SIP_MOVING):
                sip = parse_standard_sip(data)
                if sip is None:
                    stats.bad_length += 1
                    continue
                stats.frames += 1
                out.append(sip)
                continue
            stats.frames += 1  # config, encoder, I/O packets, sync echoes, commands
            out.append(ArcosPacket(data[0], data[1:]))
        stats.bytes_skipped += skipped
        if pos:
            del buf[:pos]
        return out

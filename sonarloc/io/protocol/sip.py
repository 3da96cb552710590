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

import math
import struct
from dataclasses import dataclass

from sonarloc.io.logfile import OdomRecord, Record, RigRecord, SensorMount, TofRecord
from sonarloc.io.protocol.framing import SYNC, cut_packets
from sonarloc.io.protocol.messages import DecoderStats

MIN_COUNT = 3  # one data byte + checksum
MAX_PACKET = 3 + 0xFF

SIP_STOPPED, SIP_MOVING = 0x32, 0x33

# client commands
SYNC0, SYNC1, SYNC2 = 0, 1, 2
PULSE, OPEN, CLOSE, ENABLE, SONAR = 0, 1, 2, 4, 28
ARG_INT, ARG_NINT, ARG_STR = 0x3B, 0x1B, 0x2B

_FIXED = struct.Struct("<HHhhhBHhHBB")
_SONAR = struct.Struct("<BH")


def _checksum_ok(buf: bytearray, start: int, end: int) -> bool:
    return sip_checksum(buf[start + 3:end - 2]) == (buf[end - 2] << 8 | buf[end - 1])


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
        stats = self.stats
        out: list[StandardSip | ArcosPacket] = []
        for data in cut_packets(self._buf, stats, final=final, min_count=MIN_COUNT,
                                checksum_ok=_checksum_ok):
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
        return out


# ---------------------------------------------------------------------------------------
# standard SIP -> log records
# ---------------------------------------------------------------------------------------
P3DX_SONAR_MM_DEG: tuple[tuple[int, int, int, int], ...] = (
    (0, 69, 136, 90), (1, 114, 119, 50), (2, 148, 78, 30), (3, 166, 27, 10),
    (4, 166, -27, -10), (5, 148, -78, -30), (6, 114, -119, -50), (7, 69, -136, -90),
    (8, -157, -136, -90), (9, -203, -119, -130), (10, -237, -78, -150), (11, -255, -27, -170),
    (12, -255, 27, 170), (13, -237, 78, 150), (14, -203, 119, 130), (15, -157, 136, 90),
)
"""Sonar of a Pioneer 3-DX (front and rear rings): id, x mm, y mm, heading deg
(the robot parameter file ``p3dx.p`` of ARIA)."""


def p3dx_rig(speed_of_sound_mps: float = 343.0) -> RigRecord:
    """The rig record of a Pioneer 3-DX's 16 sonar."""
    return RigRecord(tuple(SensorMount(i, x / 1000.0, y / 1000.0, float(h))
                           for i, x, y, h in P3DX_SONAR_MM_DEG), speed_of_sound_mps)


def _signed15(v: int) -> int:
    v &= 0x7FFF
    return v - 0x8000 if v >= 0x4000 else v


class SipConverter:
    """Standard SIPs -> OdomRecord + TofRecords (pure; keeps the position unwrap state).

    Parameters
    ----------
    dist_conv : mm per XPOS/YPOS unit (DistConvFactor; 1.0 on a P3-DX).
    angle_conv_rad : rad per THPOS unit (AngleConvFactor; 2 pi / 4096).
    range_conv : mm per sonar RANGE unit (RangeConvFactor; 1.0 on a P3-DX).
    max_range_mm : a range at or beyond this is no echo.
    speed_of_sound_mps : to turn ranges into times of flight.
    """

    def __init__(self, *, dist_conv: float = 1.0, angle_conv_rad: float = 2 * math.pi / 4096,
                 range_conv: float = 1.0, max_range_mm: float = 5000.0,
                 speed_of_sound_mps: float = 343.0):
        for name, v in (("dist_conv", dist_conv), ("angle_conv_rad", angle_conv_rad),
                        ("range_conv", range_conv), ("max_range_mm", max_range_mm),
                        ("speed_of_sound_mps", speed_of_sound_mps)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"`{name}` must be positive, got {v!r}")
        self.dist_conv, self.angle_conv_rad, self.range_conv = dist_conv, angle_conv_rad, range_conv
        self.max_range_mm, self.c = max_range_mm, speed_of_sound_mps
        self._raw: tuple[int, int] | None = None
        self._xy = (0, 0)  # unwrapped encoder units

    def records(self, sip: StandardSip, t_s: float) -> list[Record]:
        raw = (sip.xpos & 0x7FFF, sip.ypos & 0x7FFF)
        if self._raw is None:
            self._xy = (_signed15(raw[0]), _signed15(raw[1]))
        else:
            self._xy = (self._xy[0] + _signed15(raw[0] - self._raw[0]),
                        self._xy[1] + _signed15(raw[1] - self._raw[1]))
        self._raw = raw
        yaw = math.degrees(sip.thpos * self.angle_conv_rad)
        yaw = (yaw + 180.0) % 360.0 - 180.0
        out: list[Record] = [OdomRecord(t_s, self._xy[0] * self.dist_conv / 1000.0,
                                        self._xy[1] * self.dist_conv / 1000.0, yaw)]
        for number, rng in sip.sonars:
            r_mm = rng * self.range_conv
            tof = None if r_mm >= self.max_range_mm else 2.0 * r_mm / 1000.0 / self.c * 1e6
            out.append(TofRecord(t_s, number, tof))
        return out

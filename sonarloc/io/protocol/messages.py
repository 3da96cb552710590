"""Messages of the sonarloc module protocol, in wire units (docs/PROTOCOL.md).

The same messages travel as serial packets (:mod:`.framing`) and as classic CAN
frames (:mod:`.canbus`). Fields are the integers that go on the wire, so an
encode/decode round trip is exact; :mod:`.records` converts to and from the
SI log records of :mod:`sonarloc.io.logfile`.

Wire units: time in microseconds of the module's free-running 32-bit clock
(``_us``), time of flight in 2 us counts, positions in 0.1 mm (``_dmm``), odometry
heading in millidegrees (``_mdeg``), pan and mount angles in centidegrees
(``_cdeg``), speed of sound in cm/s (``_cmps``).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

U8 = (0, 0xFF)
U16 = (0, 0xFFFF)
U32 = (0, 0xFFFF_FFFF)
I8 = (-0x80, 0x7F)
I16 = (-0x8000, 0x7FFF)
I32 = (-0x8000_0000, 0x7FFF_FFFF)

ALL_SENSORS = 0xFF
"""``sensor`` value of :class:`Settings` that addresses every transducer."""


def _check(owner: str, name: str, value: Any, bounds: tuple[int, int]) -> None:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError(f"{owner}.{name} must be an integer, got {value!r}")
    lo, hi = bounds
    if not lo <= value <= hi:
        raise ValueError(f"{owner}.{name} must be in [{lo}, {hi}], got {value}")


class _Checked:
    """Range-checks every integer field against ``_bounds`` after construction."""

    __slots__ = ()
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {}

    def __post_init__(self) -> None:
        owner = type(self).__name__
        for name, bounds in self._bounds.items():
            value = getattr(self, name)
            if value is None and name == "pan_cdeg":
                continue
            _check(owner, name, value, bounds)


@dataclass(frozen=True, slots=True)
class Echo(_Checked):
    """One ping of one transducer (module -> host).

    ``tof_counts`` is the first-echo time of flight in 2 us counts (meaningless and
    sent as 0 when ``no_echo``); ``pan_cdeg`` the angle of a panning transducer
    relative to its mount, None for a fixed one.
    """

    sensor: int
    ping_time_us: int
    tof_counts: int
    no_echo: bool = False
    pan_cdeg: int | None = None
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "sensor": U8, "ping_time_us": U32, "tof_counts": U16, "pan_cdeg": I16}


@dataclass(frozen=True, slots=True)
class Odom(_Checked):
    """Wheel-odometry pose of ``base_link`` in ``odom`` at ``time_us`` (module -> host)."""

    time_us: int
    x_dmm: int
    y_dmm: int
    yaw_mdeg: int
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "time_us": U32, "x_dmm": I32, "y_dmm": I32, "yaw_mdeg": I32}


@dataclass(frozen=True, slots=True)
class RigInfo(_Checked):
    """Start of a rig description: ``n_sensors`` :class:`RigMount` messages follow."""

    time_us: int
    c_cmps: int
    n_sensors: int
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "time_us": U32, "c_cmps": U16, "n_sensors": (1, 0xFF)}


@dataclass(frozen=True, slots=True)
class RigMount(_Checked):
    """Mount pose of one transducer in ``base_link``."""

    sensor: int
    x_dmm: int
    y_dmm: int
    yaw_cdeg: int
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "sensor": U8, "x_dmm": I16, "y_dmm": I16, "yaw_cdeg": I16}


ACK_OK = 0
ACK_UNSUPPORTED = 1
ACK_BAD_ARGUMENT = 2


@dataclass(frozen=True, slots=True)
class Ack(_Checked):
    """The module's answer to a command: its serial type code, its sequence number
    (0 on CAN, which has none) and a status (``ACK_OK``, ``ACK_UNSUPPORTED``,
    ``ACK_BAD_ARGUMENT``)."""

    command: int
    command_seq: int
    status: int
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "command": U8, "command_seq": U16, "status": U8}


@dataclass(frozen=True, slots=True)
class Start:
    """Start (or resume) firing and reporting (host -> module)."""


@dataclass(frozen=True, slots=True)
class Stop:
    """Stop firing; the module stays connected and answers commands."""


@dataclass(frozen=True, slots=True)
class RequestRig:
    """Ask the module to send its rig description (RigInfo + RigMounts) now."""


@dataclass(frozen=True, slots=True)
class Firing(_Checked):
    """One group of a firing pattern: the transducers in ``mask`` (bit i = sensor i)
    fire together; the module fires group 0, 1, ..., ``n_groups - 1`` in turn, one
    group every ``period_ms``."""

    group: int
    n_groups: int
    period_ms: int
    mask: int
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "group": U8, "n_groups": (1, 0xFF), "period_ms": U16, "mask": U32}

    def __post_init__(self) -> None:
        _Checked.__post_init__(self)
        if self.group >= self.n_groups:
            raise ValueError(f"Firing.group must be < n_groups={self.n_groups}, got {self.group}")


@dataclass(frozen=True, slots=True)
class Settings(_Checked):
    """Receiver settings of one transducer (``sensor`` = ``ALL_SENSORS`` for all):
    gain in dB, detection threshold in mV, blanking after the burst in us."""

    sensor: int
    gain_db: int
    threshold_mv: int
    blanking_us: int
    _bounds: ClassVar[dict[str, tuple[int, int]]] = {
        "sensor": U8, "gain_db": I8, "threshold_mv": U16, "blanking_us": U16}


Message = Echo | Odom | RigInfo | RigMount | Ack | Start | Stop | RequestRig | Firing | Settings
MESSAGE_TYPES: tuple[type, ...] = (Echo, Odom, RigInfo, RigMount, Ack, Start, Stop, RequestRig,
                                   Firing, Settings)
COMMAND_TYPES: tuple[type, ...] = (Start, Stop, RequestRig, Firing, Settings)


def message_fields(msg: Message) -> dict[str, Any]:
    """The fields of a message as a dict (for printing and JSON)."""
    return {f.name: getattr(msg, f.name) for f in fields(msg)}


@dataclass
class DecoderStats:
    """Counters every decoder keeps (serial, CAN, Pioneer SIP, MaxBotix ASCII).

    ``frames``: good frames decoded into messages. ``crc_errors``: frames whose
    CRC/checksum failed. ``bytes_skipped``: input bytes that were not part of a good
    frame (garbage, resync). ``seq_gaps``/``frames_lost``: discontinuities of the
    sender's sequence numbers and how many frames they imply were lost.
    ``unknown``: good frames of unknown type or CAN id. ``bad_length``: good frames
    of a known type with the wrong length; ``bad_value`` those whose fields are out
of range (a firing group beyond the group count). ``error_frames``: CAN error frames.
    ``incomplete``: multi-frame CAN messages missing a part. ``bytes_in`` counts
    every byte fed to a byte decoder; ``bytes_framed`` those in good frames.
    """

    frames: int = 0
    crc_errors: int = 0
    bytes_skipped: int = 0
    seq_gaps: int = 0
    frames_lost: int = 0
    seq_backwards: int = 0
    unknown: int = 0
    bad_length: int = 0
    bad_value: int = 0
    error_frames: int = 0
    incomplete: int = 0
    bytes_in: int = 0
    bytes_framed: int = 0
    unknown_ids: Counter[int] = field(default_factory=Counter)

    MAX_UNKNOWN_IDS: ClassVar[int] = 64  # distinct unknown ids/types remembered

    def note_unknown(self, key: int) -> None:
        self.unknown += 1
        if key in self.unknown_ids or len(self.unknown_ids) < self.MAX_UNKNOWN_IDS:
            self.unknown_ids[key] += 1

    def as_dict(self) -> dict[str, int]:
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name != "unknown_ids"}

    def summary(self) -> str:
        """One line: good / CRC / skipped / gaps, then whatever else is non-zero."""
        parts = [f"good {self.frames}", f"crc {self.crc_errors}",
                 f"skipped {self.bytes_skipped} B",
                 f"gaps {self.seq_gaps} (lost {self.frames_lost})"]
        for name in ("seq_backwards", "unknown", "bad_length", "bad_value", "error_frames",
                     "incomplete"):
            value = getattr(self, name)
            if value:
                parts.append(f"{name.replace('_', ' ')} {value}")
        return ", ".join(parts)


class SeqTracker:
    """Counts gaps in a modular sequence number into a :class:`DecoderStats`."""

    __slots__ = ("modulus", "last")

    def __init__(self, modulus: int):
        self.modulus = modulus
        self.last: int | None = None

    def see(self, seq: int, stats: DecoderStats) -> None:
        last, self.last = self.last, seq
        if last is None:
            return
        d = (seq - last - 1) % self.modulus
        if d == 0:
            return
        if d < self.modulus // 2:
            stats.seq_gaps += 1
            stats.frames_lost += d
        else:  # repeated or older number: sender restarted, or reordering
            stats.seq_backwards += 1

    def reset(self) -> None:
        self.last = None

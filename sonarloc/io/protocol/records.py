"""Between log records (SI, :mod:`sonarloc.io.logfile`) and protocol messages (wire units).

:func:`messages_from_record` quantizes a record the way the module reports it:
time to the microsecond of a 32-bit clock, TOF to 2 us counts (a count that does
not fit 16 bits is reported as no echo, as the module's counter times out), poses
to 0.1 mm and 0.001 deg, pan and mount angles to 0.01 deg. :class:`RecordAssembler`
turns the message stream back into records: it unwraps the module clock, collects a
rig description and drops repeats of an unchanged rig. Passing records through both
gives exactly what a host receives, which is how ``serve-sim --sent-log`` writes
what it sent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sonarloc.io.logfile import (
    OdomRecord,
    Record,
    RigRecord,
    SensorMount,
    TofRecord,
)
from sonarloc.io.protocol.messages import Echo, Message, Odom, RigInfo, RigMount

CLOCK_MODULUS = 1 << 32
COUNT_US = 2.0
MAX_COUNTS = 0xFFFF


def time_us(t_s: float) -> int:
    """Module clock reading (32-bit microseconds, wrapping) of a time in seconds."""
    if not math.isfinite(t_s):
        raise ValueError(f"`t_s` must be finite, got {t_s!r}")
    return round(t_s * 1e6) % CLOCK_MODULUS


def wrap_mdeg(yaw_deg: float) -> int:
    """Heading in millidegrees, wrapped to (-180000, 180000]."""
    m = (round(yaw_deg * 1000.0) + 180000) % 360000 - 180000
    return 180000 if m == -180000 else m


def echo_message(rec: TofRecord) -> Echo:
    """The Echo a module reports for a TOF record."""
    tof = rec.tof_us
    counts, no_echo = 0, True
    if tof is not None and math.isfinite(tof):
        if tof < 0:
            raise ValueError(f"`tof_us` must be non-negative, got {tof!r}")
        counts, no_echo = round(tof / COUNT_US), False
        if counts > MAX_COUNTS:
            counts, no_echo = 0, True
    pan = None if rec.pan_deg is None else round(rec.pan_deg * 100.0)
    return Echo(rec.sensor, time_us(rec.t_s), counts, no_echo, pan)


def odom_message(rec: OdomRecord) -> Odom:
    return Odom(time_us(rec.t_s), round(rec.x_m * 1e4), round(rec.y_m * 1e4),
                wrap_mdeg(rec.yaw_deg))


def rig_messages(rec: RigRecord) -> list[Message]:
    """RigInfo followed by one RigMount per sensor."""
    out: list[Message] = [RigInfo(time_us(rec.t_s), round(rec.speed_of_sound_mps * 100.0),
                                  len(rec.sensors))]
    for s in rec.sensors:
        yaw = (s.yaw_deg + 180.0) % 360.0 - 180.0
        out.append(RigMount(s.id, round(s.x_m * 1e4), round(s.y_m * 1e4), round(yaw * 100.0)))
    return out


def messages_from_record(rec: Record) -> list[Message]:
    """The messages a module sends for a record (none for ``init`` and ``truth``)."""
    if isinstance(rec, TofRecord):
        return [echo_message(rec)]
    if isinstance(rec, OdomRecord):
        return [odom_message(rec)]
    if isinstance(rec, RigRecord):
        return rig_messages(rec)
    return []


class ModuleClock:
    """Unwraps the module's 32-bit microsecond clock into a monotonic count.

    Each reading is placed within half a wrap (35 min) of the previous one, so
    messages slightly out of order and the wrap every 71.6 min are both handled.
    The first reading is taken as is (no offset), so a stream that starts at
    clock 0 gives ``t_s`` equal to the simulator's.

    A step back of more than :attr:`RESTART_US` (1 s) is a restarted module, whose
    clock began again at zero: it is counted (``restarts``) and the clock re-based so
    that time goes on from the last reading, by the host's time between the two
    readings when the caller gives arrival times (``host_s``), else by nothing.
    """

    RESTART_US = 1_000_000

    __slots__ = ("last", "offset", "restarts", "_host_last")

    def __init__(self) -> None:
        self.last: int | None = None
        self.offset = 0  # added to readings of a restarted module
        self.restarts = 0
        self._host_last: float | None = None

    def unwrap(self, raw: int, host_s: float | None = None) -> int:
        """The unwrapped count of clock reading ``raw``, which arrived at the host's time
        ``host_s`` (seconds on any clock of the host; None if unknown)."""
        if self.last is None:
            self.last = raw
        else:
            d = (raw + self.offset - self.last + CLOCK_MODULUS // 2) % CLOCK_MODULUS \
                - CLOCK_MODULUS // 2
            if d < -self.RESTART_US:
                self.restarts += 1
                gap = 0
                if host_s is not None and self._host_last is not None:
                    gap = max(round((host_s - self._host_last) * 1e6), 0)
                self.offset += gap - d
                d = gap
            self.last += d
        if host_s is not None:
            self._host_last = host_s
        return self.last


@dataclass
class AssemblerStats:
    rigs: int = 0
    rig_repeats: int = 0
    orphan_mounts: int = 0
    other: int = 0  # acks and commands: not records


class RecordAssembler:
    """Messages in, log records out (TofRecord, OdomRecord, RigRecord)."""

    def __init__(self) -> None:
        self.clock = ModuleClock()
        self.stats = AssemblerStats()
        self._info: RigInfo | None = None
        self._mounts: dict[int, RigMount] = {}
        self.rig: RigRecord | None = None

    def push(self, msg: Message, host_s: float | None = None) -> list[Record]:
        """The records completed by ``msg``, which arrived at the host's time ``host_s``
        (seconds on any one clock of the host; it times the outage of a restarted
        module, see :class:`ModuleClock`)."""
        if isinstance(msg, Echo):
            t = self.clock.unwrap(msg.ping_time_us, host_s) / 1e6
            tof = None if msg.no_echo else msg.tof_counts * COUNT_US
            pan = None if msg.pan_cdeg is None else msg.pan_cdeg / 100.0
            return [TofRecord(t, msg.sensor, tof, pan)]
        if isinstance(msg, Odom):
            return [OdomRecord(self.clock.unwrap(msg.time_us, host_s) / 1e6, msg.x_dmm / 1e4,
                               msg.y_dmm / 1e4, msg.yaw_mdeg / 1000.0)]
        if isinstance(msg, RigInfo):
            self._info, self._mounts = msg, {}
            return []
        if isinstance(msg, RigMount):
            if self._info is None:
                self.stats.orphan_mounts += 1
                return []
            self._mounts[msg.sensor] = msg
            if len(self._mounts) < self._info.n_sensors:
                return []
            return self._finish_rig(self._info, host_s)
        self.stats.other += 1
        return []

    def _finish_rig(self, info: RigInfo, host_s: float | None) -> list[Record]:
        mounts = tuple(SensorMount(m.sensor, m.x_dmm / 1e4, m.y_dmm / 1e4, m.yaw_cdeg / 100.0)
                       for m in self._mounts.values())
        self._info, self._mounts = None, {}
        rig = RigRecord(mounts, info.c_cmps / 100.0,
                        self.clock.unwrap(info.time_us, host_s) / 1e6)
        if self.rig is not None and (self.rig.sensors, self.rig.speed_of_sound_mps) == (
                rig.sensors, rig.speed_of_sound_mps):
            self.stats.rig_repeats += 1
            return []
        self.rig = rig
        self.stats.rigs += 1
        return [rig]

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
from dataclasses import dataclass, replace

from sonarloc.io.logfile import (
    OdomRecord,
    Record,
    RigRecord,
    SensorMount,
    TofRecord,
)
from sonarloc.io.protocol.messages import Echo, Message, Odom, RigInfo, RigMount

CLOCK_MODULUS = 1 << 32
_HALF_WRAP = CLOCK_MODULUS // 2
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

    A reading more than :attr:`JUMP_US` (1 s) before or after the last one is held
    (:attr:`pending`) until the next reading says which time is right:

    * the next one follows it (is at most 1 s before it, and nearer to it than to the
      reading before the jump): the jump was real and is kept. A jump forward: the
      module's clock moved on (a pause); a jump back: a restarted module, whose clock
      began again at zero, counted (``restarts``) and re-based so that time goes on
      from the last reading, by the host's time between the two readings when the
      caller gives arrival times (``host_s``), else by nothing;
    * else the held reading alone was wrong (a corrupted or spiked time): it is
      dropped and counted (``spikes``), and the clock goes on from the reading
      before it, so one bad time costs that one reading, not the rest of the log.

    After each :meth:`unwrap`, :attr:`pending` says whether that reading is held and
    :attr:`verdict` what became of the one held before it (True kept, False dropped,
    None: none was held). :meth:`flush` keeps a reading still held at the end of the
    stream (nothing contradicts it).
    """

    JUMP_US = 1_000_000
    RESTART_US = JUMP_US  # a step back of more than this is a restart (if the next follows)

    __slots__ = ("last", "offset", "restarts", "spikes", "pending", "verdict", "_host_last",
                 "_held")

    def __init__(self) -> None:
        self.last: int | None = None
        self.offset = 0  # added to readings of a restarted module
        self.restarts = 0
        self.spikes = 0
        self.pending = False
        self.verdict: bool | None = None
        self._host_last: float | None = None
        self._held: tuple[int, int, bool] | None = None  # (last, offset, restart) if kept

    @staticmethod
    def _step(raw: int, last: int, offset: int) -> int:
        """Signed microseconds from ``last`` to ``raw`` (within half a wrap)."""
        return (raw + offset - last + _HALF_WRAP) % CLOCK_MODULUS - _HALF_WRAP

    def unwrap(self, raw: int, host_s: float | None = None) -> int:
        """The unwrapped count of clock reading ``raw``, which arrived at the host's time
        ``host_s`` (seconds on any clock of the host; None if unknown). With
        :attr:`pending` set, the count is provisional (see the class docstring)."""
        self.verdict = None
        if self.last is None:
            self.last, self.pending, self._host_last = raw, False, host_s
            return raw
        if self._held is not None:
            last, offset, _ = self._held
            d_old = self._step(raw, self.last, self.offset)
            d_new = self._step(raw, last, offset)
            self.verdict = d_new >= -self.JUMP_US and (d_old < -self.JUMP_US or d_new < d_old)
            self._settle(self._held, self.verdict)
        d = self._step(raw, self.last, self.offset)
        self.pending = abs(d) > self.JUMP_US
        if not self.pending:
            self.last += d
            self._host_last = host_s
            return self.last
        if d > 0:
            self._held = (self.last + d, self.offset, False)
        else:
            gap = 0
            if host_s is not None and self._host_last is not None:
                gap = max(round((host_s - self._host_last) * 1e6), 0)
            self._held = (self.last + gap, self.offset + gap - d, True)
        self._host_last = host_s
        return self._held[0]

    def flush(self) -> bool | None:
        """End of stream: a reading still held is kept (True); None if none was."""
        self.verdict = None if self._held is None else True
        if self._held is not None:
            self._settle(self._held, True)
        self.pending = False
        return self.verdict

    def peek(self, raw: int) -> int:
        """The count of ``raw`` without moving the clock: that of the last reading if
        ``raw`` is more than :attr:`JUMP_US` from it (the time of a rig description,
        which must not be lost to a held time)."""
        if self.last is None:
            return raw
        d = self._step(raw, self.last, self.offset)
        return self.last + d if abs(d) <= self.JUMP_US else self.last

    def _settle(self, held: tuple[int, int, bool], keep: bool) -> None:
        if keep:
            self.last, self.offset, restart = held
            self.restarts += restart
        else:
            self.spikes += 1
        self._held = None


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
        self._held: Record | None = None  # a reading whose time jumped (see ModuleClock)
        self._odom_restarts = 0  # clock.restarts when the last odom record came out

    def push(self, msg: Message, host_s: float | None = None) -> list[Record]:
        """The records completed by ``msg``, which arrived at the host's time ``host_s``
        (seconds on any one clock of the host; it times the outage of a restarted
        module, see :class:`ModuleClock`).

        A reading whose time jumped by more than a second is held back until the next
        reading confirms it (it then comes out first) or shows it was a spike (it is
        dropped, counted in ``clock.spikes``); :meth:`flush` releases it at the end."""
        if isinstance(msg, Echo):
            t = self.clock.unwrap(msg.ping_time_us, host_s) / 1e6
            tof = None if msg.no_echo else msg.tof_counts * COUNT_US
            pan = None if msg.pan_cdeg is None else msg.pan_cdeg / 100.0
            return self._reading(TofRecord(t, msg.sensor, tof, pan))
        if isinstance(msg, Odom):
            t = self.clock.unwrap(msg.time_us, host_s) / 1e6
            return self._reading(OdomRecord(t, msg.x_dmm / 1e4, msg.y_dmm / 1e4,
                                            msg.yaw_mdeg / 1000.0))
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
            return self._finish_rig(self._info)
        self.stats.other += 1
        return []

    def flush(self) -> list[Record]:
        """End of stream: the reading still held back, kept (nothing contradicts its time)."""
        self.clock.flush()
        held, self._held = self._held, None
        return [] if held is None else self._mark_reset([held])

    def _reading(self, rec: Record) -> list[Record]:
        """``rec``, whose time the clock just placed, after the reading held back before it
        if this one confirmed that one's time; held back itself if its time jumped."""
        held, self._held = self._held, None
        out = [held] if held is not None and self.clock.verdict else []
        if self.clock.pending:
            self._held = rec
            return self._mark_reset(out)
        out.append(rec)
        return self._mark_reset(out)

    def _mark_reset(self, out: list[Record]) -> list[Record]:
        """``out`` with the first odom record after a module restart flagged ``reset``:
        a restarted module's odometry begins again (at zero), a new odometry frame that
        must not be differenced against the pose before the restart."""
        restarts = self.clock.restarts
        if restarts == self._odom_restarts:
            return out
        for k, rec in enumerate(out):
            if isinstance(rec, OdomRecord):
                out[k] = replace(rec, reset=True)
                self._odom_restarts = restarts
                break
        return out

    def _finish_rig(self, info: RigInfo) -> list[Record]:
        mounts = tuple(SensorMount(m.sensor, m.x_dmm / 1e4, m.y_dmm / 1e4, m.yaw_cdeg / 100.0)
                       for m in self._mounts.values())
        self._info, self._mounts = None, {}
        # a rig is never held back: its time comes from the clock without moving it
        rig = RigRecord(mounts, info.c_cmps / 100.0, self.clock.peek(info.time_us) / 1e6)
        if self.rig is not None and (self.rig.sensors, self.rig.speed_of_sound_mps) == (
                rig.sensors, rig.speed_of_sound_mps):
            self.stats.rig_repeats += 1
            return []
        self.rig = rig
        self.stats.rigs += 1
        return [rig]

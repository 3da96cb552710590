"""The module protocol as classic CAN frames, described by ``sonarloc/data/sonarloc.dbc``.

Frames are encoded and decoded with cantools from the DBC shipped in the package
(docs/PROTOCOL.md section 3). Most messages are one 8-byte frame; two need a pair:

* an :class:`Echo` of a panning transducer is an ``ECHO_PAN`` frame followed by its
  ``ECHO`` frame (same sensor, 4-bit counter and ping time);
* an :class:`Odom` is ``ODOM_POS`` followed by ``ODOM_YAW`` (same 8-bit counter).

:class:`CanDecoder` is pure: frames in, messages out. It skips and counts error
frames, remote frames and unknown ids (``unknown``), frames of a known id with the
wrong length (``bad_length``) and pairs missing a part (``incomplete``); the
rolling counters give sequence gaps. Its state is two small dicts bounded by the
number of sensor ids.
"""

from __future__ import annotations

import functools
from importlib import resources
from typing import Any, cast

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage

from sonarloc.io.protocol.framing import REQUEST_RIG, START, STOP
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

COMMAND, FIRING, SETTINGS = 0x100, 0x101, 0x102
ECHO, ECHO_PAN, ODOM_POS, ODOM_YAW = 0x110, 0x111, 0x120, 0x121
RIG_INFO, RIG_MOUNT, ACK = 0x130, 0x131, 0x140

ODOM_XY_BOUNDS = (-(1 << 27), (1 << 27) - 1)  # 28-bit signed, 0.1 mm
ODOM_YAW_BOUNDS = (-(1 << 23), (1 << 23) - 1)  # 24-bit signed, millidegrees

_COMMAND_CODES: dict[type, int] = {Start: START, Stop: STOP, RequestRig: REQUEST_RIG}
_COMMANDS: dict[int, Message] = {START: Start(), STOP: Stop(), REQUEST_RIG: RequestRig()}


def dbc_path() -> str:
    """Filesystem path of the DBC file shipped with the package."""
    return str(resources.files("sonarloc") / "data" / "sonarloc.dbc")


@functools.lru_cache(maxsize=1)
def load_dbc() -> Database:
    """The protocol's cantools database (loaded once)."""
    text = (resources.files("sonarloc") / "data" / "sonarloc.dbc").read_text(encoding="utf-8")
    db = cantools.database.load_string(text, database_format="dbc")
    if not isinstance(db, Database):
        raise TypeError(f"{dbc_path()} did not load as a CAN database")
    return db


def _frame(defn: DbcMessage, values: dict[str, int]) -> can.Message:
    return can.Message(arbitration_id=defn.frame_id, is_extended_id=False,
                       data=defn.encode(values, scaling=False, strict=False, padding=False))


def _in(owner: str, name: str, value: int, bounds: tuple[int, int]) -> None:
    if not bounds[0] <= value <= bounds[1]:
        raise ValueError(f"{owner}.{name} must be in [{bounds[0]}, {bounds[1]}] to fit a CAN "
                         f"frame, got {value}")


class CanEncoder:
    """Messages -> CAN frames, with the rolling counters of one sender."""

    def __init__(self) -> None:
        db = load_dbc()
        self._defs = {m.frame_id: m for m in db.messages}
        self._echo_counter = 0
        self._odom_counter = 0

    def encode(self, msg: Message) -> list[can.Message]:
        """The frame(s) carrying ``msg`` (two for a panned Echo or an Odom)."""
        d = self._defs
        if isinstance(msg, Echo):
            c = self._echo_counter
            self._echo_counter = (c + 1) & 0xF
            echo = _frame(d[ECHO], {
                "sensor": msg.sensor, "no_echo": int(msg.no_echo),
                "pan_valid": int(msg.pan_cdeg is not None), "counter": c,
                "tof_us": 0 if msg.no_echo else msg.tof_counts,
                "ping_time_us": msg.ping_time_us})
            if msg.pan_cdeg is None:
                return [echo]
            pan = _frame(d[ECHO_PAN], {"sensor": msg.sensor, "counter": c,
                                       "pan_deg": msg.pan_cdeg,
                                       "ping_time_us": msg.ping_time_us})
            return [pan, echo]
        if isinstance(msg, Odom):
            _in("Odom", "x_dmm", msg.x_dmm, ODOM_XY_BOUNDS)
            _in("Odom", "y_dmm", msg.y_dmm, ODOM_XY_BOUNDS)
            _in("Odom", "yaw_mdeg", msg.yaw_mdeg, ODOM_YAW_BOUNDS)
            c = self._odom_counter
            self._odom_counter = (c + 1) & 0xFF
            return [_frame(d[ODOM_POS], {"x_m": msg.x_dmm, "y_m": msg.y_dmm, "counter": c}),
                    _frame(d[ODOM_YAW], {"yaw_deg": msg.yaw_mdeg, "counter": c,
                                         "time_us": msg.time_us})]
        if isinstance(msg, RigInfo):
            return [_frame(d[RIG_INFO], {"time_us": msg.time_us,
                                         "speed_of_sound_mps": msg.c_cmps,
                                         "n_sensors": msg.n_sensors})]
        if isinstance(msg, RigMount):
            return [_frame(d[RIG_MOUNT], {"sensor": msg.sensor, "x_m": msg.x_dmm,
                                          "y_m": msg.y_dmm, "yaw_deg": msg.yaw_cdeg})]
        if isinstance(msg, Ack):
            return [_frame(d[ACK], {"command": msg.command, "command_seq": msg.command_seq,
                                    "status": msg.status})]
        if isinstance(msg, Firing):
            return [_frame(d[FIRING], {"group": msg.group, "n_groups": msg.n_groups,
                                       "period_ms": msg.period_ms, "mask": msg.mask})]
        if isinstance(msg, Settings):
            return [_frame(d[SETTINGS], {"sensor": msg.sensor, "gain_db": msg.gain_db,
                                         "threshold_mv": msg.threshold_mv,
                                         "blanking_us": msg.blanking_us})]
        code = _COMMAND_CODES.get(type(msg))
        if code is None:
            raise ValueError(f"not a protocol message: {msg!r}")
        return [_frame(d[COMMAND], {"command": code})]


class CanDecoder:
    """CAN frames in, messages out, with counters (see the module docstring)."""

    def __init__(self) -> None:
        db = load_dbc()
        self._defs: dict[int, DbcMessage] = {m.frame_id: m for m in db.messages}
        self.stats = DecoderStats()
        self._pans: dict[int, tuple[int, int, int]] = {}  # sensor -> (counter, time, pan)
        self._pos: tuple[int, int, int] | None = None  # (counter, x, y)
        self._echo_seq = SeqTracker(16)
        self._odom_seq = SeqTracker(256)

    @property
    def pending(self) -> int:
        """First halves of pairs held back waiting for their second frame."""
        return len(self._pans) + (self._pos is not None)

    def feed(self, frame: can.Message) -> list[Message]:
        """Decode one frame; returns zero or one message (a list, like the serial decoder)."""
        stats = self.stats
        if frame.is_error_frame:
            stats.error_frames += 1
            return []
        fid = frame.arbitration_id
        defn = self._defs.get(fid)
        if defn is None or frame.is_extended_id or frame.is_remote_frame:
            stats.note_unknown(fid)
            return []
        data = bytes(frame.data or b"")
        if len(data) != defn.length:
            stats.bad_length += 1
            return []
        v = cast(dict[str, Any], defn.decode(data, decode_choices=False, scaling=False))
        try:
            msg = self._message(fid, v)
        except ValueError:
            stats.bad_value += 1
            return []
        stats.frames += 1
        return [] if msg is None else [msg]

    def _message(self, fid: int, v: dict[str, Any]) -> Message | None:
        stats = self.stats
        if fid == ECHO:
            self._echo_seq.see(v["counter"], stats)
            pan = None
            if v["pan_valid"]:
                pending = self._pans.pop(v["sensor"], None)
                if pending is None or pending[:2] != (v["counter"], v["ping_time_us"]):
                    stats.incomplete += 1  # a panned echo without its angle is useless
                    return None
                pan = pending[2]
            return Echo(v["sensor"], v["ping_time_us"], v["tof_us"], bool(v["no_echo"]), pan)
        if fid == ECHO_PAN:
            if self._pans.pop(v["sensor"], None) is not None:
                stats.incomplete += 1  # the previous angle never got its echo
            self._pans[v["sensor"]] = (v["counter"], v["ping_time_us"], v["pan_deg"])
            return None
        if fid == ODOM_POS:
            if self._pos is not None:
                stats.incomplete += 1
            self._pos = (v["counter"], v["x_m"], v["y_m"])
            return None
        if fid == ODOM_YAW:
            pos, self._pos = self._pos, None
            self._odom_seq.see(v["counter"], stats)
            if pos is None or pos[0] != v["counter"]:
                stats.incomplete += 1
                return None
            return Odom(v["time_us"], pos[1], pos[2], v["yaw_deg"])
        if fid == RIG_INFO:
            return RigInfo(v["time_us"], v["speed_of_sound_mps"], v["n_sensors"])
        if fid == RIG_MOUNT:
            return RigMount(v["sensor"], v["x_m"], v["y_m"], v["yaw_deg"])
        if fid == ACK:
            return Ack(v["command"], v["command_seq"], v["status"])
        if fid == FIRING:
            return Firing(v["group"], v["n_groups"], v["period_ms"], v["mask"])
        if fid == SETTINGS:
            return Settings(v["sensor"], v["gain_db"], v["threshold_mv"], v["blanking_us"])
        if fid == COMMAND:
            cmd = _COMMANDS.get(v["command"])
            if cmd is None:
                raise ValueError(f"unknown command code {v['command']}")
            return cmd
        raise ValueError(f"no decoder for frame id {fid:#x}")  # DBC and code out of step

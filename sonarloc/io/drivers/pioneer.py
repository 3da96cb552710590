"""Pioneer robots (ARCOS/P2OS firmware): sonar and odometry from standard SIPs.

``pioneer:/dev/ttyS0`` (or ``pioneer:socket://127.0.0.1:8101`` for a simulator that
serves the robot over TCP). On every (re)connect the driver runs the ARCOS
handshake (SYNC0, SYNC1, SYNC2 echoed by the robot), sends OPEN and SONAR 1 to
start the server information packets, and then keeps the robot's watchdog fed
with PULSE. Each standard SIP becomes an ``odom`` record and one ``tof`` record
per new sonar reading (:class:`~sonarloc.io.protocol.sip.SipConverter`), stamped
with the host's clock since the driver opened. The rig defaults to the 16 sonar of
a Pioneer 3-DX.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from sonarloc.errors import DeviceError
from sonarloc.io.drivers.port import PortDriver
from sonarloc.io.logfile import RigRecord
from sonarloc.io.protocol.messages import DecoderStats
from sonarloc.io.protocol.sip import (
    CLOSE,
    OPEN,
    PULSE,
    SONAR,
    SYNC0,
    SYNC1,
    SYNC2,
    ArcosDecoder,
    ArcosPacket,
    SipConverter,
    StandardSip,
    client_command,
    p3dx_rig,
)

CONVERTER_OPTIONS = ("dist_conv", "angle_conv_rad", "range_conv", "max_range_mm",
                     "speed_of_sound_mps")
"""The :class:`SipConverter` settings a PioneerDriver also takes as keyword arguments."""

MAX_SEEN = 4096  # bytes of a handshake step kept for the SIP decoder


class PioneerDriver(PortDriver):
    """Reads a Pioneer robot's SIPs.

    Parameters
    ----------
    url : serial device or pyserial URL of the robot.
    rig : the sonar mounts: a RigRecord or a rig JSON file (default
        :func:`~sonarloc.io.protocol.sip.p3dx_rig`).
    handshake : run SYNC0/1/2 + OPEN on connect (False: the robot already streams).
    handshake_timeout_s : per SYNC step.
    pulse_s : watchdog keep-alive period (ARCOS stops the robot after ~2 s of silence).
    converter : :class:`SipConverter` options (``dist_conv``, ``range_conv``,
        ``max_range_mm``, ``speed_of_sound_mps``, ``angle_conv_rad``); each may also be a
        keyword argument of its own.
    """

    scheme = "pioneer"
    default_baudrate = 9600

    def __init__(self, url: str, *, rig: RigRecord | str | Path | None = None,
                 handshake: bool = True, handshake_timeout_s: float = 1.0, pulse_s: float = 1.0,
                 converter: dict[str, Any] | None = None, **kwargs: Any):
        # the converter's settings also come one by one, as `sonarloc record pioneer:PORT
        # --option range_conv=0.268` gives them
        conv = {**(converter or {}),
                **{key: kwargs.pop(key) for key in CONVERTER_OPTIONS if key in kwargs}}
        super().__init__(url, **kwargs)
        self.converter = SipConverter(**conv)
        self.rig = self._mounts(rig)
        self.handshake = handshake
        self.handshake_timeout_s = handshake_timeout_s
        self.pulse_s = pulse_s
        self.decoder = ArcosDecoder()
        self.robot_info: tuple[str, ...] = ()
        self.other_packets = 0
        self._t0 = time.monotonic()
        self._last_pulse = 0.0
        self._rig_sent = False

    def _mounts(self, rig: RigRecord | str | Path | None) -> RigRecord:
        """The sonar mounts: a RigRecord, a rig JSON file (the log's ``rig`` record without
        ``type``, as `--option rig=RIG.json` names it) or the P3-DX's. The speed of sound
        is the converter's in every case: it turned the ranges into times of flight."""
        if rig is None:
            return p3dx_rig(self.converter.c)
        if isinstance(rig, (str, Path)):
            from sonarloc.io.rosbag import load_rig_json

            return RigRecord(load_rig_json(rig)[0].sensors, self.converter.c)
        if not isinstance(rig, RigRecord):
            raise ValueError(f"`rig` must be a rig JSON file or a RigRecord, got {rig!r}")
        return rig

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    def _on_connect(self) -> None:
        streaming = self._sync() if self.handshake else b""
        self.write(client_command(OPEN))
        self.write(client_command(SONAR, 1))
        self._last_pulse = time.monotonic()
        if not self._rig_sent:
            self._rig_sent = True
            self._deliver([self.rig])
        if streaming:
            self._on_bytes(streaming)

    def _sync(self) -> bytes:
        """The SYNC handshake; the bytes read in the step that found the robot already
        streaming SIPs (b"" after a full handshake), for the SIP decoder."""
        if self._port is None:
            raise DeviceError(f"{self.source}: not connected")
        dec = ArcosDecoder()
        for step in (SYNC0, SYNC1, SYNC2):
            self.write(client_command(step))
            deadline = time.monotonic() + self.handshake_timeout_s
            seen = bytearray()  # this step's bytes (a read may hold several SIPs)
            while True:
                if time.monotonic() > deadline:
                    raise DeviceError(f"{self.source}: no answer to SYNC{step} "
                                      f"(is it a Pioneer, at {self.baudrate} baud?)")
                data = self._read()
                seen += data
                del seen[:-MAX_SEEN]
                packets = dec.feed(data)
                if any(isinstance(p, StandardSip) for p in packets):
                    return bytes(seen)  # already open: the robot streams SIPs
                reply = next((p for p in packets if isinstance(p, ArcosPacket)
                              and p.type == step), None)
                if reply is not None:
                    if step == SYNC2:
                        self.robot_info = tuple(s.decode("ascii", "replace") for s in
                                                reply.data.split(b"\0") if s)
                    break
        return b""

    def _on_idle(self) -> None:
        now = time.monotonic()
        if now - self._last_pulse >= self.pulse_s:
            self._last_pulse = now
            self.write(client_command(PULSE))

    def _on_bytes(self, data: bytes) -> None:
        t = time.monotonic() - self._t0
        out = []
        for p in self.decoder.feed(data):
            if isinstance(p, StandardSip):
                out.extend(self.converter.records(p, t))
            else:
                self.other_packets += 1
        self._deliver(out)

    def _on_stream_end(self) -> None:
        t = time.monotonic() - self._t0
        out = []
        for p in self.decoder.flush():
            if isinstance(p, StandardSip):
                out.extend(self.converter.records(p, t))
        self._deliver(out)

    def _close(self) -> None:
        self._stop.set()  # no PULSE may follow the CLOSE
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        if self._port is not None:
            try:
                self.write(client_command(CLOSE))
            except DeviceError:
                pass
        super()._close()

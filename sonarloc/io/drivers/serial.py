"""The sonarloc module over a serial line (docs/PROTOCOL.md section 2), on pyserial.

>>> from sonarloc.io.drivers import open_driver
>>> with open_driver("loop://") as drv:          # doctest: +SKIP
...     rec = drv.read(timeout=1.0)
"""

from __future__ import annotations

import threading
import time
from typing import Any

from sonarloc.io.drivers.base import Wakeup
from sonarloc.io.drivers.port import PortDriver
from sonarloc.io.protocol.framing import SerialDecoder, SerialEncoder, SerialFrame
from sonarloc.io.protocol.messages import (
    COMMAND_TYPES,
    Ack,
    DecoderStats,
    Message,
    RequestRig,
    Start,
)
from sonarloc.io.protocol.records import RecordAssembler


class SerialDriver(PortDriver):
    """Reads the module protocol from a serial device or pyserial URL.

    Parameters
    ----------
    url : ``/dev/ttyUSB0``, a pty path, ``socket://127.0.0.1:PORT``, ``loop://``, ...
    start : send Start and RequestRig after every (re)connect, so a module that waits
        for a host begins streaming and a host that joins late learns the rig.
    wake_s : with ``start``, send them again after every ``wake_s`` seconds without a
        packet from the module (a module that restarted behind a port that stayed open
        waits for a Start, see :class:`~sonarloc.io.drivers.base.Wakeup`); not after
        the host sent Stop. None: never.
    Other parameters: :class:`~sonarloc.io.drivers.port.PortDriver`.
    """

    scheme = "serial"

    def __init__(self, url: str, *, start: bool = True, wake_s: float | None = 2.0,
                 **kwargs: Any):
        super().__init__(url, **kwargs)
        self.start_on_connect = start
        self.wake_s = wake_s
        self._wake = Wakeup(wake_s, time.monotonic())
        self.decoder = SerialDecoder()
        self.assembler = RecordAssembler()
        self._encoder = SerialEncoder()
        self._send_lock = threading.RLock()
        self.acks: list[Ack] = []  # the last few acknowledgements, newest last

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    def send(self, msg: Message) -> None:
        """Frame ``msg`` with this host's sequence number and write it."""
        with self._send_lock:
            self._wake.sent(msg, time.monotonic())
            self.write(self._encoder.encode(msg))

    def _on_connect(self) -> None:
        if self.start_on_connect:
            self.send(Start())
            self.send(RequestRig())

    def _on_bytes(self, data: bytes) -> None:
        frames = self.decoder.feed_frames(data)
        if any(not isinstance(f.message, COMMAND_TYPES) for f in frames):
            self._wake.heard(time.monotonic())  # the module's packets, not line noise
        self._handle(frames)

    def _on_idle(self) -> None:
        if self.start_on_connect:
            self._wake_if_silent(self._wake, self._send_lock)

    def _on_stream_end(self) -> None:
        self._handle(self.decoder.flush())

    def _handle(self, frames: list[SerialFrame]) -> None:
        out = []
        now = time.monotonic()
        for f in frames:
            if isinstance(f.message, Ack):
                self.acks = (self.acks + [f.message])[-16:]
            out.extend(self.assembler.push(f.message, now))
        self._deliver(out)

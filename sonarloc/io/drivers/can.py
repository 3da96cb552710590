"""The sonarloc module on a CAN bus (docs/PROTOCOL.md section 3), on python-can.

Any python-can interface works (``virtual``, ``socketcan``, ``pcan``, ``kvaser``,
``slcan``, ...): ``can:INTERFACE:CHANNEL``. A :class:`can.Notifier` runs the
receive thread and calls this driver's listener, which feeds the pure
:class:`~sonarloc.io.protocol.canbus.CanDecoder`. Error frames, unknown ids and
wrong lengths are skipped and counted. Bus errors raised by the interface are
counted (``bus_errors``) and, if they persist, reported by :meth:`Driver.read`.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import can

from sonarloc.errors import DeviceError
from sonarloc.io.drivers.base import Driver, RecordCallback
from sonarloc.io.protocol.canbus import CanDecoder, CanEncoder
from sonarloc.io.protocol.messages import Ack, DecoderStats, Message, RequestRig, Start
from sonarloc.io.protocol.records import RecordAssembler


class _Listener(can.Listener):
    def __init__(self, driver: CanDriver):
        self.driver = driver

    def on_message_received(self, msg: can.Message) -> None:
        self.driver._on_frame(msg)

    def on_error(self, exc: Exception) -> None:
        self.driver._on_bus_error(exc)


class CanDriver(Driver):
    """Reads the module protocol from a python-can bus.

    Parameters
    ----------
    interface, channel : python-can interface name and channel (``"virtual"``, ``"x"``).
    bus : an already open bus to use instead (the caller keeps ownership).
    start : send Start and RequestRig after opening.
    max_bus_errors : consecutive bus errors after which :meth:`read` raises.
    bus_options : passed to :class:`can.Bus` (``bitrate=500000``, ...).
    """

    scheme = "can"

    def __init__(self, interface: str = "virtual", channel: Any = "sonarloc", *,
                 bus: can.BusABC | None = None, start: bool = True, max_bus_errors: int = 20,
                 on_record: RecordCallback | None = None, queue_size: int = 100_000,
                 **bus_options: Any):
        super().__init__(on_record=on_record, queue_size=queue_size)
        self.interface = interface
        self.channel = channel
        self.start_on_open = start
        self.max_bus_errors = max_bus_errors
        self.bus_errors = 0
        self._consecutive_errors = 0
        self._bus_options = bus_options
        self._bus = bus
        self._own_bus = bus is None
        self._notifier: can.Notifier | None = None
        self.decoder = CanDecoder()
        self.assembler = RecordAssembler()
        self._encoder = CanEncoder()
        self._lock = threading.Lock()
        self.acks: list[Ack] = []

    @property
    def source(self) -> str:
        return f"can:{self.interface}:{self.channel}"

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    def counters(self) -> dict[str, int]:
        out = super().counters()
        out["bus_errors"] = self.bus_errors
        return out

    @property
    def bus(self) -> can.BusABC:
        if self._bus is None:
            raise DeviceError(f"{self.source}: not open")
        return self._bus

    def _open(self) -> None:
        if self._bus is None:
            try:
                self._bus = can.Bus(interface=self.interface, channel=self.channel,
                                    **self._bus_options)
            except (can.CanError, OSError, ValueError, ImportError) as err:
                raise DeviceError(f"cannot open {self.source}: {err}") from err
        self._notifier = can.Notifier(self._bus, [_Listener(self)], timeout=0.05)
        if self.start_on_open:
            self.send(Start())
            self.send(RequestRig())

    def _close(self) -> None:
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        if self._bus is not None and self._own_bus:
            self._bus.shutdown()
        self._bus = None

    def send(self, msg: Message) -> None:
        with self._lock:
            frames = self._encoder.encode(msg)
        try:
            for f in frames:
                self.bus.send(f, timeout=1.0)
        except can.CanError as err:
            raise DeviceError(f"{self.source}: send failed: {err}") from err

    def _on_frame(self, frame: can.Message) -> None:
        self._consecutive_errors = 0
        out = []
        for m in self.decoder.feed(frame):
            if isinstance(m, Ack):
                self.acks = (self.acks + [m])[-16:]
            out.extend(self.assembler.push(m, frame.timestamp))
        self._deliver(out)

    def _on_bus_error(self, exc: Exception) -> None:
        self.bus_errors += 1
        self._consecutive_errors += 1
        if self._consecutive_errors >= self.max_bus_errors:
            self._fail(exc)
        time.sleep(0.05)  # the notifier retries at once; do not spin on a dead bus

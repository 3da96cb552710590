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
from sonarloc.io.drivers.base import Driver, RecordCallback, Wakeup
from sonarloc.io.protocol.canbus import COMMAND, FIRING, SETTINGS, CanDecoder, CanEncoder
from sonarloc.io.protocol.messages import Ack, DecoderStats, Message, RequestRig, Start
from sonarloc.io.protocol.records import RecordAssembler

_HOST_IDS = (COMMAND, FIRING, SETTINGS)


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
    wake_s : with ``start``, send them again after every ``wake_s`` seconds without a
        frame from the module: a restarted module waits for a host's Start, and CAN has
        no connection to lose and reopen (see :class:`~sonarloc.io.drivers.base.Wakeup`).
        Not after the host sent Stop. None: never.
    max_bus_errors : consecutive bus errors after which :meth:`read` raises.
    bus_options : passed to :class:`can.Bus` (``bitrate=500000``, ...).
    """

    scheme = "can"

    def __init__(self, interface: str = "virtual", channel: Any = "sonarloc", *,
                 bus: can.BusABC | None = None, start: bool = True, wake_s: float | None = 2.0,
                 max_bus_errors: int = 20, on_record: RecordCallback | None = None,
                 queue_size: int = 100_000, **bus_options: Any):
        super().__init__(on_record=on_record, queue_size=queue_size)
        self.wake_s = wake_s
        self._wake = Wakeup(wake_s, time.monotonic())
        self._send_lock = threading.RLock()
        self._watch_stop = threading.Event()
        self._watcher: threading.Thread | None = None
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
            if self.wake_s is not None:
                self._watcher = threading.Thread(target=self._watch, args=(self.wake_s,),
                                                 daemon=True,
                                                 name=f"sonarloc {self.source} wake-up")
                self._watcher.start()

    def _watch(self, wake_s: float) -> None:
        """Send Start again to a module that fell silent (see :class:`Wakeup`)."""
        while not self._watch_stop.wait(min(wake_s / 4, 0.25)):
            try:
                self._wake_if_silent(self._wake, self._send_lock)
            except DeviceError:
                pass  # the bus refused it (bus off, queue full): tried after wake_s

    def _close(self) -> None:
        self._watch_stop.set()
        if self._watcher is not None:
            self._watcher.join()
            self._watcher = None
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        if self._bus is not None and self._own_bus:
            self._bus.shutdown()
        self._bus = None

    def send(self, msg: Message) -> None:
        with self._send_lock:
            self._wake.sent(msg, time.monotonic())
            with self._lock:
                frames = self._encoder.encode(msg)
            try:
                for f in frames:
                    self.bus.send(f, timeout=1.0)
            except can.CanError as err:
                raise DeviceError(f"{self.source}: send failed: {err}") from err

    def _on_frame(self, frame: can.Message) -> None:
        self._consecutive_errors = 0
        good = self.decoder.stats.frames
        msgs = self.decoder.feed(frame)
        if self.decoder.stats.frames > good and frame.arbitration_id not in _HOST_IDS:
            self._wake.heard(time.monotonic())  # the module's frame: not junk, not a host's
        out = []
        for m in msgs:
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

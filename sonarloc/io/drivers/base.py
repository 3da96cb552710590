"""What every driver is: a source of log records from a device, a bus or a file.

A driver turns what a device sends into :mod:`sonarloc.io.logfile` records
(``RigRecord``, ``OdomRecord``, ``TofRecord``) and hands them to the caller, either
through :meth:`Driver.read` / :meth:`Driver.records` (pull) or through an
``on_record`` callback run on the driver's reader thread (push). Decoder counters
(good frames, CRC failures, skipped bytes, sequence gaps, ...) and driver counters
(reconnects, dropped records) are in :meth:`Driver.counters`.
"""

from __future__ import annotations

import threading
import time
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from types import TracebackType
from typing import ClassVar

from sonarloc.errors import DeviceError, DeviceTimeoutError
from sonarloc.io.logfile import Record
from sonarloc.io.protocol.messages import DecoderStats, Message, RequestRig, Start, Stop
from sonarloc.io.protocol.records import ModuleClock, RecordAssembler

RecordCallback = Callable[[Record], None]


@dataclass
class DriverStats:
    """Counters of a driver beyond its decoder's."""

    records: int = 0
    reconnects: int = 0
    disconnects: int = 0
    dropped: int = 0  # records lost because the caller did not read them fast enough
    malformed_lines: int = 0  # text logs: lines no reader could parse
    callback_errors: int = 0  # exceptions raised by an on_record callback
    wakeups: int = 0  # Start sent again to a module silent for wake_s (restarted, waiting)


class Wakeup:
    """When to send Start again to a module of the protocol that fell silent.

    A module waits for a host's Start after power-up and says nothing meanwhile, so a
    module that restarted mid-recording behind a link that stayed up (a CAN node
    power-cycled, a processor reset behind a USB adapter) is silent until it is sent
    Start: silence is the only sign. Start is idempotent ("start or resume"), so it is
    sent again after every ``wake_s`` seconds without a frame from the module, never
    while the module is heard and never after the host sent Stop (until it sends Start).

    Pure: the caller gives the time (``now``, seconds on one monotonic clock), so the
    rule is tested without sleeping. The driver calls :meth:`sent` before writing a
    command and checks :meth:`due` under the same lock, so a Stop is never followed by
    a wake-up Start.
    """

    __slots__ = ("wake_s", "_last", "_stopped")

    def __init__(self, wake_s: float | None, now: float):
        if wake_s is not None and not (isinstance(wake_s, (int, float)) and wake_s > 0):
            raise ValueError(f"`wake_s` must be a positive number of seconds or None, "
                             f"got {wake_s!r}")
        self.wake_s = wake_s
        self._last = now  # the module last heard, or Start last sent
        self._stopped = False

    def heard(self, now: float) -> None:
        """A good frame came from the module."""
        self._last = max(self._last, now)

    def sent(self, msg: Message, now: float) -> None:
        """The host is sending ``msg`` (call before writing it)."""
        if isinstance(msg, Stop):
            self._stopped = True
        elif isinstance(msg, Start):
            self._stopped = False
            self._last = max(self._last, now)

    def due(self, now: float) -> bool:
        """True if Start should be sent again now."""
        return self.wake_s is not None and not self._stopped and now - self._last >= self.wake_s


def sleep_until(due: float, deadline: float | None) -> bool:
    """Sleep until ``time.monotonic()`` reaches ``due``, but not past ``deadline`` (None:
    no limit); True if ``due`` was reached. Paced replays use it so that a jump ahead in a
    file's time does not hold up ``read(timeout)``."""
    if deadline is not None and due > deadline:
        time.sleep(max(deadline - time.monotonic(), 0.0))
        return False
    wait = due - time.monotonic()
    if wait > 0:
        time.sleep(wait)
    return True


MAX_PACED_STEP_S = 5.0
"""Longest step forward in a replayed file's time that a paced replay waits for."""


class Pacer:
    """Wall-clock pacing of a replay against the records' (or frames') own time.

    Each step of the file's time is waited for, divided by ``rate``; a step backwards
    or one longer than ``max_step_s`` (a clock spike in the recording, a recorder
    paused for an hour) is not: counted in :attr:`jumps`, the replay goes on at once
    and paces the steps after it as before. Without this, one reading stamped an hour
    late held a paced replay up for that hour. The times sent are never changed.
    :attr:`elapsed_s` is the file time paced so far (the jumps left out).

    >>> p = Pacer(rate=2.0)
    >>> p.due(100.0, now=0.0), p.due(101.0, now=0.0), p.due(4000.0, now=0.0)
    (0.0, 0.5, 0.5)
    >>> p.jumps, p.elapsed_s
    (1, 1.0)
    """

    __slots__ = ("rate", "max_step_s", "jumps", "elapsed_s", "_wall", "_t")

    def __init__(self, rate: float | None, max_step_s: float = MAX_PACED_STEP_S):
        if rate is not None and not rate > 0:
            raise ValueError(f"`rate` must be positive or None, got {rate!r}")
        if not max_step_s > 0:
            raise ValueError(f"`max_step_s` must be positive, got {max_step_s!r}")
        self.rate, self.max_step_s = rate, max_step_s
        self.jumps = 0
        self.elapsed_s = 0.0
        self._wall: float | None = None  # when the last record was due (monotonic s)
        self._t = 0.0                    # and its file time

    def due(self, t_s: float, now: float) -> float:
        """When (``time.monotonic()`` seconds) the record at file time ``t_s`` is due;
        the first is due at ``now``. Asking again for the same ``t_s`` gives the same
        answer (a record read before its time and kept)."""
        if self._wall is None:
            self._wall, self._t = now, t_s
            return now
        step = t_s - self._t
        if not step <= self.max_step_s or step < -self.max_step_s:
            self.jumps += 1  # NaN lands here too
        if not 0.0 < step <= self.max_step_s:
            step = 0.0
        self.elapsed_s += step
        if self.rate is not None:
            self._wall += step / self.rate
        self._t = t_s
        return self._wall

    def shift(self, seconds: float) -> None:
        """Move what is due later by ``seconds`` (the replay was paused)."""
        if self._wall is not None:
            self._wall += seconds


class Driver(ABC):
    """Base of all drivers. Use as a context manager, or call :meth:`open`/:meth:`close`.

    Parameters
    ----------
    on_record : if given, called with every record (on the driver's thread for
        threaded drivers) instead of queueing it for :meth:`read`.
    queue_size : records kept for :meth:`read` before the oldest are dropped
        (and counted in ``dropped``).
    """

    scheme: ClassVar[str] = ""
    #: a replay's pacing (file drivers with a ``rate``); None for live devices
    pacer: Pacer | None = None

    def __init__(self, *, on_record: RecordCallback | None = None, queue_size: int = 100_000):
        if queue_size < 1:
            raise ValueError(f"`queue_size` must be positive, got {queue_size}")
        self.stats = DriverStats()
        self._on_record = on_record
        self._queue: deque[Record] = deque()
        self._queue_size = queue_size
        self._cond = threading.Condition()
        self._ended = False
        self._error: BaseException | None = None
        self._opened = False
        self.end_reason = ""  # why a live stream ended by itself, in words (pty hang-up)

    # -- to implement -----------------------------------------------------------------
    @property
    @abstractmethod
    def source(self) -> str:
        """What this driver reads, as it would be written on the command line."""

    @property
    @abstractmethod
    def decoder_stats(self) -> DecoderStats:
        """Counters of the wire decoder."""

    @abstractmethod
    def _open(self) -> None:
        """Open the device and start delivering (called once by :meth:`open`)."""

    @abstractmethod
    def _close(self) -> None:
        """Stop delivering and release everything (called once by :meth:`close`)."""

    def _pull(self, timeout: float | None) -> None:
        """Pull-style drivers (``pulls = True``): deliver records or end the stream,
        waiting at most ``timeout`` seconds. Threaded drivers deliver from their thread."""
        raise NotImplementedError

    pulls: ClassVar[bool] = False

    # -- public -----------------------------------------------------------------------
    def open(self) -> Driver:
        if not self._opened:
            self._opened = True
            self._open()
        return self

    def close(self) -> None:
        if self._opened:
            self._opened = False
            try:
                self._close()
            finally:
                self._end()

    def __enter__(self) -> Driver:
        return self.open()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def send(self, msg: Message) -> None:
        """Send a command to the device (Start, Stop, RequestRig, Firing, Settings)."""
        raise DeviceError(f"{self.source}: this source does not take commands")

    def _wake_if_silent(self, wake: Wakeup, send_lock: threading.RLock) -> None:
        """Send Start and RequestRig again if ``wake`` says the module fell silent
        (counted: ``stats.wakeups``). Checked under ``send_lock``, the lock :meth:`send`
        holds while it tells ``wake`` what it sends, so a Stop being sent is seen first."""
        with send_lock:
            if not wake.due(time.monotonic()):
                return
            self.stats.wakeups += 1
            self.send(Start())
            self.send(RequestRig())

    def read(self, timeout: float | None = 1.0) -> Record | None:
        """The next record; None once the stream has ended (end of file, closed).

        Raises
        ------
        DeviceTimeoutError
            if no record arrived within ``timeout`` seconds (None waits forever).
        DeviceError
            if the device failed for good.
        """
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            with self._cond:
                if self._queue:
                    return self._queue.popleft()
                if self._error is not None:
                    err, self._error = self._error, None
                    raise DeviceError(f"{self.source}: {err}") from err
                if self._ended:
                    return None
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise DeviceTimeoutError(
                        f"{self.source}: no record within {timeout:g} s ({self.summary()})")
                if not self.pulls:
                    self._cond.wait(left)
                    continue
            self._pull(left)

    def records(self, timeout: float | None = 1.0,
                duration_s: float | None = None) -> Iterator[Record]:
        """Iterate records until the stream ends or ``duration_s`` of wall time passes.

        ``timeout`` is the longest silence allowed (DeviceTimeoutError after it).
        """
        end = None if duration_s is None else time.monotonic() + duration_s
        while True:
            wait = timeout
            if end is not None:
                left = end - time.monotonic()
                if left <= 0:
                    return
                if wait is None or left < wait:
                    wait = left
            try:
                rec = self.read(wait)
            except DeviceTimeoutError:
                if end is not None and time.monotonic() >= end:
                    return
                raise
            if rec is None:
                return
            yield rec

    def counters(self) -> dict[str, int]:
        """Decoder and driver counters in one flat dict."""
        out = self.decoder_stats.as_dict()
        out.update({f.name: getattr(self.stats, f.name) for f in fields(self.stats)})
        clock = self._module_clock()
        if clock is not None:
            out["module_restarts"] = clock.restarts
            out["clock_spikes"] = clock.spikes
        if self.pacer is not None and self.pacer.rate is not None:
            out["time_jumps"] = self.pacer.jumps
        return out

    def summary(self) -> str:
        """One line of counters: good/CRC/skipped/gaps first."""
        s = self.stats
        extra = [f"{s.records} records"]
        clock = self._module_clock()
        if clock is not None and clock.restarts:
            extra.append(f"module restarts {clock.restarts}")
        if clock is not None and clock.spikes:
            extra.append(f"clock spikes {clock.spikes} (readings dropped)")
        for name in ("disconnects", "reconnects", "wakeups", "dropped", "malformed_lines"):
            if getattr(s, name):
                extra.append(f"{name.replace('_', ' ')} {getattr(s, name)}")
        if self.pacer is not None and self.pacer.rate is not None and self.pacer.jumps:
            extra.append(f"time jumps {self.pacer.jumps} (not waited for)")
        return f"{self.decoder_stats.summary()}; {', '.join(extra)}"

    def _module_assembler(self) -> RecordAssembler | None:
        """The record assembler of a driver of the module protocol; None for others."""
        asm = getattr(self, "assembler", None)
        return asm if isinstance(asm, RecordAssembler) else None

    def _module_clock(self) -> ModuleClock | None:
        """The module's clock as a driver of the module protocol unwraps it (restarts,
        spikes); None for other drivers."""
        asm = self._module_assembler()
        return None if asm is None else asm.clock

    # -- for subclasses ---------------------------------------------------------------
    def _deliver(self, recs: list[Record]) -> None:
        if not recs:
            return
        self.stats.records += len(recs)
        if self._on_record is not None:
            for rec in recs:
                try:
                    self._on_record(rec)
                except Exception as err:  # the caller's bug must not kill the reader
                    self.stats.callback_errors += 1
                    self._fail(err)
            return
        with self._cond:
            self._queue.extend(recs)
            over = len(self._queue) - self._queue_size
            for _ in range(max(over, 0)):
                self._queue.popleft()
            if over > 0:
                self.stats.dropped += over
            self._cond.notify_all()

    def _end(self) -> None:
        """No more records will come (end of file, or closed): a reading the module
        protocol held back (its time jumped; no later reading came) is delivered first."""
        asm = self._module_assembler()
        if asm is not None:
            self._deliver(asm.flush())
        with self._cond:
            self._ended = True
            self._cond.notify_all()

    def _fail(self, err: BaseException) -> None:
        """A fatal device error: the next :meth:`read` raises it as a DeviceError."""
        with self._cond:
            self._error = err
            self._cond.notify_all()

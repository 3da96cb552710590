"""A simulated sonar module: the device side of the protocol, for tests and ``serve-sim``.

:class:`SimModule` streams log records (from the simulator or a log file) as the
module protocol over a transport, paced in (optionally accelerated) real time, and
answers commands from the host:

* :class:`PtyTransport` — a pseudo-terminal; the host opens its path like a serial
  device. ``link=`` keeps a stable symlink (like udev's ``/dev/serial/by-id``), so
  :meth:`PtyTransport.replug` can simulate unplugging and replugging the cable.
* :class:`TcpTransport` — a TCP server on 127.0.0.1 speaking the serial protocol to
  one host at a time (as ser2net: another is told ``Port already in use``); the host
  opens ``socket://127.0.0.1:PORT``. :meth:`TcpTransport.drop_client` pulls the cable.
* :class:`CanBusTransport` — any python-can bus (``virtual`` within one process).
* :class:`CandumpTransport` — writes a candump log with python-can's writer.

Unless told otherwise the module waits for the host's Start before it streams
(transports that carry commands), and sends its rig after Start, on RequestRig and
every ``rig_every_s`` of stream time. ``sent_log`` records exactly what went out, as
the host will decode it (quantized, rig repeats dropped), in the log format.

:class:`SimDriver` (``sim:LOG.jsonl``) is the host side without any wire: a log
replayed through the serial encoder and decoder in memory.

Example: a simulated module on a pseudo-terminal, read with the robot's own driver::

    with SimModule.on_pty(iter_log("drive.jsonl"), rate=20.0) as sim, \\
            open_driver(sim.url) as drv:
        for rec in drv.records(timeout=2.0):
            ...
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import os
import select
import socket
import struct
import termios
import threading
import time
import tty
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, Any, ClassVar

import can

from sonarloc.errors import DeviceError, LogFormatError
from sonarloc.io.drivers.base import Driver, Pacer, RecordCallback, sleep_until
from sonarloc.io.logfile import LogStats, LogWriter, Record, RigRecord, iter_log
from sonarloc.io.protocol.canbus import CanDecoder, CanEncoder
from sonarloc.io.protocol.framing import SerialDecoder, SerialEncoder, type_code
from sonarloc.io.protocol.messages import (
    ACK_OK,
    Ack,
    DecoderStats,
    Firing,
    Message,
    RequestRig,
    Settings,
    Start,
    Stop,
)
from sonarloc.io.protocol.records import RecordAssembler, messages_from_record

CommandCallback = Callable[[Message, int], None]


# ---------------------------------------------------------------------------------------
# transports (device side)
# ---------------------------------------------------------------------------------------
class Transport(ABC):
    """Where a simulated module's messages go, and where its commands come from."""

    accepts_commands: ClassVar[bool] = True

    @property
    @abstractmethod
    def url(self) -> str:
        """The source a host passes to :func:`~sonarloc.io.drivers.open_driver`."""

    @abstractmethod
    def open(self, on_command: CommandCallback) -> None:
        """Start taking commands (``on_command(message, seq)`` on a transport thread)."""

    @abstractmethod
    def send(self, msgs: list[Message], t_s: float) -> bool:
        """Send messages; False if they were lost (no host, buffer full, bus error)."""

    @abstractmethod
    def close(self) -> None:
        """Release everything (idempotent)."""


class _ByteTransport(Transport):
    """Serial framing over a byte stream, with a thread reading the host's commands."""

    def __init__(self) -> None:
        self._encoder = SerialEncoder()
        self._decoder = SerialDecoder()
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._on_command: CommandCallback | None = None

    def open(self, on_command: CommandCallback) -> None:
        self._on_command = on_command
        self._thread = threading.Thread(target=self._reader, name=f"sim {self.url}", daemon=True)
        self._thread.start()

    def send(self, msgs: list[Message], t_s: float) -> bool:
        with self._lock:
            return self._write(b"".join(self._encoder.encode(m) for m in msgs))

    @abstractmethod
    def _write(self, data: bytes) -> bool: ...

    @abstractmethod
    def _reader(self) -> None: ...

    def _commands(self, data: bytes) -> None:
        for f in self._decoder.feed_frames(data):
            if self._on_command is not None:
                self._on_command(f.message, f.seq)

    def _join(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None


class PtyTransport(_ByteTransport):
    """A pseudo-terminal pair; the host opens :attr:`url` (the slave or ``link``)."""

    def __init__(self, link: str | Path | None = None):
        super().__init__()
        self.link = None if link is None else Path(link)
        self._master = -1
        self.slave_path = ""
        self._new_pty()

    @property
    def url(self) -> str:
        return str(self.link) if self.link is not None else self.slave_path

    def _new_pty(self) -> None:
        link = self.link
        if link is not None and link.exists() and not link.is_symlink():
            # a symlink is ours to replace (left by a module killed earlier); a file is not
            raise DeviceError(f"link {link} exists and is not a symlink; not replacing it")
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo, no CR/LF translation: a clean 8-bit line
        path = os.ttyname(slave)
        os.close(slave)
        os.set_blocking(master, False)
        if link is not None:
            tmp = link.with_name(link.name + ".new")
            try:
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
                os.symlink(path, tmp)
                os.replace(tmp, link)
            except OSError as err:
                os.close(master)
                raise DeviceError(f"cannot link {link} to {path}: {err.strerror}") from err
        self._master, self.slave_path = master, path

    def replug(self) -> None:
        """Pull the cable and plug it back: the old pty closes, a new one takes the link."""
        if self.link is None:
            raise DeviceError("replug needs a PtyTransport with a `link` path")
        with self._lock:
            os.close(self._master)
            self._decoder = SerialDecoder()
            self._new_pty()

    WRITE_WAIT_S = 0.2

    def _write(self, data: bytes) -> bool:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
            except BlockingIOError:
                # the host is behind: wait a little for room (like hardware flow control),
                # then give up as a UART without flow control would
                _, ready, _ = select.select([], [self._master], [], self.WRITE_WAIT_S)
                if not ready:
                    return False
                continue
            except OSError:
                return False
            view = view[n:]
        return True

    def _reader(self) -> None:
        while not self._stop.is_set():
            with self._lock:
                fd = self._master
            try:
                ready, _, _ = select.select([fd], [], [], 0.05)
                data = os.read(fd, 4096) if ready else b""
            except (BlockingIOError, InterruptedError):
                continue
            except OSError:  # EIO: no host has the slave open (or replug in progress)
                self._stop.wait(0.05)
                continue
            if data:
                self._commands(data)

    DRAIN_WAIT_S = 5.0
    """Longest :meth:`close` waits for the host to read what is still in the terminal."""

    def _drain(self, timeout_s: float) -> None:
        """Wait until the host has read every byte written (at most ``timeout_s``).

        Closing the master hangs the terminal up, and Linux then drops what the host
        has not read yet: a host slowed down by a loaded machine would lose the last
        records. The bytes still unread are the slave's input queue (FIONREAD on a
        descriptor of the slave of our own); the kernel moves written bytes there a
        little later, so the queue must be seen empty twice, 50 ms apart."""
        try:
            fd = os.open(self.slave_path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError:
            return   # no terminal left to wait for
        try:
            end = time.monotonic() + timeout_s
            empty_since = None
            while (now := time.monotonic()) < end:
                unread = struct.unpack("i", fcntl.ioctl(fd, termios.FIONREAD, b"\0" * 4))[0]
                if unread:
                    empty_since = None
                elif empty_since is None:
                    empty_since = now
                elif now - empty_since >= 0.05:
                    return
                time.sleep(0.01)
        except OSError:
            return
        finally:
            os.close(fd)

    def _host_attached(self) -> bool:
        """Whether a host has the slave open: the master reports a hang-up (POLLHUP)
        while no descriptor of the slave is open. A host gone (closed, or never came)
        reads nothing more, so :meth:`close` need not wait for it to drain the line."""
        poller = select.poll()
        poller.register(self._master, select.POLLIN)
        return not any(ev & select.POLLHUP for _, ev in poller.poll(0))

    def close(self) -> None:
        self._join()
        with self._lock:
            if self._master >= 0:
                if self._host_attached():
                    self._drain(self.DRAIN_WAIT_S)
                os.close(self._master)
                self._master = -1
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                if self.link.is_symlink():
                    self.link.unlink()


class TcpTransport(_ByteTransport):
    """A TCP server speaking the serial protocol to one host at a time.

    A module has one host, and so has a serial-to-network bridge in front of it:
    ser2net (its default ``max-connections: 1``) answers a connection that comes while
    another host is connected with the line :data:`BUSY` and closes it, and so does
    this server (counted: ``refused``). The first host keeps its connection and every
    record; the other learns why at once instead of taking the line over and being
    taken over in turn (two recorders reconnecting, each losing about half the records).
    """

    BUSY = b"Port already in use\r\n"
    """What ser2net sends to a connection it refuses, before closing it."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0):
        super().__init__()
        try:
            self._server = socket.create_server((host, port))
        except OSError as err:
            raise DeviceError(f"cannot listen on {host}:{port}: {err.strerror}") from err
        self.host, self.port = self._server.getsockname()[:2]
        self._client: socket.socket | None = None
        self.clients = 0  # hosts served
        self.refused = 0  # hosts turned away while another was connected
        self._refusing: dict[socket.socket, float] = {}  # refused, until (monotonic)

    @property
    def url(self) -> str:
        return f"socket://{self.host}:{self.port}"

    def _write(self, data: bytes) -> bool:
        client = self._client
        if client is None:
            return False
        try:
            client.sendall(data)
        except OSError:
            self._drop(client)
            return False
        return True

    def drop_client(self) -> None:
        """Pull the cable: close the connection to the current host (it may reconnect)."""
        client = self._client
        if client is not None:
            self._drop(client)

    def _drop(self, client: socket.socket) -> None:
        with self._lock:
            if self._client is client:
                self._client = None
        with contextlib.suppress(OSError):
            client.shutdown(socket.SHUT_RDWR)
        client.close()

    def _reader(self) -> None:
        while not self._stop.is_set():
            client = self._client
            watch = [self._server, *self._refusing] + ([client] if client is not None else [])
            try:
                ready, _, _ = select.select(watch, [], [], 0.05)
            except (OSError, ValueError):  # a socket closed under us
                continue
            # the host's hang-up before a new connection: a host that reconnects at
            # once is served again, not refused by its own dead connection
            if client is not None and client in ready:
                try:
                    data = client.recv(4096)
                except OSError:
                    data = b""
                if data:
                    self._commands(data)
                else:
                    self._drop(client)
            self._linger([c for c in self._refusing if c in ready])
            if self._server in ready:
                self._accept()

    REFUSE_LINGER_S = 2.0
    """Longest a refused connection is kept open for its host to read :data:`BUSY`."""

    def _accept(self) -> None:
        """Serve a new host, or refuse it while another is connected."""
        try:
            conn, _ = self._server.accept()
        except OSError:
            return
        with self._lock:
            busy = self._client is not None
            if not busy:
                conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.settimeout(1.0)
                self._client = conn
                self._decoder = SerialDecoder()
                self.clients += 1
        if not busy:
            return
        self.refused += 1
        try:
            conn.setblocking(False)
            conn.send(self.BUSY)
            conn.shutdown(socket.SHUT_WR)
        except OSError:
            conn.close()
            return
        # Closed now, a socket holding the host's unread Start would be reset, and the
        # reset can overtake the line; kept until the host hangs up (it reads the line
        # and EOF), its bytes discarded.
        self._refusing[conn] = time.monotonic() + self.REFUSE_LINGER_S

    def _linger(self, ready: list[socket.socket]) -> None:
        """Discard what refused hosts send; close them when they hang up or time out."""
        now = time.monotonic()
        for conn in list(self._refusing):
            done = self._refusing[conn] <= now
            if conn in ready:
                try:
                    done = done or not conn.recv(4096)
                except OSError:
                    done = True
            if done:
                del self._refusing[conn]
                conn.close()

    def close(self) -> None:
        self._join()
        client = self._client
        if client is not None:
            self._drop(client)
        for conn in self._refusing:
            conn.close()
        self._refusing.clear()
        self._server.close()


class CanBusTransport(Transport):
    """The module on a python-can bus (its own bus object on the channel)."""

    def __init__(self, interface: str = "virtual", channel: Any = "sonarloc", *,
                 bus: can.BusABC | None = None, **bus_options: Any):
        self.interface, self.channel = interface, channel
        self._own_bus = bus is None
        if bus is None:
            try:
                bus = can.Bus(interface=interface, channel=channel, **bus_options)
            except (can.CanError, OSError, ValueError, ImportError) as err:
                raise DeviceError(f"cannot open CAN {interface}:{channel}: {err}") from err
        self._bus = bus
        self._encoder = CanEncoder()
        self._decoder = CanDecoder()
        self._notifier: can.Notifier | None = None
        self._lock = threading.Lock()

    @property
    def url(self) -> str:
        return f"can:{self.interface}:{self.channel}"

    def open(self, on_command: CommandCallback) -> None:
        def listener(frame: can.Message) -> None:
            for m in self._decoder.feed(frame):
                on_command(m, 0)

        self._notifier = can.Notifier(self._bus, [listener], timeout=0.05)

    def send(self, msgs: list[Message], t_s: float) -> bool:
        with self._lock:
            frames = [f for m in msgs for f in self._encoder.encode(m)]
            try:
                for f in frames:
                    self._bus.send(f, timeout=0.5)
            except can.CanError:
                return False
        return True

    def close(self) -> None:
        if self._notifier is not None:
            self._notifier.stop()
            self._notifier = None
        if self._own_bus and self._bus is not None:
            self._bus.shutdown()
        self._own_bus = False


class CandumpTransport(Transport):
    """Writes the module's frames to a candump log (timestamps = stream time)."""

    accepts_commands = False

    def __init__(self, path: str | Path, channel: str = "can0"):
        self.path = Path(path)
        try:
            self._writer: can.CanutilsLogWriter | None = can.CanutilsLogWriter(
                self.path, channel=channel)
        except OSError as err:
            raise DeviceError(f"cannot write {self.path}: {err.strerror}") from err
        self._encoder = CanEncoder()
        self._channel = channel

    @property
    def url(self) -> str:
        return f"candump:{self.path}"

    def open(self, on_command: CommandCallback) -> None:
        pass

    def send(self, msgs: list[Message], t_s: float) -> bool:
        if self._writer is None:
            return False
        for m in msgs:
            for f in self._encoder.encode(m):
                f.timestamp = t_s
                f.channel = self._channel
                self._writer.on_message_received(f)
        return True

    def close(self) -> None:
        if self._writer is not None:
            self._writer.stop()
            self._writer = None


# ---------------------------------------------------------------------------------------
# the module
# ---------------------------------------------------------------------------------------
@dataclass
class SimStats:
    records: int = 0  # device records streamed (rig, odom, tof; not init/truth)
    messages: int = 0  # messages offered to the transport
    lost: int = 0  # messages the transport could not deliver
    rigs_sent: int = 0
    commands: int = 0
    unsendable: int = 0  # readings the wire cannot carry (a negative TOF, a sensor id > 255)
    first_unsendable: str = ""  # the first of them and why

    def note_unsendable(self, rec: Record, err: ValueError) -> None:
        self.unsendable += 1
        if not self.first_unsendable:
            self.first_unsendable = _unsendable(rec, err)


def _unsendable(rec: Record, err: ValueError) -> str:
    """Which record the wire could not carry, and why."""
    return f"{rec.type} at t_s {rec.t_s:g}: {err}"[:200]


class SimModule:
    """A simulated sonar module streaming ``records`` over ``transport``.

    Parameters
    ----------
    records : log records in non-decreasing ``t_s`` (``simulate_records(...)``,
        ``iter_log(path)``); ``init`` and ``truth`` records are not sent.
    transport : where to (see the module docstring), or use the ``on_*`` constructors.
    rate : pacing against ``t_s`` (1.0 real time, 10.0 ten times faster); None sends as
        fast as the transport takes it.
    duration_s : stop after this much stream time (the time jumps that pacing does
        not wait for, :class:`~sonarloc.io.drivers.base.Pacer`, left out).
    sent_log : path, text stream or LogWriter receiving what was sent.
    wait_for_start : hold the stream until the host sends Start (default: if the
        transport carries commands).
    rig_every_s : repeat the rig description this often (stream time).
    """

    MAX_SETTINGS = 64

    def __init__(self, records: Iterable[Record], transport: Transport, *,
                 rate: float | None = 1.0, duration_s: float | None = None,
                 sent_log: str | Path | IO[str] | LogWriter | None = None,
                 wait_for_start: bool | None = None, rig_every_s: float = 1.0):
        self.pacer = Pacer(rate)  # checks `rate`
        if duration_s is not None and not duration_s >= 0:
            raise ValueError(f"`duration_s` must be non-negative, got {duration_s!r}")
        if not rig_every_s > 0:
            raise ValueError(f"`rig_every_s` must be positive, got {rig_every_s!r}")
        self.transport = transport
        self.rate = rate
        self.duration_s = duration_s
        self.rig_every_s = rig_every_s
        self.stats = SimStats()
        self.settings: list[Message] = []  # Firing/Settings received (not applied)
        self._records = iter(records)
        self._own_writer = sent_log is not None and not isinstance(sent_log, LogWriter)
        self._writer = (sent_log if isinstance(sent_log, LogWriter) or sent_log is None
                        else LogWriter(sent_log))
        self._sent = RecordAssembler()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._running = threading.Event()
        self.finished = threading.Event()
        self._rig: RigRecord | None = None
        self._rig_due = False
        self._last_rig_t = -float("inf")
        self._t_now = 0.0
        self._thread: threading.Thread | None = None
        self._opened = False
        self.error: BaseException | None = None  # what ended a background stream early
        if not (transport.accepts_commands if wait_for_start is None else wait_for_start):
            self._running.set()

    # -- constructors ---------------------------------------------------------------------
    @classmethod
    def on_pty(cls, records: Iterable[Record], *, link: str | Path | None = None,
               **kwargs: Any) -> SimModule:
        return cls(records, PtyTransport(link), **kwargs)

    @classmethod
    def on_tcp(cls, records: Iterable[Record], *, host: str = "127.0.0.1", port: int = 0,
               **kwargs: Any) -> SimModule:
        return cls(records, TcpTransport(host, port), **kwargs)

    @classmethod
    def on_can(cls, records: Iterable[Record], *, interface: str = "virtual",
               channel: Any = "sonarloc", bus_options: dict[str, Any] | None = None,
               **kwargs: Any) -> SimModule:
        return cls(records, CanBusTransport(interface, channel, **(bus_options or {})), **kwargs)

    @classmethod
    def to_candump(cls, records: Iterable[Record], path: str | Path, *,
                   rate: float | None = None, **kwargs: Any) -> SimModule:
        return cls(records, CandumpTransport(path), rate=rate, **kwargs)

    # -- life cycle -----------------------------------------------------------------------
    @property
    def url(self) -> str:
        """What a host opens: ``/dev/pts/N``, ``socket://127.0.0.1:PORT``, ``can:virtual:x``."""
        return self.transport.url

    def start(self) -> SimModule:
        """Stream on a background thread (returns at once)."""
        self._open()
        if self._thread is None:
            self._thread = threading.Thread(target=self._stream, name=f"sim module {self.url}",
                                            daemon=True)
            self._thread.start()
        return self

    def run(self) -> SimStats:
        """Stream in the calling thread until the records end, the duration is reached
        or :meth:`stop` is called."""
        self._open()
        self._stream()
        return self.stats

    def wait(self, timeout: float | None = None) -> bool:
        """True once the stream has ended."""
        return self.finished.wait(timeout)

    def sleep(self, seconds: float) -> bool:
        """Wait ``seconds`` unless :meth:`stop` is called first; True if stopped."""
        return self._stop.wait(seconds)

    @property
    def stopped(self) -> bool:
        """True once :meth:`stop` was called."""
        return self._stop.is_set()

    def stop(self) -> None:
        self._stop.set()
        self._running.set()  # wake a module waiting for Start

    def close(self) -> None:
        self.stop()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None
        self.transport.close()
        if self._writer is not None:
            if self._own_writer:
                self._writer.close()
            else:
                self._writer.flush()
            self._writer = None

    def __enter__(self) -> SimModule:
        return self.start()

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    def _open(self) -> None:
        if not self._opened:
            self._opened = True
            self.transport.open(self._on_command)

    # -- commands ---------------------------------------------------------------------------
    def _on_command(self, msg: Message, seq: int) -> None:
        if isinstance(msg, Start):
            self._rig_due = True
            self._running.set()
        elif isinstance(msg, Stop):
            self._running.clear()
        elif isinstance(msg, RequestRig):
            self._rig_due = True
        elif isinstance(msg, (Firing, Settings)):
            self.settings = (self.settings + [msg])[-self.MAX_SETTINGS:]
        else:
            return  # not a command (a host echoing data?): ignored
        self.stats.commands += 1
        self._send([Ack(type_code(msg), seq, ACK_OK)], self._t_now)

    # -- streaming ----------------------------------------------------------------------
    def _send(self, msgs: list[Message], t_s: float) -> bool:
        with self._lock:
            self.stats.messages += len(msgs)
            ok = self.transport.send(msgs, t_s)
            if not ok:
                self.stats.lost += len(msgs)
                return False
            if self._writer is not None:
                for m in msgs:
                    for rec in self._sent.push(m):
                        self._writer.write(rec)
            return True

    def _wait_running(self) -> float:
        """Block while stopped; returns the seconds spent paused."""
        if self._running.is_set():
            return 0.0
        t = time.monotonic()
        while not self._running.wait(0.1):
            pass
        return time.monotonic() - t

    def _stream(self) -> None:
        pacer = self.pacer
        try:
            for rec in self._records:
                if self._stop.is_set():
                    break
                if isinstance(rec, RigRecord):
                    self._rig, self._rig_due = rec, True
                    continue
                try:
                    msgs = messages_from_record(rec)
                except ValueError as err:  # skipped and counted: the rest still goes
                    self.stats.note_unsendable(rec, err)
                    continue
                if not msgs:
                    continue
                pacer.shift(self._wait_running())
                if self._stop.is_set():
                    break
                wait = pacer.due(rec.t_s, time.monotonic()) - time.monotonic()
                if self.duration_s is not None and pacer.elapsed_s > self.duration_s:
                    break
                if self.rate is not None and wait > 0 and self._stop.wait(wait):
                    break
                self._t_now = rec.t_s
                if self._rig is not None and (
                        self._rig_due or rec.t_s - self._last_rig_t >= self.rig_every_s):
                    self._rig_due = False
                    self._last_rig_t = rec.t_s
                    rig = dataclasses.replace(self._rig, t_s=rec.t_s)
                    if self._send(messages_from_record(rig), rec.t_s):
                        self.stats.rigs_sent += 1
                try:
                    self._send(msgs, rec.t_s)
                except ValueError as err:  # beyond the bus's range (CAN odometry)
                    self.stats.note_unsendable(rec, err)
                    continue
                self.stats.records += 1
        except BaseException as err:
            self.error = err
            if threading.current_thread() is not self._thread:
                raise
        finally:
            with self._lock:
                if self._writer is not None:
                    for rec in self._sent.flush():  # a reading held back by its time
                        self._writer.write(rec)
                    self._writer.flush()
            self.finished.set()


# ---------------------------------------------------------------------------------------
# host side without a wire
# ---------------------------------------------------------------------------------------
class SimDriver(Driver):
    """``sim:LOG.jsonl``: a log replayed through the serial protocol in memory.

    The records come out exactly as a host would receive them from a module
    streaming that log (quantized, rig once), without threads or devices.
    """

    scheme = "sim"
    pulls = True

    def __init__(self, source: str | Path | Iterable[Record], *, rate: float | None = None,
                 on_record: RecordCallback | None = None, queue_size: int = 100_000):
        super().__init__(on_record=on_record, queue_size=queue_size)
        self.pacer: Pacer = Pacer(rate)  # checks `rate`
        self._source = source
        self.rate = rate
        self.log_stats = LogStats()
        self.decoder = SerialDecoder()
        self.assembler = RecordAssembler()
        self._encoder = SerialEncoder()
        self._iter: Iterator[Record] | None = None
        self._due: tuple[Record, list[Message]] | None = None  # read before its time (rate)
        self.unsendable = 0  # records the wire cannot carry (skipped, counted)
        self.first_unsendable = ""

    @property
    def source(self) -> str:
        return f"sim:{self._source}" if isinstance(self._source, (str, Path)) else "sim:<records>"

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    def summary(self) -> str:
        """The counters, the records the wire could not carry (the first named) and
        what the log reader met besides good records (lines named)."""
        out = super().summary()
        if self.unsendable:
            out += f", unsendable {self.unsendable} (first: {self.first_unsendable})"
        ls = self.log_stats
        if ls.malformed_count or ls.unknown or ls.time_backwards_count:
            out += f"; log: {ls.summary()}"
        return out

    def _open(self) -> None:
        if isinstance(self._source, (str, Path)):
            if not Path(self._source).is_file():
                raise DeviceError(f"cannot open {self.source}: no such file")
            self._iter = iter_log(self._source, self.log_stats)
        else:
            self._iter = iter(self._source)

    def _close(self) -> None:
        self._iter = None

    def _pull(self, timeout: float | None) -> None:
        it = self._iter
        deadline = None if timeout is None else time.monotonic() + timeout
        while it is not None:
            if self._due is not None:
                (rec, msgs), self._due = self._due, None
            else:
                try:
                    rec = next(it)
                except StopIteration:
                    break
                except LogFormatError as err:
                    self._fail(err)
                    break
                self.stats.malformed_lines = self.log_stats.malformed_count
                try:
                    msgs = messages_from_record(rec)
                except ValueError as err:  # skipped and counted, as a module does
                    self.unsendable += 1
                    self.first_unsendable = self.first_unsendable or _unsendable(rec, err)
                    continue
                if not msgs:
                    continue
            if self.rate is not None:
                if not sleep_until(self.pacer.due(rec.t_s, time.monotonic()), deadline):
                    self._due = (rec, msgs)  # the timeout comes first: read() says so
                    return
            wire = b"".join(self._encoder.encode(m) for m in msgs)
            recs = [r for m in self.decoder.feed(wire) for r in self.assembler.push(m)]
            if recs:
                self._deliver(recs)
                return
        self.stats.malformed_lines = self.log_stats.malformed_count
        self._end()

"""A pyserial port with a reader thread and reconnect-with-back-off (base of byte drivers).

Any pyserial port or URL works: device paths (``/dev/ttyUSB0``, a pseudo-terminal),
``socket://HOST:PORT``, ``loop://``, ``rfc2217://``. The reader thread feeds the bytes
to a pure decoder (subclass); when the port fails (cable pulled, TCP peer gone,
pty closed) the decoder is flushed so no good packet is lost, the port is closed
and reopened with exponential back-off until :meth:`close`; a pty named by its
``/dev/pts/N`` path is not reopened (its number is reused): the stream ends.
"""

from __future__ import annotations

import contextlib
import select
import socket
import threading
from abc import abstractmethod
from typing import Any

import serial
from serial.urlhandler.protocol_socket import Serial as SocketSerial

from sonarloc.errors import DeviceError
from sonarloc.io.drivers.base import Driver, RecordCallback

_PORT_ERRORS = (serial.SerialException, OSError, ValueError, TypeError)

PTY_SLAVES = "/dev/pts/"
"""A pseudo-terminal named by this path is not reopened once it hangs up: its number goes
to the next terminal opened on the machine (another program's), which the driver would
read from and send Start to. A stable link to it (``serve-sim --pty --link``) is."""

READ_CHUNK = 4096
"""Most bytes one read of a ``socket://`` port takes (what the socket holds, up to this)."""

NETWORK_PORTS = ("socket://", "rfc2217://")
"""URLs of a serial line behind a network bridge (ser2net, a terminal server)."""

REFUSAL_MAX = 200
"""Most bytes of a first connection kept to tell a bridge's refusal (a line of text)."""


class SocketPort(SocketSerial):
    """pyserial's ``socket://`` port, keeping what the other end sent at once.

    pyserial's open throws away the bytes received by then (a "clean start"), and they may
    be all a network bridge says before it closes a connection it refuses (ser2net: ``Port
    already in use``): the host would see a bare hang-up, or the line, by chance."""

    _opening = False

    def open(self) -> None:
        self._opening = True
        try:
            super().open()
        finally:
            self._opening = False

    def reset_input_buffer(self) -> None:
        if not self._opening:
            super().reset_input_buffer()

    def close(self) -> None:
        """Close the connection at once. pyserial's close then sleeps 0.3 s "in case of quick
        reconnects" (its own comment); the driver's reconnects have their back-off, and a
        host stopping (``record`` at its ``--duration``, each test) should not wait."""
        if not getattr(self, "is_open", False):
            return
        sock: socket.socket | None = getattr(self, "_socket", None)
        self._socket = None
        if sock is not None:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)
            sock.close()
        self.is_open = False


def refusal_text(data: bytes) -> str | None:
    """The line a network bridge sent before closing a connection it refused (ser2net:
    ``Port already in use``), or None if ``data`` is not one line of printable text."""
    text = data.decode("ascii", errors="replace").strip()
    if not text or len(data) >= REFUSAL_MAX or "\n" in text \
            or not all(c.isprintable() for c in text):
        return None
    return text


class PortDriver(Driver):
    """Base of drivers that read bytes from a pyserial port.

    Parameters
    ----------
    url : device path or pyserial URL.
    baudrate : line speed (ignored by socket:// and loop://).
    reconnect : reopen the port after a failure (with back-off) instead of failing.
    backoff_s : (first, longest) wait between reopen attempts, seconds.
    read_timeout_s : longest a single port read blocks (how fast close() returns).
    """

    default_baudrate = 115200

    def __init__(self, url: str, *, baudrate: int | None = None, reconnect: bool = True,
                 backoff_s: tuple[float, float] = (0.05, 2.0), read_timeout_s: float = 0.05,
                 on_record: RecordCallback | None = None, queue_size: int = 100_000,
                 **port_options: Any):
        super().__init__(on_record=on_record, queue_size=queue_size)
        if not url:
            raise ValueError("`url` must name a serial device or pyserial URL")
        if not (0 < backoff_s[0] <= backoff_s[1]):
            raise ValueError(f"`backoff_s` must be (first, longest) with 0 < first <= longest, "
                             f"got {backoff_s!r}")
        self.url = url
        self.baudrate = baudrate or self.default_baudrate
        self.reconnect = reconnect
        self.backoff_s = backoff_s
        self.read_timeout_s = read_timeout_s
        self._port_options = port_options
        self._port: serial.SerialBase | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._first_bytes = bytearray()  # of the first connection (see _refused)

    @property
    def source(self) -> str:
        plain = not self.scheme or self.scheme == "serial"
        return self.url if plain else f"{self.scheme}:{self.url}"

    # -- subclass hooks ---------------------------------------------------------------
    @abstractmethod
    def _on_bytes(self, data: bytes) -> None:
        """Decode bytes and deliver records (reader thread)."""

    def _on_connect(self) -> None:
        """After every (re)open, before reading: handshakes, start commands."""

    def _on_stream_end(self) -> None:
        """The byte stream broke or ended: flush the decoder."""

    def _on_idle(self) -> None:
        """Called by the reader thread after every read (keep-alives)."""

    # -- port handling ------------------------------------------------------------------
    def _connect(self) -> serial.SerialBase:
        # A device file is locked for this driver alone (flock, as pyserial's
        # ``exclusive``): a second reader of one tty takes every other chunk of bytes,
        # so both would see corrupt frames and gaps; it now fails to open, naming the
        # port. URL ports (socket://, loop://, ...) have no file to lock.
        options = {"exclusive": "://" not in self.url, **self._port_options}
        try:
            if self.url.startswith("socket://"):  # as serial_for_url does, with our class
                port = SocketPort(None, baudrate=self.baudrate, timeout=0, **options)
                port.port = self.url  # timeout 0: _read waits for the socket (select)
                port.open()
            else:
                port = serial.serial_for_url(self.url, baudrate=self.baudrate,
                                             timeout=self.read_timeout_s, **options)
        except _PORT_ERRORS as err:
            raise DeviceError(f"cannot open {self.source}: {err}") from err
        return port

    def _open(self) -> None:
        self._port = self._connect()
        try:
            self._on_connect()
        except BaseException:
            self._drop_port()
            raise
        self._thread = threading.Thread(target=self._run, name=f"sonarloc {self.source}",
                                        daemon=True)
        self._thread.start()

    def _close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
            self._thread = None
        self._drop_port()
        self._on_stream_end()

    def _drop_port(self) -> None:
        with self._lock:
            port, self._port = self._port, None
        if port is not None:
            try:
                port.close()
            except _PORT_ERRORS:
                pass

    def write(self, data: bytes) -> None:
        """Write raw bytes to the port (DeviceError while disconnected)."""
        with self._lock:
            port = self._port
            if port is None:
                raise DeviceError(f"{self.source}: not connected")
            try:
                port.write(data)
                port.flush()
            except _PORT_ERRORS as err:
                raise DeviceError(f"{self.source}: write failed: {err}") from err

    def _read(self) -> bytes:
        """The bytes waiting at the port, after waiting at most ``read_timeout_s`` for one."""
        port = self._port
        if port is None:
            raise serial.SerialException("port closed")
        if isinstance(port, SocketSerial):
            # pyserial's socket:// in_waiting is only 0 or 1 (readable or not), so the
            # read below took one byte per call: ~20 us of CPU per byte. Wait for the
            # socket here; the port's read (timeout 0) then takes all it holds at once.
            ready, _, _ = select.select([port.fileno()], [], [], self.read_timeout_s)
            return bytes(port.read(READ_CHUNK)) if ready else b""
        # a device or pty: in_waiting is the kernel's count; read(1) waits for a first byte
        return bytes(port.read(port.in_waiting or 1))

    def _run(self) -> None:
        try:
            self._loop()
        except BaseException as err:  # a bug must not die silently: read() reports it
            self._fail(err)
            self._end()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                data = self._read()
            except _PORT_ERRORS + (DeviceError,) as err:
                if not self._lost(err):
                    return
                continue
            if data:  # before the idle hook, which may act on how long the line was quiet
                if len(self._first_bytes) < REFUSAL_MAX and not self.stats.disconnects:
                    self._first_bytes += data[:REFUSAL_MAX]
                self._on_bytes(data)
            try:
                self._on_idle()
            except _PORT_ERRORS + (DeviceError,) as err:
                if not self._lost(err):
                    return

    def _lost(self, err: BaseException) -> bool:
        """The port failed: flush, count, and reopen it; False if the reader must end."""
        if self._stop.is_set():
            return False
        refused = self._refused()
        self.stats.disconnects += 1
        self._drop_port()
        self._on_stream_end()
        if refused is not None:  # not reopened: the other host keeps the line
            self._fail(DeviceError(refused))
            self._end()
            return False
        if not self.reconnect:
            self._fail(err)
            self._end()
            return False
        if self.url.startswith(PTY_SLAVES):  # the module's terminal is gone for good
            self.end_reason = (f"the terminal {self.url} hung up; a {PTY_SLAVES} path is not "
                               f"reopened (its number goes to the next terminal opened; use "
                               f"serve-sim --link, or a stable link to the device)")
            self._end()
            return False
        self._reopen()
        return True

    def _refused(self) -> str | None:
        """Why a network bridge closed the first connection, if it refused it: one line of
        text and nothing else came (ser2net's answer while another host is connected)."""
        if self.stats.disconnects or self.stats.records or not self.url.startswith(
                NETWORK_PORTS):
            return None
        text = refusal_text(bytes(self._first_bytes))
        if text is None:
            return None
        return (f"the other end refused the connection: {text!r} (a module is read by one "
                f"host at a time: another host, such as a second `sonarloc record`, has it)")

    def _reopen(self) -> None:
        delay = self.backoff_s[0]
        while not self._stop.wait(delay):
            try:
                port = self._connect()
            except DeviceError:
                delay = min(2 * delay, self.backoff_s[1])
                continue
            with self._lock:
                self._port = port
            try:
                self._on_connect()
            except (DeviceError,) + _PORT_ERRORS:
                self._drop_port()
                delay = min(2 * delay, self.backoff_s[1])
                continue
            self.stats.reconnects += 1
            return

"""Fixtures of the I/O tests: every test must leave no thread, CAN bus, socket or pty behind.

Like python-can's own test suite, which fails a test that leaks a bus: after each
test we wait briefly for threads to end and then compare against the state before.
"""

from __future__ import annotations

import os
import subprocess
import threading
import time
import tty
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager

import pytest

_WATCHED_FD_KINDS = ("socket:", "/dev/pts", "/dev/ptmx", "pipe:")


def _watched_fds() -> dict[str, str]:
    out = {}
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith(_WATCHED_FD_KINDS):
            out[fd] = target
    return out


def _virtual_buses() -> dict[object, int]:
    from can.interfaces import virtual

    with virtual.channels_lock:
        return {ch: len(qs) for ch, qs in virtual.channels.items() if qs}


@pytest.fixture(autouse=True)
def no_leaks() -> Iterator[None]:
    threads = set(threading.enumerate())
    fds = _watched_fds()
    buses = _virtual_buses()
    yield
    deadline = time.monotonic() + 3.0
    while True:
        extra = [t for t in threading.enumerate() if t not in threads and t.is_alive()]
        new_fds = {k: v for k, v in _watched_fds().items() if fds.get(k) != v}
        new_buses = {ch: n for ch, n in _virtual_buses().items() if n > buses.get(ch, 0)}
        if not (extra or new_fds or new_buses) or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not extra, f"test leaked threads: {[t.name for t in extra]}"
    assert not new_buses, f"test leaked virtual CAN buses: {new_buses}"
    assert not new_fds, f"test leaked file descriptors: {new_fds}"


RecordOnPty = Callable[..., AbstractContextManager[tuple["subprocess.Popen[str]", int]]]


@pytest.fixture
def record_on_pty(cli_command) -> RecordOnPty:
    """``with record_on_pty(*ARGS, scheme="") as (proc, master)``: ``sonarloc record`` of a
    raw pseudo-terminal (``scheme``: a driver's prefix, e.g. ``"maxbotix:"``) with ARGS,
    stderr piped, the terminal's other end ``master`` to write the device's bytes to; the
    process is killed if it still runs at the end, and the pty closed."""

    @contextmanager
    def run(*args: str, scheme: str = "") -> Iterator[tuple[subprocess.Popen[str], int]]:
        master, slave = os.openpty()
        tty.setraw(slave)
        try:
            argv, env = cli_command("record", scheme + os.ttyname(slave), *args)
            proc = subprocess.Popen(argv, env=env, stderr=subprocess.PIPE, text=True)
            try:
                yield proc, master
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.communicate()
        finally:
            os.close(slave)
            os.close(master)

    return run

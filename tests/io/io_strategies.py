"""Hypothesis strategies for protocol messages and log records (shared by the I/O tests)."""

from __future__ import annotations

from hypothesis import strategies as st

from sonarloc.io.logfile import OdomRecord, RigRecord, SensorMount, TofRecord
from sonarloc.io.protocol.messages import (
    Ack,
    Echo,
    Firing,
    Odom,
    RequestRig,
    RigInfo,
    RigMount,
    Settings,
    Start,
    Stop,
)


def ints(lo: int, hi: int) -> st.SearchStrategy[int]:
    return st.integers(min_value=lo, max_value=hi)


u8, u16, u32 = ints(0, 0xFF), ints(0, 0xFFFF), ints(0, 0xFFFF_FFFF)
i16 = ints(-0x8000, 0x7FFF)


@st.composite
def echoes(draw: st.DrawFn) -> Echo:
    no_echo = draw(st.booleans())
    return Echo(draw(u8), draw(u32), 0 if no_echo else draw(u16), no_echo,
                draw(st.none() | i16))


@st.composite
def firings(draw: st.DrawFn) -> Firing:
    n = draw(ints(1, 0xFF))
    return Firing(draw(ints(0, n - 1)), n, draw(u16), draw(u32))


def odoms(xy_bits: int = 32, yaw_bits: int = 32) -> st.SearchStrategy[Odom]:
    xy = ints(-(1 << (xy_bits - 1)), (1 << (xy_bits - 1)) - 1)
    return st.builds(Odom, u32, xy, xy, ints(-(1 << (yaw_bits - 1)), (1 << (yaw_bits - 1)) - 1))


def messages(can: bool = False) -> st.SearchStrategy:
    """Any protocol message; ``can=True`` keeps odometry within the CAN frame's ranges."""
    return st.one_of(
        echoes(),
        odoms(28, 24) if can else odoms(),
        st.builds(RigInfo, u32, u16, ints(1, 0xFF)),
        st.builds(RigMount, u8, i16, i16, i16),
        st.builds(Ack, u8, u16, u8),
        st.just(Start()), st.just(Stop()), st.just(RequestRig()),
        firings(),
        st.builds(Settings, u8, ints(-128, 127), u16, u16),
    )


finite = st.floats(allow_nan=False, allow_infinity=False)
times = st.floats(min_value=0.0, max_value=2000.0, allow_nan=False)  # < half a clock wrap


def tof_records() -> st.SearchStrategy[TofRecord]:
    return st.builds(TofRecord, times, u8, st.none() | st.floats(0.0, 131000.0),
                     st.none() | st.floats(-300.0, 300.0))


def odom_records() -> st.SearchStrategy[OdomRecord]:
    return st.builds(OdomRecord, times, st.floats(-1e4, 1e4), st.floats(-1e4, 1e4),
                     st.floats(-1e4, 1e4), st.booleans())


@st.composite
def rig_records(draw: st.DrawFn) -> RigRecord:
    ids = draw(st.lists(u8, min_size=1, max_size=40, unique=True))
    mounts = tuple(SensorMount(i, draw(st.floats(-3.2, 3.2)), draw(st.floats(-3.2, 3.2)),
                               draw(st.floats(-180.0, 180.0))) for i in ids)
    return RigRecord(mounts, draw(st.floats(300.0, 400.0)), draw(times))

"""Wire protocols of the sonar module: pure encoders and decoders (no I/O).

* :mod:`.messages` — the messages, in wire units, and the decoder counters;
* :mod:`.framing` — serial packets (sync 0xFA 0xFB, length, type, sequence, CRC-16);
* :mod:`.canbus` — the same messages as classic CAN frames (DBC + cantools);
* :mod:`.records` — between messages and log records;
* :mod:`.sip` — Pioneer ARCOS server information packets and client commands;
* :mod:`.maxbotix` — MaxBotix ``R####\\r`` ASCII ranges.

The specification is docs/PROTOCOL.md.
"""

from typing import Any

from sonarloc.io.protocol.framing import SerialDecoder, SerialEncoder, crc16, encode_packet
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
    Settings,
    Start,
    Stop,
)
from sonarloc.io.protocol.records import RecordAssembler, messages_from_record

_LAZY = {"CanDecoder", "CanEncoder", "load_dbc"}  # cantools is imported only when needed


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        from sonarloc.io.protocol import canbus

        return getattr(canbus, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "Ack", "CanDecoder", "CanEncoder", "DecoderStats", "Echo", "Firing", "Message", "Odom",
    "RecordAssembler", "RequestRig", "RigInfo", "RigMount", "SerialDecoder", "SerialEncoder",
    "Settings", "Start", "Stop", "crc16", "encode_packet", "load_dbc", "messages_from_record",
]

"""Device drivers, looked up by name or URL scheme (like python-can's ``BACKENDS``).

======================  ============================================================
source                  driver
======================  ============================================================
``/dev/ttyUSB0``,       :class:`~.serial.SerialDriver` — the module protocol on a
``socket://H:P``,       serial line or any pyserial URL (also ``serial:PATH``)
``loop://``, ...
``can:IFACE:CHANNEL``   :class:`~.can.CanDriver` — the module protocol on python-can
``candump:FILE.log``    :class:`~.candump.CandumpDriver` — a CAN log file
``sim:LOG.jsonl``       :class:`~.sim.SimDriver` — a log through the codec, no wire
``pioneer:PORT``        :class:`~.pioneer.PioneerDriver` — Pioneer ARCOS robots
``maxbotix:PORT``       :class:`~.maxbotix.MaxbotixDriver` — MaxBotix ASCII sensors
======================  ============================================================

Modules are imported only when their driver is used.
"""

from __future__ import annotations

import importlib
from typing import Any

from sonarloc.io.drivers.base import Driver, DriverStats

# name -> (module, class). Keep in the order of the table above.
BACKENDS: dict[str, tuple[str, str]] = {
    "serial": ("sonarloc.io.drivers.serial", "SerialDriver"),
    "can": ("sonarloc.io.drivers.can", "CanDriver"),
    "candump": ("sonarloc.io.drivers.candump", "CandumpDriver"),
    "sim": ("sonarloc.io.drivers.sim", "SimDriver"),
    "pioneer": ("sonarloc.io.drivers.pioneer", "PioneerDriver"),
    "maxbotix": ("sonarloc.io.drivers.maxbotix", "MaxbotixDriver"),
}


def driver_class(name: str) -> type[Driver]:
    """The driver class registered under ``name`` (imported now)."""
    try:
        module_name, class_name = BACKENDS[name]
    except KeyError:
        raise ValueError(f"unknown driver {name!r}; known: {', '.join(BACKENDS)}") from None
    cls = getattr(importlib.import_module(module_name), class_name)
    if not (isinstance(cls, type) and issubclass(cls, Driver)):
        raise TypeError(f"{module_name}.{class_name} is not a Driver")
    return cls


def parse_source(source: str) -> tuple[str, tuple[Any, ...]]:
    """(driver name, positional arguments) of a source string (FORMATS.md section 6).

    Examples
    --------
    >>> parse_source("can:virtual:bus0")
    ('can', ('virtual', 'bus0'))
    >>> parse_source("socket://127.0.0.1:5000")
    ('serial', ('socket://127.0.0.1:5000',))
    >>> parse_source("pioneer:/dev/ttyS0")
    ('pioneer', ('/dev/ttyS0',))
    """
    if not source:
        raise ValueError("the source must not be empty")
    scheme, sep, rest = source.partition(":")
    if sep and rest.startswith("//"):  # a pyserial URL: socket://, loop://, rfc2217://
        return "serial", (source,)
    if sep and scheme in BACKENDS:
        if not rest:
            raise ValueError(f"source {source!r} names no {scheme} target")
        if scheme == "can":
            interface, sep2, channel = rest.partition(":")
            if not (interface and sep2 and channel):
                raise ValueError(f"CAN source must be can:INTERFACE:CHANNEL, got {source!r}")
            return "can", (interface, channel)
        return scheme, (rest,)
    if sep and len(scheme) > 1 and scheme.isidentifier():
        # "maxbotics:/dev/ttyUSB0" is a mistyped scheme, not a device: say so, rather than
        # let pyserial fail to open a port of that name (device paths start with / or are
        # names like COM3; a drive letter "C:" is one character)
        raise ValueError(f"unknown source scheme {scheme!r} in {source!r}; known: "
                         f"{', '.join(BACKENDS)}, a device path or a pyserial URL "
                         "(socket://HOST:PORT, loop://)")
    return "serial", (source,)  # a device path


def open_driver(source: str, **options: Any) -> Driver:
    """Create and open the driver for ``source``; ``options`` go to its constructor.

    Examples
    --------
    >>> drv = open_driver("can:virtual:doc", start=False)
    >>> drv.source
    'can:virtual:doc'
    >>> drv.close()
    """
    name, args = parse_source(source)
    return driver_class(name)(*args, **options).open()


__all__ = ["BACKENDS", "Driver", "DriverStats", "driver_class", "open_driver", "parse_source"]

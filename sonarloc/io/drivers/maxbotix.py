"""MaxBotix MaxSonar sensors on a serial line: ``R####\\r`` ranges (``maxbotix:PORT``).

One sensor per port. Each range becomes a ``tof`` record (time of flight
``2 r / c``) stamped with the host's clock since the driver opened; a reading at
the sensor's maximum is no echo. The rig is that one sensor at ``mount``
(base_link x, y in metres, yaw in degrees), delivered first.
"""

from __future__ import annotations

import time
from typing import Any

from sonarloc.io.drivers.port import PortDriver
from sonarloc.io.logfile import RigRecord, SensorMount, TofRecord
from sonarloc.io.protocol.maxbotix import MaxbotixDecoder
from sonarloc.io.protocol.messages import DecoderStats
from sonarloc.physics.sound import check_air_speed_of_sound

UNITS_M = {"mm": 1e-3, "cm": 1e-2, "in": 0.0254}
DEFAULT_MAX = {"mm": 5000, "cm": 765, "in": 254}  # HRLV-MaxSonar, XL-MaxSonar, LV-MaxSonar
DIGITS = {"mm": 4, "cm": 3, "in": 3}  # digits per frame


class MaxbotixDriver(PortDriver):
    """Reads a MaxBotix sensor's ASCII output.

    Parameters
    ----------
    url : serial device or pyserial URL.
    unit : ``mm`` (4-digit models), ``cm`` (XL) or ``in`` (LV).
    sensor : transducer id in the log.
    mount : (x_m, y_m, yaw_deg) of the sensor in ``base_link``.
    max_value : reading meaning "nothing in range" (default per unit).
    speed_of_sound_mps : to turn ranges into times of flight.
    """

    scheme = "maxbotix"
    default_baudrate = 9600

    def __init__(self, url: str, *, unit: str = "mm", sensor: int = 0,
                 mount: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 max_value: int | None = None, speed_of_sound_mps: float = 343.0,
                 **kwargs: Any):
        super().__init__(url, **kwargs)
        if unit not in UNITS_M:
            raise ValueError(f"`unit` must be one of {', '.join(UNITS_M)}, got {unit!r}")
        check_air_speed_of_sound(speed_of_sound_mps, "`speed_of_sound_mps`")
        self.unit_m = UNITS_M[unit]
        self.max_value = DEFAULT_MAX[unit] if max_value is None else int(max_value)
        self.sensor = int(sensor)
        self.c = speed_of_sound_mps
        try:
            x_m, y_m, yaw_deg = (float(v) for v in mount)
        except (TypeError, ValueError):
            raise ValueError(f"`mount` must be x_m, y_m, yaw_deg in base_link (e.g. "
                             f"0.1,0,90), got {mount!r}") from None
        self.rig = RigRecord((SensorMount(self.sensor, x_m, y_m, yaw_deg),), speed_of_sound_mps)
        self.decoder = MaxbotixDecoder(DIGITS[unit])
        self._t0 = time.monotonic()
        self._rig_sent = False

    @property
    def decoder_stats(self) -> DecoderStats:
        return self.decoder.stats

    def _on_connect(self) -> None:
        if not self._rig_sent:
            self._rig_sent = True
            self._deliver([self.rig])

    def _records(self, values: list[int]) -> list[TofRecord]:
        t = time.monotonic() - self._t0
        return [TofRecord(t, self.sensor, None if v >= self.max_value
                          else 2.0 * v * self.unit_m / self.c * 1e6) for v in values]

    def _on_bytes(self, data: bytes) -> None:
        self._deliver(list(self._records(self.decoder.feed(data))))

    def _on_stream_end(self) -> None:
        self._deliver(list(self._records(self.decoder.flush())))

"""MaxBotix ASCII range output: ``R`` + 3 or 4 decimal digits + carriage return.

The MaxSonar serial output (9600 8N1) repeats ``R####\\r`` once per reading: four
digits in millimetres on the HRLV/HRXL models, three digits (inches on the LV,
centimetres on the XL models) on others; the unit is the driver's to say.
:class:`MaxbotixDecoder` is pure and keeps at most five bytes between calls.
"""

from __future__ import annotations

from sonarloc.io.protocol.messages import DecoderStats

_DIGITS = frozenset(b"0123456789")
_CR = 13
_MAX_DIGITS = 4
_MIN_DIGITS = 3


def encode_range(value: int, digits: int = 4) -> bytes:
    """The frame a sensor sends for ``value`` (for simulated sensors and tests)."""
    if digits not in (3, 4):
        raise ValueError(f"`digits` must be 3 or 4, got {digits}")
    if not 0 <= value < 10 ** digits:
        raise ValueError(f"`value` must fit {digits} digits, got {value}")
    return b"R" + str(value).zfill(digits).encode("ascii") + b"\r"


class MaxbotixDecoder:
    """Bytes in, range values (in the sensor's unit) out, with counters.

    ``digits``: the number of digits the sensor sends (4 in mm, 3 in cm or inches), so
    that a frame that lost a digit to line noise is counted (``bad_length``) rather than
    read as a range ten times too short; None takes 3 or 4.
    """

    def __init__(self, digits: int | None = None) -> None:
        if digits not in (None, _MIN_DIGITS, _MAX_DIGITS):
            raise ValueError(f"`digits` must be 3, 4 or None, got {digits!r}")
        self.stats = DecoderStats()
        self._buf = bytearray()
        self._digits = (_MIN_DIGITS, _MAX_DIGITS) if digits is None else (digits, digits)

    @property
    def pending(self) -> int:
        return len(self._buf)

    def feed(self, data: bytes | bytearray | memoryview) -> list[int]:
        self.stats.bytes_in += len(data)
        self._buf += data
        return self._scan(final=False)

    def flush(self) -> list[int]:
        return self._scan(final=True)

    def _scan(self, final: bool) -> list[int]:
        buf, stats = self._buf, self.stats
        out: list[int] = []
        n, pos, skipped = len(buf), 0, 0
        while True:
            i = buf.find(b"R", pos)
            if i < 0:
                skipped += n - pos
                pos = n
                break
            skipped += i - pos
            pos = i
            j = pos + 1
            while j < n and j - pos <= _MAX_DIGITS + 1 and buf[j] in _DIGITS:
                j += 1
            digits = j - pos - 1
            if digits > _MAX_DIGITS:
                stats.bad_length += 1
            elif j == n:
                if final:
                    skipped += n - pos
                    pos = n
                break  # wait for the rest
            elif buf[j] == _CR:
                if self._digits[0] <= digits <= self._digits[1]:
                    out.append(int(buf[pos + 1:j]))
                    stats.frames += 1
                    stats.bytes_framed += j + 1 - pos
                    pos = j + 1
                    continue
                stats.bad_length += 1
            skipped += 1
            pos += 1
        stats.bytes_skipped += skipped
        if pos:
            del buf[:pos]
        return out

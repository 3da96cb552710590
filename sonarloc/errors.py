"""The one exception tree of sonarloc.

Bad *arguments* raise :class:`ValueError` naming the parameter and value.
Bad *input data* (files, frames, devices) raise a :class:`SonarlocError` subclass.
Numerical trouble is never an exception: fits and filter updates return results
that carry a status and a reason.
"""

from __future__ import annotations


class SonarlocError(Exception):
    """Base class of every error sonarloc raises on bad input or device trouble."""


class MapError(SonarlocError):
    """A map file or map feature is invalid (the message names the feature index)."""


class LogFormatError(SonarlocError):
    """A log or scan file is malformed (the message names the line number)."""


class DeviceError(SonarlocError):
    """A sonar device or bus failed or could not be opened."""


class DeviceTimeoutError(DeviceError, TimeoutError):
    """No data arrived from a device within the timeout."""


class FitWorkerError(SonarlocError):
    """A landmark fit in a background worker (``LocalizerConfig.fit_workers``) failed;
    the worker's exception is the ``__cause__``."""

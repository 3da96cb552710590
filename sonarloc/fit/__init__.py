"""Landmarks from TOF curves: segmentation, separable least squares, CRLB, model selection.

Pure functions over arrays; no I/O, no hidden state.
"""

from sonarloc.fit.result import FitStatus, Landmark

__all__ = ["FitStatus", "Landmark"]

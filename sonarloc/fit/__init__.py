"""Landmarks from TOF curves: segmentation, separable least squares, CRLB, model selection.

Pure functions over arrays (``model``, ``lsq``, ``crlb``, ``select``), and one stateful
object, the online :class:`~sonarloc.fit.segment.Segmenter` (wrapped with fitting in
:class:`~sonarloc.fit.landmarks.OnlineFitter`). No I/O. See docs/FITTING.md.
"""

from sonarloc.fit.crlb import crlb
from sonarloc.fit.landmarks import OnlineFitter, fit_scan, fit_segments
from sonarloc.fit.lsq import FitConfig, fit_batch, pack_segments
from sonarloc.fit.result import FitStatus, Landmark
from sonarloc.fit.segment import Segmenter, SegmenterConfig

__all__ = ["FitConfig", "FitStatus", "Landmark", "OnlineFitter", "Segmenter",
           "SegmenterConfig", "crlb", "fit_batch", "fit_scan", "fit_segments",
           "pack_segments"]

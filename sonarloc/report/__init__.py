"""Reports for people: benchmark tables, plots (matplotlib, optional extra ``plot``), drive reports.

Nothing here is needed by the estimation pipeline; matplotlib is imported only when a
plot is drawn (:func:`sonarloc.report.plots.require_matplotlib`).
"""

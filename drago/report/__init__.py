"""One page summarising any set of runs: tables with confidence intervals, curves, heatmaps, gaps.

:func:`build_report` reads run directories (several methods x several seeds, finished or not), groups
them by method (transfer runs, found in ``RUN_DIR/transfer/`` or given directly, apart: by test case
and method) and writes a self-contained HTML page (inline CSS, figures as data URIs, nothing
fetched) and a Markdown version with the figures as PNG files beside it. Both show the same tables,
built once as data (:mod:`drago.report.content`) and only rendered twice (:mod:`drago.report.render`).

Nothing is written into the run directories: coverage missing from a run (or out of date) is
computed in memory from its checkpoints, so a report can be built while experiments are running.
Whatever the runs do not (yet) provide is listed in a "Missing" section rather than left out silently.

The modules: :mod:`~drago.report.runs` reads runs, :mod:`~drago.report.tables` and
:mod:`~drago.report.transfers` build tables, :mod:`~drago.report.figures` and
:mod:`~drago.report.heatmap` draw figures, :mod:`~drago.report.render` renders, and
:mod:`~drago.report.build` puts it together.
"""

from __future__ import annotations

from drago.report.build import build_report
from drago.report.runs import ReportError, find_run_dirs, find_transfer_dirs
from drago.report.transfers import TRANSFERS_CSV, TRANSFERS_MD, write_transfer_tables

__all__ = ["TRANSFERS_CSV", "TRANSFERS_MD", "ReportError", "build_report", "find_run_dirs", "find_transfer_dirs",
           "write_transfer_tables"]

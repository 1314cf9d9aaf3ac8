"""The HTML report of a run, one module per section; `render` assembles the page."""

from falsify.reports.run.report import WORST, ReportInput, render
from falsify.reports.run.worst import ReplayedScan

__all__ = ["WORST", "ReplayedScan", "ReportInput", "render"]

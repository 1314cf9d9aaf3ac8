"""Reports: HTML pages drawn from what they are given (a run's report, the trade-off page)."""

from falsify.reports.run import ReplayedScan, ReportInput, render

__all__ = ["ReplayedScan", "ReportInput", "render"]

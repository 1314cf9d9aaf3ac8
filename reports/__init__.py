"""Reports: HTML pages drawn from what they are given (a run's report, the trade-off page)."""

from reports.html import render_report, write_report

__all__ = ["render_report", "write_report"]

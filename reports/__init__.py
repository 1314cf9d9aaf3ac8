"""Reports of a run: one self-contained HTML page (`falsify report`) and the CI gate wiring."""

from reports.html import render_report, write_report

__all__ = ["render_report", "write_report"]

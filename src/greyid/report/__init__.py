"""Reports of fits: a self-contained HTML file with equations, tables and figures."""

from .html import SECTIONS, html_report, write_report

__all__ = ["html_report", "write_report", "SECTIONS"]

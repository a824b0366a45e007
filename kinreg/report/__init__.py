"""Rendering of results: CSV tables, report.json, report.html."""

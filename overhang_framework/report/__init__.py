"""Sweep aggregation and reports: ``results.csv`` for a sweep, ``report.md`` and figures for any results."""

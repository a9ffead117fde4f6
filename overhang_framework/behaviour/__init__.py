"""Behaviour: the log format that people, simulated participants and models all write, and its readers.

* :mod:`overhang_framework.behaviour.log`: the record format (``schema.json``),
  :func:`read_log` (records sorted by participant, trial and step), :func:`write_log`, :func:`to_csv`,
  :class:`LogError`, and :func:`last_records` (each trial's last step, for rows in any order);
* :mod:`overhang_framework.behaviour.convert`: model runs as logs (:func:`from_run`).

The names below are imported from those modules when first used, so running
either module with ``python -m`` does not import it twice.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from overhang_framework.behaviour.convert import from_run, from_runs
    from overhang_framework.behaviour.log import (
        COLUMNS,
        FIELDS,
        LOG_VERSION,
        LogError,
        in_step_order,
        last_records,
        read_log,
        records_of,
        to_csv,
        to_frame,
        write_log,
    )

_EXPORTS = {
    "COLUMNS": "log", "FIELDS": "log", "LOG_VERSION": "log", "LogError": "log", "read_log": "log",
    "in_step_order": "log", "last_records": "log",
    "records_of": "log", "to_csv": "log", "to_frame": "log", "write_log": "log",
    "from_run": "convert", "from_runs": "convert",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)

"""The practice towers file: its key, its reading and the tolerance it is kept for.

The server (:func:`overhang_framework.experiment.settings.practice_tasks`) reads what the practice command
(:mod:`overhang_framework.experiment.practice`) computes and writes; both take the file's terms from here.
"""

from __future__ import annotations

from pathlib import Path

from overhang_framework.errors import ConfigError
from overhang_framework.interfaces import Task, World
from overhang_framework.optimum import load_keyed, physics_id, sequence_key

DATA_FILE = Path(__file__).resolve().parents[1] / "data" / "practice_towers.json"
#: Tolerances from 0 up to (not including) this: below it no two blocks (at least 0.6 wide each) can pass
#: through one another between two corners of the check.
MAX_TOLERANCE = 0.3
COMMAND = "python -m overhang_framework.experiment.practice"


def check_tolerance(value, key: str = "practice.tolerance") -> float:
    """``value`` as a tolerance in units, or :class:`ConfigError` naming ``key`` and the allowed range."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 <= value < MAX_TOLERANCE:
        raise ConfigError(f"{key} must be a number of units in [0, {MAX_TOLERANCE:g}), got {value!r}")
    return float(value)


def tower_key(task: Task, world: World, tolerance: float) -> str:
    """The key of a task's buildable tower under a world's physics and resolution, for ``tolerance``."""
    return sequence_key(task.sequence, {**physics_id(world), "tolerance": round(float(tolerance), 9)})


def load_towers(path: Path | str | None = None) -> dict:
    """The buildable towers kept in ``path`` (default: the project's file), by :func:`tower_key`."""
    return load_keyed(DATA_FILE if path is None else path, "towers")

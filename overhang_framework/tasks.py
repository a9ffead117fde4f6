"""Task sets: block sequences from config or the command line."""

from __future__ import annotations

import numbers
from typing import Any, Iterable, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.errors import TaskError
from overhang_framework.geometry import WIDTHS, IllegalWidth, check_width
from overhang_framework.interfaces import Task


def generate_sequences(n: int, length: int, seed: int) -> list[list[float]]:
    """``n`` sequences of ``length`` widths drawn uniformly from :data:`WIDTHS` with ``seed``."""
    rng = np.random.default_rng(seed)
    return [[WIDTHS[i] for i in rng.integers(len(WIDTHS), size=length)] for _ in range(n)]


def parse_tasks(sequences: Optional[Sequence[Any]], ids: Optional[Sequence[Any]] = None,
                prefix: str = "task") -> list[Task]:
    """Validate ``sequences`` (lists of widths, at least two each) into :class:`Task` objects."""
    if not sequences:
        raise TaskError("no task sequences given; set tasks=paper20 or tasks.sequences=[[0.6,1.2,...],...]")
    if ids is not None and (isinstance(ids, (str, bytes)) or not isinstance(ids, Sequence)):
        raise TaskError(f"tasks.ids must be a list of ids, one per sequence, got {ids!r}")
    if ids is not None and len(ids) != len(sequences):
        raise TaskError(f"tasks.ids has {len(ids)} entries but there are {len(sequences)} sequences")
    tasks = []
    for i, seq in enumerate(sequences):
        task_id = str(ids[i]) if ids is not None else f"{prefix}{i:02d}"
        if isinstance(seq, (str, bytes)) or not isinstance(seq, Iterable):
            raise TaskError(f"task {task_id}: a sequence must be a list of widths, got {seq!r}")
        seq = list(seq)
        if len(seq) < 2:
            raise TaskError(f"task {task_id}: a sequence needs the ground block and at least one more, got {seq!r}")
        for w in seq:
            if isinstance(w, bool) or not isinstance(w, numbers.Real):
                raise TaskError(f"task {task_id}: width {w!r} is not a number; allowed widths are "
                                f"{', '.join(map(str, WIDTHS))}")
        try:
            widths = tuple(check_width(float(w)) for w in seq)
        except IllegalWidth as err:
            raise TaskError(f"task {task_id}: {err}") from None
        tasks.append(Task(task_id, widths))
    if len({t.id for t in tasks}) != len(tasks):
        raise TaskError("task ids must be unique")
    return tasks


def tasks_from_config(cfg: Mapping[str, Any]) -> list[Task]:
    """The tasks of a ``tasks`` config group entry, restricted to ``only`` when it is set."""
    seed = cfg.get("generator_seed")
    sequences = cfg.get("sequences")
    count = cfg.get("count")
    if not sequences and seed is not None and count is not None:
        length = cfg.get("length", 6)
        for name, value, least in (("count", count, 1), ("length", length, 2), ("generator_seed", seed, 0)):
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise TaskError(f"tasks.{name} must be a whole number >= {least}, got {value!r}")
        sequences = generate_sequences(count, length, seed=seed)
    if seed is not None and sequences:
        expected = generate_sequences(len(sequences), len(sequences[0]), seed=seed)
        if [list(map(float, s)) for s in sequences] != expected:
            raise TaskError(f"tasks.sequences of {cfg.get('name')} were changed; for your own sequences use "
                            "tasks=custom 'tasks.sequences=[[0.6,1.2,...],...]'")
    tasks = parse_tasks(sequences, cfg.get("ids"), prefix=str(cfg.get("prefix", "task")))
    only = cfg.get("only")
    if only:
        wanted = [only] if isinstance(only, str) else [str(x) for x in only]
        known = {t.id for t in tasks}
        missing = [x for x in wanted if x not in known]
        if missing:
            raise TaskError(f"tasks.only names unknown task ids {missing}; known ids: {', '.join(sorted(known))}")
        tasks = [t for t in tasks if t.id in set(wanted)]
    return tasks

"""One fit job: read the logs, fit its share of participants (and pooled conditions), aggregate every job's rows.

The work is split into *units*: every participant (sorted by id), then every
condition pooled. A job does the units ``k`` with ``k % shards == shard`` and
writes its rows to ``DIR/parts/shard-<shard>-of-<shards>.csv`` (atomically). Every job
then rebuilds ``DIR/fits.csv`` and ``DIR/comparison.md`` from all parts there,
under a lock, so the last job of a multirun leaves them complete, and a job
run again (with a warm score cache) replaces only its own part.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Optional, Sequence

import pandas as pd

from overhang_framework.errors import OverhangError
from overhang_framework.fit.fitting import ModelFit, Placement, fit_index, log_placements, map_placements
from overhang_framework.fit.scores import ScoreCache, ScoreTables, TableStats
from overhang_framework.fit.space import ModelIndex
from overhang_framework.results import atomic_write_json, atomic_write_text, readable

PARTS = "parts"
FITS = "fits.csv"
FIT_JSON = "fit.json"
#: The columns of fits.csv, in order.
COLUMNS = ["participant", "condition", "model", "family", "depth", "sigma", "beta", "lapse", "loglik", "k", "n",
           "bic", "aic", "unmapped"]
POOLED = "pooled:"


@dataclass
class Unit:
    """What one fit is about: a participant, or the pooled participants of a condition."""

    name: str
    condition: str
    placements: list[Placement]


def units_of(placements: Sequence[Placement], pooled: bool) -> list[Unit]:
    by_participant: dict[str, list[Placement]] = {}
    for p in placements:
        by_participant.setdefault(p.participant, []).append(p)
    units = []
    for pid in sorted(by_participant):
        ps = by_participant[pid]
        conditions = {p.condition for p in ps}
        units.append(Unit(pid, ps[0].condition if len(conditions) == 1 else "mixed", ps))
    if pooled:
        by_condition: dict[str, list[Placement]] = {}
        for p in placements:
            by_condition.setdefault(p.condition, []).append(p)
        units += [Unit(POOLED + c, c, ps) for c, ps in sorted(by_condition.items())]
    return units


@dataclass
class JobResult:
    fits: list[ModelFit]
    stats: dict[str, TableStats] = field(default_factory=dict)
    seconds: float = 0.0


def fit_units(units: Sequence[Unit], world, value, context: Mapping[str, Any], space: Sequence[ModelIndex],
              cache: Optional[ScoreCache], build_predictor: Callable[[Mapping[str, Any]], Any],
              on_unit: Callable[[str, Unit], None] = lambda label, unit: None) -> JobResult:
    """Fit every model index of ``space`` to every unit. Tables are shared across units (one
    :class:`ScoreTables` per model) and kept in ``cache``."""
    started = time.perf_counter()
    mapped = {u.name: map_placements(world, u.placements) for u in units}
    fits: list[ModelFit] = []
    stats: dict[str, TableStats] = {}
    for index in space:
        variants = [ScoreTables(world, value, build_predictor(m.predictor), m, context, cache) for m in index.variants]
        for unit in units:
            fits.append(fit_index(unit.name, unit.condition, variants, mapped[unit.name]))
            on_unit(index.label, unit)
        total = TableStats()
        for v in variants:
            for name in ("asked", "computed", "cached", "predictor_calls", "seconds"):
                setattr(total, name, getattr(total, name) + getattr(v.stats, name))
        stats[index.label] = total
    return JobResult(fits, stats, time.perf_counter() - started)


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def check_directory(out: Path, description: Mapping[str, Any]) -> None:
    """Refuse a results directory that holds fits of another log or model space; record this one's."""
    path = out / FIT_JSON
    with _locked(out / ".fit.lock"):
        if path.exists():
            try:
                previous = json.loads(path.read_text())
            except ValueError:
                raise OverhangError(f"{path} is not a fit description; move it away or use another --out") from None
            description = json.loads(json.dumps(readable(dict(description))))  # as the file holds it
            if previous != description:
                keys = sorted(k for k in set(previous) | set(description) if previous.get(k) != description.get(k))
                raise OverhangError(f"{out} holds fits of another {' and '.join(keys)}; use another --out, "
                                    f"or remove {path} and {out / PARTS} to start again")
        else:
            atomic_write_json(path, dict(description))


def write_part(out: Path, shard: int, shards: int, fits: Sequence[ModelFit]) -> Path:
    parts = out / PARTS
    parts.mkdir(parents=True, exist_ok=True)
    path = parts / f"shard-{shard}-of-{shards}.csv"
    atomic_write_text(path, pd.DataFrame([f.row() for f in fits], columns=COLUMNS).to_csv(index=False))
    return path


def aggregate(out: Path, shards: int) -> Optional[pd.DataFrame]:
    """``fits.csv`` from every part of a ``shards``-way split, when every part is there; None otherwise."""
    paths = [out / PARTS / f"shard-{k}-of-{shards}.csv" for k in range(shards)]
    if not all(p.exists() for p in paths):
        return None
    df = pd.concat([pd.read_csv(p) for p in paths], ignore_index=True)
    df = df.sort_values(["participant", "model"], kind="stable").reset_index(drop=True)
    atomic_write_text(out / FITS, df.to_csv(index=False))
    return df

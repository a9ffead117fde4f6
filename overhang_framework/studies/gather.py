"""Participants simulated already, taken as one study (``--sim DIR``): which runs may serve, and their logs and
tables gathered into the study's ``sim/``."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Optional, Sequence

import pandas as pd

from overhang_framework.errors import ConfigError
from overhang_framework.results import atomic_write_text
from overhang_framework.rundir import run_config


def population(config: Mapping, condition: str) -> dict:
    """What the participants of ``condition`` in a participants run of ``config`` (its ``run.json`` config, or a
    composed participants config) are drawn from and do: their parameters' distributions and decision times
    (the cohort's, with the condition's own on top, key by key), the motor noise, the task set, the condition's
    limits, the models and the world, and how many of the tasks each does (``cohort.n_tasks``); not how the
    work is done (``world.workers``, ``world.cache``). Two runs whose populations for a condition are equal
    simulate the same people there, whatever their cohorts are called (a graded study's 5 s and no-limit
    levels are ``cohort=paper_people``'s two conditions)."""
    cohort = dict(config.get("cohort") or {})
    own = dict((cohort.get("by_condition") or {}).get(condition) or {})
    world = {k: v for k, v in dict(config.get("world") or {}).items() if k not in ("workers", "cache")}
    return {
        "parameters": {**(cohort.get("parameters") or {}), **(own.get("parameters") or {})},
        "decision_time": {**(cohort.get("decision_time") or {}), **(own.get("decision_time") or {})},
        "motor": cohort.get("motor"), "n_tasks": cohort.get("n_tasks"),
        "condition": dict((config.get("conditions") or {}).get(condition) or {}),
        **{k: config.get(k) for k in ("planner", "predictor", "value", "tasks")}, "world": world,
    }


def _differences(a: Mapping, b: Mapping, prefix: str = "") -> list[str]:
    """The dotted keys where two nested configs differ (numbers equal to 9 digits are equal)."""
    out = []
    for key in sorted(set(a) | set(b), key=str):
        x, y = a.get(key), b.get(key)
        if isinstance(x, Mapping) and isinstance(y, Mapping):
            out += _differences(x, y, f"{prefix}{key}.")
        elif not _same(x, y):
            out.append(f"{prefix}{key}")
    return out


def _same(x, y) -> bool:
    """Equal values, numbers to 9 digits (a run.json keeps its numbers to 12), lists item by item."""
    if _numbers(x, y):
        return math.isclose(x, y, rel_tol=1e-9, abs_tol=1e-12)
    if isinstance(x, (list, tuple)) and isinstance(y, (list, tuple)):
        return len(x) == len(y) and all(_same(a, b) for a, b in zip(x, y))
    if isinstance(x, Mapping) and isinstance(y, Mapping):
        return not _differences(x, y)
    return x == y


def _numbers(*values) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)


def gather(sims: Sequence[str | Path], into: Path, cohort: str, conditions: Sequence[str],
           physics: Optional[str] = None, config: Optional[Mapping] = None,
           screened: Optional[dict[str, int]] = None) -> dict[str, int]:
    """Take the participants of finished simulations (each a run directory of ``python -m
    overhang_framework.participants`` with ``log.jsonl`` and ``participants.csv``) as a study's: their logs and
    tables, in the order given, into ``into`` (rewritten only when they change). A simulation of ``cohort``
    is taken whole; one of another cohort is taken where its participants are this study's people: each of its
    conditions with participants must be one of ``conditions`` with the same :func:`population` as ``config``
    (the study's participants config) gives it. Returns the participants per condition, in the order of
    ``conditions``; refuses, in one line, a directory without a finished simulation, another population, one
    under another physics than ``physics``, a participant id given twice, two runs whose participants draw
    from the same random streams (the same seed and index: the same people, paired across conditions), and a
    condition with nobody. A pilot's participants whom the practice screened out (``screened_out`` in its
    ``participants.csv``) did no main trial and are left out, as the preregistered exclusions say; ``screened``, when
    given, is filled with their number a condition."""
    logs, tables, seen, streams = [], [], {}, {}
    for where in map(Path, sims):
        if not (where / "log.jsonl").is_file() or not (where / "participants.csv").is_file():
            raise ConfigError(f"--sim {where}: no finished simulation there (log.jsonl and participants.csv); "
                              "run python -m overhang_framework.participants into it first")
        made_config = run_config(where)
        cohort_config = made_config.get("cohort")
        name = cohort_config.get("name") if isinstance(cohort_config, dict) else None
        made = made_config.get("world", {}).get("physics")
        if physics is not None and made != physics:
            raise ConfigError(f"--sim {where}: simulated under world.physics={made}, and this study's world is "
                              f"world.physics={physics} (give --world world.physics={made})")
        table = pd.read_csv(where / "participants.csv", dtype={"id": str})
        if "screened_out" in table.columns:
            out = table["screened_out"].astype(str).str.lower().isin(("true", "1"))
            if screened is not None:
                for condition, n in table[out]["condition"].astype(str).value_counts().items():
                    screened[condition] = screened.get(condition, 0) + int(n)
            table = table[~out].reset_index(drop=True)
        if name != cohort:
            present = [c for c in dict.fromkeys(table["condition"].astype(str))]
            if config is None:
                raise ConfigError(f"--sim {where}: a simulation of cohort {name!r}, not this study's {cohort!r}")
            for condition in present:
                if condition not in conditions:
                    raise ConfigError(f"--sim {where}: a simulation of cohort {name!r}, not this study's {cohort!r}, "
                                      f"and its {condition} participants are in none of the study's conditions "
                                      f"({', '.join(conditions)})")
                differ = _differences(population(made_config, condition), population(config, condition))
                if differ:
                    shown = ", ".join(differ[:4]) + (f" and {len(differ) - 4} more" if len(differ) > 4 else "")
                    raise ConfigError(f"--sim {where}: a simulation of cohort {name!r}, not this study's {cohort!r}; "
                                      f"its {condition} participants are other people (they differ in {shown})")
        for pid in table["id"]:
            if pid in seen:
                raise ConfigError(f"--sim {where}: participant {pid} is in {seen[pid]} too; give each simulation once, "
                                  "and simulations whose participants differ (e.g. one a condition)")
            seen[pid] = where
        seed = made_config.get("seed")
        if "index" in table.columns and seed is not None:
            for index in table["index"].astype(int):
                if (seed, index) in streams:
                    raise ConfigError(f"--sim {where}: its participants draw from the same random streams (seed {seed}) "
                                      f"as {streams[(seed, index)]}'s, participant by participant, and would be paired "
                                      "across the study's conditions; simulate one of the two with another seed=")
            streams.update({(seed, int(i)): where for i in table["index"]})
        text = (where / "log.jsonl").read_text()
        logs.append(text if text.endswith("\n") or not text else text + "\n")
        tables.append(table)
    table = pd.concat(tables, ignore_index=True)
    sizes = {c: int((table["condition"] == c).sum()) for c in conditions}
    empty = [c for c, n in sizes.items() if not n]
    if empty:
        raise ConfigError(f"--sim: no {' or '.join(empty)} participants in the simulations given; a study compares "
                          f"{' and '.join(conditions)}")
    into.mkdir(parents=True, exist_ok=True)
    for path, text in ((into / "log.jsonl", "".join(logs)), (into / "participants.csv", table.to_csv(index=False))):
        if not path.exists() or path.read_text() != text:
            atomic_write_text(path, text)
    return sizes

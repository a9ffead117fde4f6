"""One fit job: read the logs, fit its share of participants (and pooled conditions), aggregate every job's rows.

The work is split into *units*: every participant (sorted by id), then every
condition pooled. A job does the units ``k`` with ``k % shards == shard`` and
writes its rows to ``DIR/parts/shard-<shard>-of-<shards>.csv`` (atomically). Every job
then rebuilds ``DIR/fits.csv`` and ``DIR/comparison.md`` from all parts there,
under a lock, so the last job of a multirun leaves them complete, and a job
run again (with a warm score cache) replaces only its own part.

While a job runs, each finished fit is appended to its journal,
``DIR/parts/shard-<shard>-of-<shards>.fits.jsonl``: a job stopped part-way (a
Slurm time limit, a kill) and run again takes those fits from it and fits only
the rest. The journal goes once the part is written.

Logs are known by their content, not only by their paths: ``fit.json`` records each log's SHA-256
(:func:`log_hashes`), and a journal's fits carry the digest of all of them (:func:`logs_digest`), so a log
simulated again at the same path is never given the fits of the old one (:func:`check_directory`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import hashlib
import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Optional, Sequence

import pandas as pd

from overhang_framework.errors import OverhangError
from overhang_framework.fit.fitting import ModelFit, Placement, fit_index, log_placements, map_placements
from overhang_framework.fit.scores import HAND, ScoreCache, ScoreTables, TableStats, share_memory, share_tables, without_hand
from overhang_framework.interfaces import State
from overhang_framework.search import state_key
from overhang_framework.fit.space import ModelIndex
from overhang_framework.results import atomic_write_json, atomic_write_text, readable

PARTS = "parts"
FITS = "fits.csv"
FIT_JSON = "fit.json"
#: The columns of fits.csv, in order.
COLUMNS = ["participant", "condition", "model", "family", "depth", "sigma", "switch", "risk", "hand", "percept", "beta", "lapse", "loglik",
           "k", "n", "bic", "aic", "unmapped", "heldout_loglik", "folds"]
POOLED = "pooled:"
log = logging.getLogger("overhang_framework.fit")


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


def shard_units(units: Sequence[Unit], shards: int) -> list[list[Unit]]:
    """Each job's units: job ``j`` of ``shards`` does the units ``k`` with ``k % shards == j``."""
    return [[u for k, u in enumerate(units) if k % shards == j] for j in range(shards)]


@dataclass
class JobResult:
    fits: list[ModelFit]
    stats: dict[str, TableStats] = field(default_factory=dict)
    seconds: float = 0.0
    #: Fits taken from the journal of a stopped run.
    resumed: int = 0


def log_hashes(paths: Sequence[str | Path]) -> list[Optional[str]]:
    """The SHA-256 of each log's bytes, in the order of ``paths`` (None for a file that cannot be read, which
    reading the logs then reports)."""
    from overhang_framework.results import file_sha256

    return [file_sha256(p) for p in paths]


def logs_digest(hashes: Sequence[Optional[str]]) -> str:
    """One digest of the logs' contents (their :func:`log_hashes`, in order): what a journal's fits are of."""
    return hashlib.sha256(json.dumps(list(hashes)).encode()).hexdigest()


class FitJournal:
    """The fits a job has finished, one JSON line each, appended as they finish: a job run again after a stop
    takes them from here instead of fitting them again. A line cut short by a kill is ignored.

    Each line carries ``logs``, the digest of the contents of the logs it was fitted to (:func:`logs_digest`), and
    a fit is taken only by a journal of the same digest: its entries are keyed by model, unit and the logs'
    content, so a log simulated again at the same path is fitted again, whatever the journal holds."""

    #: The field of a line that holds the digest of the logs' contents.
    LOGS = "logs"

    def __init__(self, path: Path, logs: str = ""):
        self.path = Path(path)
        self.logs = str(logs)
        self.done: dict[tuple[str, str], ModelFit] = {}
        self._cut = False  # the file ends inside a line: the next line starts on a new one
        if self.path.exists():
            names = {f.name for f in dataclasses.fields(ModelFit)} | {self.LOGS}
            text = self.path.read_text()
            self._cut = bool(text) and not text.endswith("\n")
            for line in text.splitlines():
                try:
                    data = json.loads(line)
                except ValueError:
                    continue  # the last line of a job killed while writing it
                if isinstance(data, dict) and set(data) == names and data.pop(self.LOGS) == self.logs:
                    fit = ModelFit(**data)
                    self.done[(fit.label, fit.participant)] = fit

    def get(self, label: str, unit: str) -> Optional[ModelFit]:
        return self.done.get((label, unit))

    def add(self, fit: ModelFit) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with open(self.path, "a") as f:
            f.write(("\n" if self._cut else "") + json.dumps({**dataclasses.asdict(fit), self.LOGS: self.logs}) + "\n")
            f.flush()
            os.fsync(f.fileno())
        self._cut = False
        self.done[(fit.label, fit.participant)] = fit

    def remove(self) -> None:
        self.path.unlink(missing_ok=True)


def journal_path(out: Path, shard: int, shards: int) -> Path:
    return out / PARTS / f"shard-{shard}-of-{shards}.fits.jsonl"


def fit_units(units: Sequence[Unit], world, value, context: Mapping[str, Any], space: Sequence[ModelIndex],
              cache: Optional[ScoreCache], build_predictor: Callable[[Mapping[str, Any]], Any],
              on_unit: Callable[[str, Unit], None] = lambda label, unit: None, states: str = "logged",
              jobs: int = 1, on_table: Callable[[], None] = lambda: None,
              on_total: Callable[[int], None] = lambda n: None, folds: int = 0,
              journal: Optional[FitJournal] = None, shards: Sequence[Sequence[Unit]] = (),
              shard: int = 0, motor=None) -> JobResult:
    """Fit every model index of ``space`` to every unit. Tables are shared across units (one
    :class:`ScoreTables` per model) and kept in ``cache``. ``states`` says how decision states are built
    (:func:`~overhang_framework.fit.fitting.map_placements`). The tables not in the cache are first computed
    state by state, every model's tables of a state together (:func:`fill_tables`), on ``jobs`` worker
    processes when ``jobs > 1`` and in this process otherwise (``on_table`` is called for each). Fits in
    ``journal`` are taken from it; every other one is added to it as it finishes.

    ``shards`` holds the units of every job of a multirun that shares ``cache``, in shard order, this job's
    (``units``) at index ``shard``: the jobs then split the tables they all need between them
    (:func:`fill_tables`) instead of each computing those of its own units (with a cache on disk; without
    one ``shards`` is not used). ``motor`` (a :class:`~overhang_framework.fit.motor.Motor`) puts the executed
    placements' motor noise in the likelihood."""
    started = time.perf_counter()
    mapped = {u.name: map_placements(world, u.placements, states, motor) for u in units}
    tables = model_tables(space, world, value, context, cache, build_predictor)
    distinct = list({id(t.tables): t.tables for variants in tables for t in variants}.values())
    share_memory(distinct)
    share_tables(distinct)

    def done(label: str, unit: Unit) -> Optional[ModelFit]:
        return journal.get(label, unit.name) if journal is not None else None

    todo = [u for u in units if any(done(index.label, u) is None for index in space)]
    mine = [s for u in todo for s in mapped[u.name].states]
    sharing = len(shards) > 1 and bool(mine) and cache is not None and cache.path is not None
    fill_tables(distinct, mine, jobs, on_table, on_total,
                _shards_states(world, shards, shard, mine, states) if sharing else (), shard)
    seen = seen_states(space, tables, mine)
    if seen:
        log.info("score tables: %d percepts of the decision states for %d models with perceptual noise",
                 sum(len(s) for _, s in seen), len(seen))
        for base, percepts_ in seen:
            fill_tables([base], percepts_, jobs, on_table, on_total)
    fits: list[ModelFit] = []
    stats: dict[str, TableStats] = {}
    resumed = 0
    for index, variants in zip(space, tables):
        for unit in units:
            fit = done(index.label, unit)
            resumed += fit is not None
            if fit is None:
                fit = fit_index(unit.name, unit.condition, variants, mapped[unit.name], folds)
                if journal is not None:
                    journal.add(fit)
            fits.append(fit)
            on_unit(index.label, unit)
        total = TableStats()
        for v in {id(v.tables): v.tables for v in variants}.values():
            for name in ("asked", "computed", "cached", "predictor_calls", "seconds"):
                setattr(total, name, getattr(total, name) + getattr(v.stats, name))
        stats[index.label] = total
    return JobResult(fits, stats, time.perf_counter() - started, resumed)


class Variant:
    """A model of the space and the score tables it asks: its own, or, for a model with perceptual noise, those of
    the same model without it (asked in the towers the participant may have seen), shared with that model."""

    def __init__(self, model, tables: ScoreTables):
        self.model, self.tables, self.world = model, tables, tables.world

    def table(self, state: State):
        return self.tables.table(state)


def model_tables(space: Sequence[ModelIndex], world, value, context: Mapping[str, Any], cache: Optional[ScoreCache],
                 build_predictor: Callable[[Mapping[str, Any]], Any]) -> list[list[Variant]]:
    """The variants of every model index of ``space``, one :class:`ScoreTables` per distinct table key."""
    by_key: dict[str, ScoreTables] = {}
    out = []
    for index in space:
        variants = []
        for m in index.variants:
            base = dataclasses.replace(m, percept=0.0)
            key = base.key(context)
            if key not in by_key:
                by_key[key] = ScoreTables(world, value, build_predictor(base.predictor), base, context, cache)
            variants.append(Variant(m, by_key[key]))
        out.append(variants)
    return out


def seen_states(space: Sequence[ModelIndex], tables: Sequence[Sequence[Variant]], states: Sequence[State]
                ) -> list[tuple[ScoreTables, list[State]]]:
    """The towers the participants may have seen in ``states`` that each model with perceptual noise asks its
    tables about, by tables (distinct seen towers, in the decision states' order)."""
    from overhang_framework.fit.percept import percepts

    out: dict[int, tuple[ScoreTables, dict]] = {}
    for variants in tables:
        for v in variants:
            if not v.model.percept:
                continue
            base, seen = out.setdefault(id(v.tables), (v.tables, {}))
            for s in states:
                for x in percepts(s, v.model.percept):
                    seen.setdefault(state_key(x), x)
    return [(base, list(seen.values())) for base, seen in out.values()]


def _shards_states(world, shards: Sequence[Sequence[Unit]], shard: int, mine: Sequence[State],
                   states: str) -> list[Sequence[State]]:
    """Every job's decision states for :func:`fill_tables`: ``mine`` for this job, the others' units mapped."""
    return [mine if k == shard else [s for u in units for s in map_placements(world, u.placements, states).states]
            for k, units in enumerate(shards)]


#: States per work item of :func:`fill_tables`: enough to amortise the hand-over, few enough to balance.
CHUNK = 8


class Predictors:
    """The predictors of a model space, built once per settings and shared.

    Models that differ only in depth or risk aversion share one predictor; a hybrid whose early or late
    part has the settings of a predictor of the space (or of another hybrid's part) is given that predictor
    as its part. Every predictor that can remember its answers does (the CNN by tower, always; the IPE by
    tower, actions and draws, turned on here), so the models of one predictor at every depth and risk, the
    hybrids of every switch point, and a hybrid and the model of its part's settings where their draws
    agree (the CNN's always do), ask once: the same numbers, computed once.
    """

    #: Answers a hybrid's IPE part remembers (see :meth:`IPEPredictor.remember`): the switch points' tables
    #: of a worker's item of states ask each question within a few hundred calls of each other.
    MEMORY = 10_000

    def __init__(self, registry, world):
        self.registry, self.world = registry, world
        self.built: dict[str, Any] = {}
        self._parts: dict[tuple, Optional[str]] = {}

    @staticmethod
    def key(config: Mapping[str, Any]) -> str:
        return repr(sorted(config.items()))

    def __call__(self, config: Mapping[str, Any]):
        key = self.key(config)
        if key not in self.built:
            predictor = self.registry.create("predictor", dict(config), world=self.world)
            if config.get("name") == HAND and hasattr(predictor, "inner"):  # a hand asks the family's predictor
                predictor.inner = self(without_hand(config))
            self.built[key] = predictor
            self._remember(predictor)  # models of these settings at other depths or risks ask the same questions
            for other in list(self.built.values()):
                self._share(other)
        return self.built[key]

    def _remember(self, predictor) -> None:
        remember = getattr(predictor, "remember", None)
        if callable(remember) and not getattr(predictor, "memory_size", 0):
            remember(self.MEMORY)

    def _share(self, predictor) -> None:
        names, params = getattr(predictor, "names", None), getattr(predictor, "params", None)
        if not isinstance(names, dict) or not isinstance(params, dict):
            return
        from overhang_framework.fit.scores import predictor_config as _predictor_config

        for part in ("early", "late"):
            if part not in names:
                continue
            asked = (str(names[part]), self.key(dict(params.get(part) or {})))
            if asked not in self._parts:  # composing a config costs a Hydra compose: once per part's settings
                try:
                    self._parts[asked] = self.key(_predictor_config(asked[0], dict(params.get(part) or {})))
                except (OverhangError, ValueError):
                    self._parts[asked] = None
            key = self._parts[asked]
            if key is None:
                continue
            if key not in self.built:  # the first hybrid's part serves every later one
                self.built[key] = getattr(predictor, part)
            elif getattr(predictor, part, None) is not self.built[key]:
                setattr(predictor, part, self.built[key])
            self._remember(self.built[key])


def fill_tables(all_tables: Sequence[ScoreTables], states: Sequence[State], jobs: int,
                on_table: Callable[[], None] = lambda: None, on_total: Callable[[int], None] = lambda n: None,
                shards: Sequence[Sequence[State]] = (), shard: int = 0) -> None:
    """Compute every table of ``all_tables`` x ``states`` that neither memory nor the cache holds, and hand
    each to its :class:`ScoreTables` (which keeps it and writes it to the cache).

    The states keep their order (a trial's steps stay together, so an expander reuses the subtrees they
    share), and a state's tables are computed together, every model's, so that models sharing a predictor
    (:class:`Predictors`) share its answers: a hybrid's parts answer from what the models of their
    settings asked just before, within the answers they remember. With ``jobs > 1`` each worker process
    is given the next few states at a time; otherwise they are computed here. A table is the same
    whichever process computes it (common random numbers).

    ``shards`` holds the states of every job of a multirun that shares the score cache, this job's
    (``states``) at index ``shard``. Each state that several of them lack is then given to one of them
    (:func:`split_states`). A job computes its share first, then the states given to the others that it
    needs too, each other job's share from its far end: a table is read from the cache when its turn comes
    if another job has written it by then (with ``jobs > 1`` the worker processes read the cache too), so
    where a job falls behind the others meet it from the end of its share. Overlapping jobs (a pooled
    condition's states are its participants') compute each table about once and finish together. The
    total given to ``on_total`` is an upper bound then: it counts the tables the others write first.
    """
    rows = _missing(all_tables, states)
    on_total(sum(len(ks) for _, ks in rows))
    if len(shards) > 1 and rows:
        lacking = [_missing(all_tables, s, keep=False) if k != shard else rows for k, s in enumerate(shards)]
        assigned = split_states(lacking)
        place = {state_key(state): n for k, own in enumerate(lacking) for n, (state, _) in enumerate(own)
                 if assigned[state_key(state)] == k}
        first = [row for row in rows if assigned[state_key(row[0])] == shard]
        later = sorted((row for row in rows if assigned[state_key(row[0])] != shard),
                       key=lambda row: -place[state_key(row[0])])
        log.info("score tables: this job lacks %d, %d of them its share; the rest are other jobs' shares, "
                 "read from the cache once they are written", sum(len(ks) for _, ks in rows),
                 sum(len(ks) for _, ks in first))
        rows = first + later
    _fill(all_tables, rows, jobs, on_table)


def split_states(shards: Sequence[Sequence[tuple[State, list[int]]]]) -> dict[tuple, int]:
    """The job that computes each state of ``shards`` (every job's missing states with the tables they lack,
    :func:`_missing`), keyed by :func:`state_key`: a job's own where no other needs it; a state several need
    goes to the one of them with the fewest tables so far, the shared states taken in an order every job
    computes alike (by a digest of the state), so every job reaches the same split from the same cache."""
    need: dict[tuple, list[int]] = {}
    cost: dict[tuple, int] = {}
    for k, rows in enumerate(shards):
        for state, ks in rows:
            key = state_key(state)
            need.setdefault(key, []).append(k)
            cost[key] = max(cost.get(key, 0), len(ks))
    load = [0] * len(shards)
    out: dict[tuple, int] = {}
    for key, ks in need.items():
        if len(ks) == 1:
            out[key] = ks[0]
            load[ks[0]] += cost[key]
    shared = sorted((k for k, ks in need.items() if len(ks) > 1),
                    key=lambda k: hashlib.sha256(repr(k).encode()).hexdigest())
    for key in shared:
        k = min(need[key], key=lambda j: (load[j], j))
        out[key] = k
        load[k] += cost[key]
    return out


def _fill(all_tables: Sequence[ScoreTables], rows: Sequence[tuple[State, list[int]]], jobs: int,
          on_table: Callable[[], None]) -> None:
    """Compute the tables of ``rows`` (from :func:`_missing`), here or on ``jobs`` worker processes."""
    if jobs <= 1:
        for state, ks in rows:
            for k in ks:
                all_tables[k].compute(state)
                on_table()
        return
    from overhang_framework.parallel import pool_map

    # chunks of CHUNK states, fewer when there are few states, so that every worker has items
    size = max(1, min(CHUNK, len(rows) // (4 * max(jobs, 1))))
    items = []
    for i in range(0, len(rows), size):
        chunk = rows[i:i + size]
        items.append([(k, [state for state, ks in chunk if k in ks]) for k in range(len(all_tables))
                      if any(k in ks for _, ks in chunk)])
    if not items:
        return
    first = all_tables[0]
    cache = first.cache.path if first.cache is not None else None  # the workers read and write it themselves
    # each model whole (its risk too), its predictor config a plain dict for the worker processes
    setup = (dict(first.context), [dataclasses.replace(t.model, predictor=dict(t.model.predictor)) for t in all_tables],
             cache)
    for item, results, _ in pool_map(_tables_setup, setup, _tables_work, items, jobs, on_table):
        for (k, chunk), (scores, stats) in zip(item, results):
            all_tables[k].receive(chunk, scores, stats, written=cache is not None)


def _missing(all_tables: Sequence[ScoreTables], states: Sequence[State],
             keep: bool = True) -> list[tuple[State, list[int]]]:
    """Each distinct state of ``states``, in their order, with the indices of the tables to compute in it:
    not known, and not computed by another of ``all_tables`` (:func:`~overhang_framework.fit.scores.share_tables`).
    ``keep=False`` only looks (:meth:`ScoreTables.known`): for states of other jobs."""
    rows, seen = [], set()
    present = {id(t) for t in all_tables}
    for state in states:
        key = state_key(state)
        if key in seen:
            continue
        seen.add(key)
        ks = [k for k, tables in enumerate(all_tables) if not tables.known(state, keep)
              and ((owner := tables.owner(state)) is tables or id(owner) not in present)]
        if ks:
            rows.append((state, ks))
    return rows


def _tables_setup(context: Mapping[str, Any], models: list, cache: Optional[Path] = None) -> list:
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", dict(context["world"]))
    value = registry.create("value", dict(context["value"]), world=world)
    built = Predictors(registry, world)
    shared = ScoreCache(cache) if cache is not None else None
    tables = [ScoreTables(world, value, built(model.predictor), model, context, shared) for model in models]
    share_memory(tables)
    share_tables(tables)
    return tables


def _tables_work(tables: list, item: list) -> list[tuple[list, TableStats]]:
    from overhang_framework.parallel import tick

    out = []
    for k, states in item:
        mine = tables[k]
        before = TableStats(**vars(mine.stats))
        scores = []
        for state in states:
            scores.append(mine.table(state))
            tick()
        delta = TableStats(**{name: getattr(mine.stats, name) - getattr(before, name) for name in vars(before)})
        out.append((scores, delta))
    return out


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
    """Refuse a results directory that holds fits of another log or model space; record this one's.

    ``description`` holds the logs' paths (``logs``) and the SHA-256 of each one's bytes (``log_sha256``, in the
    same order). A log whose content changed at the same path (simulated again) is refused, with a one-line
    error naming it, rather than fitted again in place: the directory's ``fits.csv``, its comparison and the
    other jobs' parts are fits of the log as it was, and a job can replace only its own part, so fitting again
    in place would mix fits of two versions of the data, or delete results nobody asked to delete. A directory
    whose ``fit.json`` records no hashes (written before they were kept) cannot tell its logs' contents and is
    refused the same way."""
    path = out / FIT_JSON
    with _locked(out / ".fit.lock"):
        if path.exists():
            try:
                previous = json.loads(path.read_text())
            except ValueError:
                raise OverhangError(f"{path} is not a fit description; move it away or use another --out") from None
            description = json.loads(json.dumps(readable(dict(description))))  # as the file holds it
            previous.setdefault("states", "logged")  # fits written before the setting existed used the logged towers
            previous.setdefault("cv", 0)  # and no cross-validation
            if previous != description:
                keys = sorted(k for k in set(previous) | set(description) if previous.get(k) != description.get(k))
                again = f"use another --out, or remove {path} and {out / PARTS} to start again"
                if keys == ["log_sha256"] and "log_sha256" not in previous:
                    raise OverhangError(f"{out} holds fits of logs whose contents {path} does not record (a fit made "
                                        f"before log hashes were kept), so they may be of other data; {again}")
                if keys == ["log_sha256"]:
                    changed = [p for p, a, b in zip(description.get("logs") or [], previous["log_sha256"] or [],
                                                    description["log_sha256"]) if a != b]
                    named = changed[0] if len(changed) == 1 else f"{len(changed)} logs ({', '.join(changed)})"
                    raise OverhangError(f"{out} holds fits of {named} as it was before it changed (its SHA-256 "
                                        f"differs from the one {path} records); {again}")
                raise OverhangError(f"{out} holds fits of another {' and '.join(keys)}; {again}")
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

"""Score tables: a model's scores of every legal action in a decision state, computed once and kept on disk.

A *model* of a participant is a physics predictor (any registered one, with its
settings) and a planning depth ``D`` (1: the myopic planner's ``p(s, a) * r(s, a)``;
``D >= 2``: the lookahead's ``max_pi prod_k p * V``). Its *score table* in a
decision state holds the planner's exact score of every legal action of the
world's grid, in the order of ``world.legal_actions(state)``: what a softmax
choice needs (:func:`overhang_framework.search.root_scores` with every score exact).

**Common random numbers.** The predictor's draws at every node of the search
come from :func:`overhang_framework.search.node_rng`, a generator derived from
the model's *draw seed* and the node's canonical key. The draw seed depends on
the model's settings other than its noise level (``sigma``) and a hybrid's switch point, so a table is
a fixed function of the model and the state: the likelihood surface is
deterministic, the tables of neighbouring ``sigma`` share their standard
normal draws (the IPE scales one set of draws by ``sigma``), and the hybrids of every switch point ask
their parts the same questions with the same draws (a predictor that remembers its answers gives them
once: :class:`~overhang_framework.fit.run.Predictors`).

**Reuse.** Within a process, one :class:`~overhang_framework.search.Expander` per
model keeps the nodes it has expanded (up to ``memo_limit``), so the subtrees
that the steps of a trial share, and the early states that participants doing
the same task share, are searched once. Across processes and runs, the tables
themselves are kept in a :class:`ScoreCache` (an SQLite file) keyed by the
model's key and the state's canonical key.

**What a key holds.** A model's key (:meth:`Model.key`) is made of what its numbers depend on, by content
rather than by name: the model's settings and the world's and value's; the version of the code that
computes a table (:data:`SCORES_VERSION`, the framework's version and the version of each installed
distribution whose plugin registers a predictor of the model); the identity of the physics every
backend of the world or of a simulating predictor runs (:func:`physics_identity`, every parameter with
its default); and the content of the files a predictor loads (the CNN's checkpoint by the SHA-256 of
its bytes, :func:`content_identity`). A table computed by other code, on other physics or with other
weights under the same name is not found.

**Shared tables.** The hybrids of a switch-point grid give the same table in a state for most switch
points, and where every tower goes to a deterministic late part, the late part's model's table:
:func:`share_tables` lets each such table be computed once, and kept in the cache under every model's key.

**Batches.** A predictor whose ``batched`` attribute is true (the CNN, and a
hybrid with one) is asked for all the root's children in one call at depth 2
and more: the exact table expands each child that may stand anyway, so the work
and the scores are the same, in fewer, larger calls. Deeper levels are expanded
as the search reaches them: expanding every grandchild ahead (the search's
``prefetch``) would score the many that its bounds skip.
"""

from __future__ import annotations

import functools
import hashlib
import json
import sqlite3
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.results import file_sha256  # noqa: F401  (the fit's keys use it)
from overhang_framework.errors import OverhangError
from overhang_framework.interfaces import Budget, State, World
from overhang_framework.search import Expander, root_scores, state_key

#: Predictor settings that set a noise level; the draw seed leaves them out (common random numbers).
NOISE_KEYS = ("sigma", "sigma_position", "sigma_gravity", "sigma_friction")
#: The predictor that knows its hand (``predictor=hand``): a model with a hand wraps its family's predictor in it.
HAND = "hand"
#: Other fitted settings the draw seed leaves out: a hybrid's switch point, so that the hybrids of every
#: switch point ask their parts the same questions with the same draws and share the answers.
SHARED_DRAW_KEYS = ("switch",)
#: Settings that choose how the same numbers are computed (the IPE's scene path, the static LP stage):
#: a table's key and draw seed leave them out, so either way gives and finds the same tables.
ENGINE_KEYS = ("scenes", "lp_nnls", "compiled", "nnls", "lazy", "settle_batch")


#: The version of how a table is computed (this module, the searches and planners it calls): raised when a
#: change gives a table other numbers, so that the tables kept before are not reused.
SCORES_VERSION = 1


def _digest(data: Any) -> str:
    return hashlib.sha256(json.dumps(data, sort_keys=True, default=str).encode()).hexdigest()


def _strip(config: Any, keys: tuple) -> Any:
    if isinstance(config, Mapping):
        return {k: _strip(v, keys) for k, v in config.items() if k not in keys}
    return config


def _strip_noise(config: Any) -> Any:
    if isinstance(config, Mapping) and config.get("name") == HAND:  # the hands of a grid share their draws too
        config = {k: v for k, v in config.items() if k != "sd"}
    return _strip(config, NOISE_KEYS + SHARED_DRAW_KEYS + ENGINE_KEYS)


def with_hand(config: Mapping[str, Any], hand: float, nodes: int = 3) -> dict:
    """``config`` (a predictor's, with its ``name``) as a planner with motor noise ``hand`` (metres) judges:
    wrapped in ``predictor=hand``; ``config`` itself when ``hand`` is 0."""
    config = dict(config)
    if not hand:
        return config
    return {"name": HAND, "inner": config["name"], "inner_params": {k: v for k, v in config.items() if k != "name"},
            "sd": float(hand), "nodes": int(nodes)}


def without_hand(config: Mapping[str, Any]) -> Mapping[str, Any]:
    """The predictor config inside a hand (:func:`with_hand`), or ``config`` itself."""
    if config.get("name") == HAND and "inner" in config:
        return {"name": config["inner"], **dict(config.get("inner_params") or {})}
    return config


@dataclass(frozen=True)
class Model:
    """One model of the model space: a predictor config (as ``conf/predictor/*.yaml`` gives it), a depth, the
    planner's risk aversion (``risk``, ``risk_form``: :func:`overhang_framework.search.risk_weight`; 0,
    risk-neutral, by default), and the participant's perceptual noise (``percept``; 0, none, by default)."""

    predictor: Mapping[str, Any]
    depth: int
    family: str = ""
    risk: float = 0.0
    risk_form: str = "power"
    #: The perceptual noise (metres) of the participant the model describes: its tables are the model's without
    #: it, asked in the towers the participant may have seen (:mod:`overhang_framework.fit.percept`).
    percept: float = 0.0

    def __post_init__(self):
        from overhang_framework.search import check_risk

        if isinstance(self.depth, bool) or not isinstance(self.depth, int) or self.depth < 1:
            raise ValueError(f"depth must be a whole number >= 1, got {self.depth!r}")
        object.__setattr__(self, "risk", check_risk(self.risk, self.risk_form))
        if isinstance(self.percept, bool) or not isinstance(self.percept, (int, float)) \
                or not np.isfinite(self.percept) or self.percept < 0:
            raise ValueError(f"percept must be a number of metres >= 0, got {self.percept!r}")
        object.__setattr__(self, "percept", float(self.percept))
        if not self.family:
            object.__setattr__(self, "family", str(without_hand(self.predictor)["name"]))

    @property
    def judged_by(self) -> Mapping[str, Any]:
        """The family's predictor config: :attr:`predictor` without the hand around it."""
        return without_hand(self.predictor)

    @property
    def hand(self) -> float:
        """The motor noise (metres) the planner plans for: ``predictor=hand``'s ``sd``, else 0."""
        return float(self.predictor.get("sd", 0.0)) if self.predictor.get("name") == HAND else 0.0

    @property
    def sigma(self) -> Optional[float]:
        value = self.judged_by.get("sigma")
        return None if value is None else float(value)

    @property
    def switch(self) -> Optional[int]:
        """The hybrid's switch point (towers of fewer blocks go to its early predictor), or None."""
        value = self.judged_by.get("switch")
        return None if value is None else int(value)

    @property
    def planner(self) -> str:
        return "myopic" if self.depth == 1 else f"D{self.depth}"

    @property
    def label(self) -> str:
        """``ipe/D2``, ``cnn/myopic``: the model index (family and depth), without its fitted sigma."""
        return f"{self.family}/{self.planner}"

    def key(self, context: Mapping[str, Any]) -> str:
        """The key of this model's tables: every setting that changes a score (``context``: world and value), the
        version of the code that computes them (:func:`code_identity`), the identity of the physics they run on
        (:func:`physics_identity`) and the content of the files the predictor loads (:func:`content_identity`);
        not the percept, which changes the states a table is asked in, not the table."""
        data = {"predictor": _strip(dict(self.predictor), ENGINE_KEYS), "depth": self.depth,
                "context": _strip(dict(context), ENGINE_KEYS), "code": code_identity(self.predictor),
                "physics": physics_identity(context)}
        content = content_identity(self.predictor)
        if content:
            data["content"] = content
        if self.risk:
            data["risk"] = [self.risk, self.risk_form]
        shared = [k for k in SHARED_DRAW_KEYS if k in self.predictor]
        if shared:  # these tables' draws leave those settings out
            data["draws_without"] = shared
        if _stage_switch(self.predictor):  # its draws are its early part's
            data["draws_of"] = "early"
        return _digest(data)

    def draw_settings(self) -> Mapping[str, Any]:
        """The settings the model's draws follow: the predictor's, or a stage-switch hybrid's early part's (a
        config with ``early``, ``late`` and ``early_params``, as ``predictor=hybrid``), as that predictor's own
        config gives them. So a hybrid draws what its early part alone would, and where every tower goes to
        the early part its table is that part's model's table, to the bit (:func:`share_tables`)."""
        if _stage_switch(self.predictor):
            return _part_config(str(self.predictor["early"]), self.predictor.get("early_params") or {})
        return self.predictor

    def draw_seed(self, context: Mapping[str, Any]) -> int:
        """The seed of the predictor's draws: the settings of :meth:`draw_settings` without the noise levels
        and the switch point (and without the risk, which weighs the same answers)."""
        digest = _digest({"predictor": _strip_noise(dict(self.draw_settings())),
                          "context": _strip(dict(context), ENGINE_KEYS)})
        return int(digest[:16], 16)


_REGISTRY: list = []


def _entry(name: Any):
    """The registry's entry of predictor ``name``, or None when no plugin registers it."""
    from overhang_framework.plugins import Registry

    if not isinstance(name, str):
        return None
    for fresh in (False, True):  # a plugin registered since the registry was read is found on a second look
        if fresh or not _REGISTRY:
            _REGISTRY[:] = [Registry()]
        entry = _REGISTRY[0].entries["predictor"].get(name)
        if entry is not None:
            return entry
    return None


@functools.lru_cache(maxsize=None)
def _defaults(factory: Any) -> dict:
    import inspect

    try:
        parameters = inspect.signature(factory).parameters.values()
    except (TypeError, ValueError):
        return {}
    return {p.name: p.default for p in parameters if p.default is not inspect.Parameter.empty}


def predictor_parts(config: Mapping[str, Any], _depth: int = 0) -> list[tuple[str, dict]]:
    """The name and settings of the predictor ``config`` describes and of every predictor inside it: a setting
    ``X`` that names a predictor beside a mapping ``X_params`` of its settings (the hybrid's ``early`` and
    ``late``, the hand's ``inner``), from the factory's defaults where ``config`` leaves it out."""
    name = config.get("name")
    params = {str(k): v for k, v in config.items() if k != "name"}
    parts = [(str(name), params)]
    entry = _entry(name)
    if entry is None or _depth > 8:
        return parts
    try:
        defaults = _defaults(entry.factory)
    except TypeError:  # a factory that cannot be a cache's key
        defaults = _defaults.__wrapped__(entry.factory)
    for key in sorted(set(params) | set(defaults)):
        holder = f"{key}_params"
        if key.endswith("_params") or (holder not in params and holder not in defaults):
            continue
        part = params.get(key, defaults.get(key))
        inner = params.get(holder, defaults.get(holder)) or {}
        if isinstance(part, str) and isinstance(inner, Mapping) and _entry(part) is not None:
            parts += predictor_parts({**dict(inner), "name": part}, _depth + 1)
    return parts


@functools.lru_cache(maxsize=None)
def _distribution(name: str) -> str:
    """``project version`` of the installed distribution whose plugin registers predictor ``name``; '' for a
    plugin registered by a running program (a test's), or a name no plugin registers."""
    from overhang_framework.plugins import get_plugin_manager

    entry = _entry(name)
    if entry is None:
        return ""
    pm = get_plugin_manager()
    plugin = pm.get_plugin(entry.plugin)
    for registered, dist in pm.list_plugin_distinfo():
        if registered is plugin:
            return f"{dist.project_name} {dist.version}"
    return ""


def code_identity(predictor: Mapping[str, Any]) -> dict:
    """The versions of the code that computes a table of a model with predictor config ``predictor``:
    :data:`SCORES_VERSION`, the framework's version, and the installed distribution (project and version) of the
    plugin that registers each predictor it names (:func:`predictor_parts`)."""
    from overhang_framework.version import version

    names = sorted({name for name, _ in predictor_parts(predictor)})
    return {"scores": SCORES_VERSION, "framework": version(), "plugins": {n: _distribution(n) for n in names}}


@functools.lru_cache(maxsize=64)
def _physics(world: str) -> dict:
    from overhang_framework.physics.factory import BACKENDS, identity

    config = json.loads(world)
    resolution = config.get("resolution")
    return {"physics": config.get("physics", "tiered"),
            "backends": {name: identity(name, dict(config.get(name) or {}), resolution)["params"]
                         for name in BACKENDS}}


def physics_identity(context: Mapping[str, Any]) -> dict:
    """The physics a model's tables run on, from the world's config in ``context``: the world's physics and every
    backend's parameters with their defaults (the identity :func:`overhang_framework.physics.factory.identity` gives
    the benchmark's optima, less how a verdict is computed). The IPE simulates on one of these backends with
    the world's parameters for it, overridden by its own ``backend_params`` (part of its config); the
    tiered physics builds on the others."""
    world = context.get("world") if isinstance(context, Mapping) else None
    world = dict(world) if isinstance(world, Mapping) else {}
    return _physics(json.dumps(_plain(world), sort_keys=True, default=str))


def content_identity(predictor: Mapping[str, Any]) -> list:
    """What the answers of predictor config ``predictor`` depend on beyond its settings, by each predictor it
    names (:func:`predictor_parts`): what a factory's ``content_identity(settings)`` gives (the CNN: the
    SHA-256 of its checkpoint's bytes), as ``[name, identity]`` pairs. Empty when no part loads a file."""
    out = []
    for name, params in predictor_parts(predictor):
        entry = _entry(name)
        identify = getattr(entry.factory, "content_identity", None) if entry is not None else None
        found = identify(params) if callable(identify) else None
        if found:
            out.append([name, dict(found)])
    return out


def _stage_switch(config: Mapping[str, Any]) -> bool:
    return all(k in config for k in ("early", "late", "early_params"))


def predictor_config(name: str, overrides: Mapping[str, Any]) -> dict:
    """The config of installed predictor ``name`` (``conf/predictor``) with ``overrides`` over its defaults;
    :class:`ConfigError` naming an unknown predictor or setting and what is allowed."""
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config, group_options
    from overhang_framework.errors import ConfigError

    options = group_options("predictor")
    if name not in options:
        raise ConfigError(f"fit.models: unknown predictor {name!r}; installed predictors: {', '.join(options)}")
    base = OmegaConf.to_container(compose_config([f"predictor={name}"]).predictor, resolve=True)
    unknown = [k for k in overrides if k not in base]
    if unknown:
        raise ConfigError(f"fit.models.{name}: predictor {name!r} has no setting {unknown[0]!r}; "
                          f"settings: {', '.join(sorted(base))}")
    base.update(overrides)
    return base


@functools.lru_cache(maxsize=64)
def _composed_part(name: str, params: str) -> str:
    return json.dumps(predictor_config(name, json.loads(params)), sort_keys=True, default=str)


def _part_config(name: str, params: Mapping[str, Any]) -> dict:
    """The config of predictor ``name`` with ``params`` over its defaults (one compose per distinct part)."""
    plain = json.loads(json.dumps(_plain(params), sort_keys=True, default=str))
    try:
        return json.loads(_composed_part(name, json.dumps(plain, sort_keys=True)))
    except (OverhangError, ValueError):  # a part the registry refuses fails where the predictor is built
        return {"name": name, **plain}


def _plain(config: Any) -> Any:
    if isinstance(config, Mapping):
        return {str(k): _plain(v) for k, v in config.items()}
    if isinstance(config, (list, tuple)):
        return [_plain(v) for v in config]
    return config


class ScoreCache:
    """Score tables on disk: an SQLite file that several processes (a multirun's jobs) share.

    ``path=None`` keeps nothing. Tables are written as they are computed, so a
    stopped fit keeps what it computed.
    """

    def __init__(self, path: Optional[str | Path]):
        self.path = None if path is None else Path(path).expanduser()
        self.hits = 0
        self.misses = 0
        self._db = None
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # Switching a new file to WAL takes a lock that SQLite does not wait for: two shards opening
            # one cache at once retry it (for as long as the connection's own timeout) instead of failing.
            deadline = time.monotonic() + 120
            while True:
                try:
                    self._db = sqlite3.connect(str(self.path), timeout=120, isolation_level=None)
                    self._db.execute("PRAGMA journal_mode=WAL")
                    # A table is committed on its own as it is computed; in WAL mode NORMAL keeps the file
                    # whole through a crash of the process (only the operating system's may lose the last
                    # tables, which are then computed again) and spares a flush to disk per table.
                    self._db.execute("PRAGMA synchronous=NORMAL")
                    self._db.execute("CREATE TABLE IF NOT EXISTS scores (key TEXT PRIMARY KEY, n INTEGER, scores BLOB)")
                    break
                except sqlite3.DatabaseError as err:
                    if isinstance(err, sqlite3.OperationalError) and "locked" in str(err) \
                            and time.monotonic() < deadline:
                        if self._db is not None:
                            self._db.close()
                            self._db = None
                        time.sleep(0.05)
                        continue
                    raise ValueError(f"score cache {self.path} is not a usable SQLite file ({err}); "
                                     "move it away or give another fit.cache") from None

    @staticmethod
    def entry(model_key: str, state: State) -> str:
        return hashlib.sha256(repr((model_key, state_key(state))).encode()).hexdigest()

    def get(self, key: str) -> Optional[np.ndarray]:
        if self._db is None:
            self.misses += 1
            return None
        row = self._db.execute("SELECT n, scores FROM scores WHERE key = ?", (key,)).fetchone()
        if row is None:
            self.misses += 1
            return None
        self.hits += 1
        return np.frombuffer(row[1], dtype=np.float64, count=row[0]).copy()

    def put(self, key: str, scores: np.ndarray) -> None:
        if self._db is None:
            return
        data = np.ascontiguousarray(scores, dtype=np.float64)
        self._db.execute("INSERT OR REPLACE INTO scores (key, n, scores) VALUES (?, ?, ?)",
                         (key, int(data.size), data.tobytes()))

    def __contains__(self, key: str) -> bool:
        return self._db is not None and \
            self._db.execute("SELECT 1 FROM scores WHERE key = ?", (key,)).fetchone() is not None

    def __len__(self) -> int:
        if self._db is None:
            return 0
        return int(self._db.execute("SELECT COUNT(*) FROM scores").fetchone()[0])

    def close(self) -> None:
        if self._db is not None:
            self._db.close()
            self._db = None


@dataclass
class TableStats:
    """What computing tables cost: tables asked, computed, found in the cache, predictor calls, seconds."""

    asked: int = 0
    computed: int = 0
    cached: int = 0
    predictor_calls: int = 0
    seconds: float = 0.0


#: Search nodes a process keeps in memory over all its models' expanders (about 12 KB a node: an IPE D = 2
#: node with its children's states), shared out by :func:`share_memory`.
MEMO_NODES = 200_000


def share_memory(tables: Sequence["ScoreTables"], nodes: int = MEMO_NODES) -> None:
    """Give the expanders of ``tables`` (one process's) an equal share of ``nodes``, at least 2,000 each: the
    states a worker's item holds are searched close together, so a model needs its recent nodes only."""
    each = max(2_000, nodes // max(len(tables), 1))
    for t in tables:
        t.memo_limit = each


@dataclass
class ScoreTables:
    """The score tables of one model on one world and value, computed once per state and cached.

    ``context`` names the world and value settings that change a score (part of
    the cache key). ``memo_limit`` bounds the nodes kept in memory between
    tables (the expander is emptied when it holds more).
    """

    world: World
    value: Any
    predictor: Any
    model: Model
    context: Mapping[str, Any]
    cache: Optional[ScoreCache] = None
    memo_limit: int = 200_000
    stats: TableStats = field(default_factory=TableStats)
    #: The tables this model's table equals in a given state, or None (set by :func:`share_tables`).
    same_as: Optional[Callable[[State], Optional["ScoreTables"]]] = None

    def __post_init__(self):
        self.key = self.model.key(self.context)
        self._expander = self._new_expander()
        self._tables: dict[tuple, np.ndarray] = {}

    def _new_expander(self) -> Expander:
        return Expander(self.world, self.predictor, Budget(), seed=self.model.draw_seed(self.context), auto_lazy=False,
                        risk=self.model.risk, risk_form=self.model.risk_form)

    def owner(self, state: State) -> "ScoreTables":
        """The tables that compute this model's table of ``state``: these, or others whose table there is the
        same numbers (:func:`share_tables`)."""
        tables = self
        for _ in range(8):
            other = tables.same_as(state) if tables.same_as is not None else None
            if other is None or other is tables:
                return tables
            tables = other
        raise OverhangError(f"the score tables of {self.model.label} point to each other in a cycle in a state of "
                            f"{len(state.geometry)} blocks; a predictor's equivalent_switch must return a switch "
                            "point whose own is itself")

    def known(self, state: State, keep: bool = True) -> bool:
        """Whether the table of ``state`` is in memory or in the cache (computing nothing); with ``keep``, a
        table found in the cache is then kept in memory (a fit of this job uses it)."""
        if state_key(state) in self._tables:
            return True
        if self.cache is not None:
            entry = ScoreCache.entry(self.key, state)
            if not keep:
                if entry in self.cache:
                    return True
            elif (scores := self.cache.get(entry)) is not None:
                self._tables[state_key(state)] = scores
                self.stats.cached += 1
                return True
        owner = self.owner(state)
        return owner is not self and owner.known(state, keep)

    def receive(self, states, scores, stats: "TableStats", written: bool = False) -> None:
        """Tables of ``states`` computed elsewhere (a worker process), with what they cost there; ``written``:
        that process wrote them to the cache already."""
        for state, table in zip(states, scores):
            self._tables[state_key(state)] = np.asarray(table, dtype=float)
            if self.cache is not None and not written:
                self.cache.put(ScoreCache.entry(self.key, state), np.asarray(table, dtype=float))
        for name in ("computed", "cached", "predictor_calls", "seconds"):
            setattr(self.stats, name, getattr(self.stats, name) + getattr(stats, name))

    def _expand_children(self, state: State) -> None:
        """Expand the children of ``state`` that an exact table searches (those that may stand), in one call."""
        root = self._expander.expand(state, force=True)
        self._expander.expand_many([child for child, p in zip(root.children, root.p) if p > 0])

    def table(self, state: State) -> np.ndarray:
        """The model's score of every action of ``world.legal_actions(state)``, in that order."""
        self.stats.asked += 1
        return self._table(state)

    def compute(self, state: State) -> None:
        """Compute and keep the table of ``state`` ahead of the fit that asks for it (not counted as asked)."""
        self._table(state)

    def _table(self, state: State) -> np.ndarray:
        skey = state_key(state)
        known = self._tables.get(skey)
        if known is not None:
            return known
        entry = ScoreCache.entry(self.key, state)
        scores = self.cache.get(entry) if self.cache is not None else None
        owner = self.owner(state) if scores is None else self
        if scores is not None:
            self.stats.cached += 1
        elif owner is not self:  # the same numbers as owner's: computed there, kept under this model's key too
            scores = owner._table(state)
            if self.cache is not None:
                self.cache.put(entry, scores)
        else:
            started = time.perf_counter()
            if len(self._expander._memo) > self.memo_limit:
                self._expander = self._new_expander()
            calls = self._expander.stats.predictor_calls
            batched = bool(getattr(self.predictor, "batched", False))
            if batched and self.model.depth >= 2:
                self._expand_children(state)
            scores = np.asarray(root_scores(self._expander, self.value, state, self.model.depth, True), dtype=float)
            self.stats.predictor_calls += self._expander.stats.predictor_calls - calls
            self.stats.computed += 1
            self.stats.seconds += time.perf_counter() - started
            if self.cache is not None:
                self.cache.put(entry, scores)
        self._tables[skey] = scores
        return scores


def _switch_stage(members: Mapping[int, ScoreTables], late: Optional[ScoreTables], early: Optional[ScoreTables],
                  predictor: Any, depth: int, state: State) -> Optional[ScoreTables]:
    """The tables equal to those of hybrid ``predictor`` at horizon ``depth`` in ``state``."""
    n = len(state.geometry)
    stage = int(predictor.equivalent_switch(n, depth))
    if stage <= n + 1 and late is not None:
        return late
    if stage >= n + depth + 1 and early is not None:
        return early
    return members.get(stage)


def _same_risk(a: Model, b: Model) -> bool:
    return (a.risk, a.risk_form if a.risk else "") == (b.risk, b.risk_form if b.risk else "")


def share_tables(tables: Sequence[ScoreTables]) -> None:
    """Let the tables of ``tables`` that are the same numbers in a state be computed once.

    A stage-switch hybrid (a predictor with ``switch``, ``late`` and ``equivalent_switch``, as
    ``predictor=hybrid``) at horizon ``D`` judges, from a state of ``n`` blocks, only towers of ``n + 1`` to
    ``n + D`` blocks, so its switch points give at most ``D + 1`` different tables there: each hybrid's table
    is that of its ``equivalent_switch(n, D)``, when the hybrids of ``tables`` (the same settings otherwise,
    the same depth) include it. Where that sends every tower to ``late`` and ``late`` is deterministic (its
    answers never use the draws) and is the very predictor of a model of ``tables`` at the same depth, the
    table is that model's; where it sends every tower to ``early`` and ``early`` is the very predictor of a
    model of ``tables`` at the same depth with the same draws (a hybrid draws as its early part:
    :meth:`Model.draw_settings`), the table is that model's. A table computed elsewhere is also kept under its own model's key in the cache, so
    a later fit or check with other models finds it.
    """
    groups: dict[str, dict[int, ScoreTables]] = {}
    collided: set[str] = set()
    for t in tables:
        p = t.predictor
        if t.model.switch is None or not callable(getattr(p, "equivalent_switch", None)) \
                or getattr(p, "switch", None) != t.model.switch:
            continue
        top = {k: v for k, v in dict(t.model.predictor).items() if k != "switch"}
        key = _digest({"predictor": _strip(top, ENGINE_KEYS), "depth": t.model.depth, "family": t.model.family,
                       "context": t.context, "risk": [t.model.risk, t.model.risk_form]})
        group = groups.setdefault(key, {})
        if t.model.switch in group and group[t.model.switch] is not t:
            collided.add(key)
        group[t.model.switch] = t
    for key, members in groups.items():
        if key in collided:
            continue
        for t in members.values():
            part = getattr(t.predictor, "late", None)
            late = None
            if getattr(part, "deterministic", False):
                late = next((u for u in tables if u.predictor is part and u.model.depth == t.model.depth
                             and u.context == t.context and _same_risk(u.model, t.model)), None)
            part, seed = getattr(t.predictor, "early", None), t.model.draw_seed(t.context)
            early = next((u for u in tables if part is not None and u.predictor is part and u.model.depth == t.model.depth
                          and u.context == t.context and u.model.draw_seed(u.context) == seed
                          and _same_risk(u.model, t.model)), None)
            t.same_as = functools.partial(_switch_stage, members, late, early, t.predictor, t.model.depth)

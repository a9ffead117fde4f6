"""The experiment's settings: ``conf/serve.yaml`` composed with command-line overrides, checked once.

Everything the server needs is resolved here (the world's config, the main
tasks, the practice tasks with their optima, the database URL, the admin
token), so a mistake stops the server before it listens, in one line.
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Optional, Sequence

from omegaconf import DictConfig, OmegaConf

from overhang_framework.errors import ConfigError
from overhang_framework.interfaces import Task

ADMIN_ENV = "OVERHANG_ADMIN_TOKEN"
#: The admin token's least length: with the wrong guesses an address may make (the server's ``ADMIN_GUESSES``), too
#: many to try.
MIN_ADMIN_TOKEN = 16
#: How the server's worker processes get the command line's settings.
SETTINGS_ENV = "OVERHANG_EXPERIMENT_OVERRIDES"
#: The environment variable that names the study's database when ``database=`` does not (the systemd unit's
#: environment file: a password there stays out of the unit and of ``ps``).
DATABASE_ENV = "OVERHANG_DATABASE_URL"
CONSENT_FILE = Path(__file__).resolve().parent / "consent.html"
REPO_WEB = Path(__file__).resolve().parents[2] / "web"


@dataclass(frozen=True)
class PracticeTask:
    task: Task
    optimum: float
    optimal_tower: list  # [width, x, layer] per block, the ground block first
    # The tower shown after an attempt, [width, x, layer] per block: the best one that stays legal and stands
    # with every placement off by up to ``tolerance`` (units), stored by ``experiment/practice.py``.
    shown_tower: list
    shown_reward: float  # its overhang
    tolerance: float
    # The reward that passes the trial: the ground block's own overhang (what any standing tower reaches)
    # plus practice.threshold x what the shown tower adds to it.
    pass_reward: float


@dataclass
class Settings:
    world: dict
    tasks: list[Task]
    practice: list[PracticeTask]
    practice_threshold: float
    practice_max_attempts: Optional[int]
    conditions: list[str]
    time_limit: float
    time_grace: float
    database: str
    admin_token: str
    completion_url: str
    screen_out_url: str
    contact: str
    public_url: Optional[str]
    bonus_per_unit: float
    currency: str
    mouse_hz: float
    animation_fps: float
    seed: int
    run_dir: Path
    web_dir: Optional[Path]
    consent_html: str = ""
    consent_version: str = ""
    allow_settings_change: bool = False
    source: str = "human"
    decline_url: str = "/declined"
    host: str = "127.0.0.1"
    port: int = 8000
    workers: int = 1
    physics_processes: int = 0
    keep_alive: float = 75.0
    forwarded_allow_ips: str = "127.0.0.1"
    extra: dict = field(default_factory=dict)
    #: The time limit (seconds, None: none) of each condition other than ``time_limited`` and ``unconstrained``.
    time_limits: dict = field(default_factory=dict)
    #: Each condition's consent page (HTML) and its version, where the text differs by condition (its duration).
    consents: dict = field(default_factory=dict)
    #: Each condition's expected duration in minutes, which its consent page states.
    durations: dict = field(default_factory=dict)
    #: The duration of a condition without its own, and the consent text's file (None: the shipped one).
    duration: float = 30.0
    consent_file: Optional[str] = None

    def consent_of(self, condition: str) -> tuple[str, str]:
        """The consent page ``condition``'s participants see and its version; a condition the study no longer
        serves (a level dropped while someone is in it) gets its own text, with its duration in ``durations`` or
        ``duration``."""
        if condition not in self.consents:
            self.consents[condition] = consent_text(self.consent_file, self.contact,
                                                    self.durations.get(condition, self.duration))
        return self.consents[condition]

    def limit_of(self, condition: str) -> Optional[float]:
        """The time limit of ``condition``'s participants: ``time_limit`` for ``time_limited``, none for
        ``unconstrained``, else its entry of ``time_limits``."""
        if condition == "time_limited":
            return self.time_limit
        if condition == "unconstrained":
            return None
        return self.time_limits[condition]


def compose(overrides: Sequence[str] = ()) -> DictConfig:
    """``conf/serve.yaml`` with ``overrides`` (Hydra syntax, as on the command line); a bad override is one
    :class:`~overhang_framework.errors.OverhangError` line, as the main command gives it (an unknown key
    with the closest existing one)."""
    from overhang_framework.preflight import compose_checked

    return compose_checked([_quoted_database(w) for w in overrides], config_name="serve")


def _quoted_database(word: str) -> str:
    """``database=URL`` with the URL quoted for Hydra, so that a URL with a query (``?host=/run/postgresql&port=5433``,
    ``?sslmode=require``) is taken as it is written; a quoted or null value is left alone."""
    key, sep, value = word.partition("=")
    if not sep or key.lstrip("+") != "database" or not value or value[0] in "'\"" or value == "null":
        return word
    # Hydra's quoted strings escape a quote, and the backslashes just before a quote or the closing one
    value = re.sub(r'(\\*)"', lambda m: m.group(1) * 2 + '\\"', value)
    value = re.sub(r'(\\+)$', lambda m: m.group(1) * 2, value)
    return f'{key}="{value}"'


def database_url(value: Optional[str], run_dir: Path) -> str:
    """The study's database: ``database=``, else the environment variable :data:`DATABASE_ENV`, else SQLite in
    ``run_dir``; one :class:`ConfigError` line when it is not a URL the server can open."""
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError

    database = value or os.environ.get(DATABASE_ENV) or f"sqlite:///{(run_dir / 'experiment.sqlite').resolve()}"
    allowed = "sqlite:///FILE or postgresql+psycopg://user:password@host/db"
    if not isinstance(database, str) or "://" not in database:
        raise ConfigError(f"database must be an SQLAlchemy URL such as {allowed}, got {database!r}")
    try:
        url = make_url(database)
        url.get_dialect()
    except (ArgumentError, NoSuchModuleError, ValueError):
        kind = database.split("://", 1)[0]
        hint = " (write postgresql+psycopg://...)" if kind in ("postgres", "postgresql", "postgresql+psycopg2") else ""
        raise ConfigError(f"database: {kind}:// is not a kind of database the server can open{hint}; use "
                          f"{allowed}") from None
    if url.get_backend_name() not in ("sqlite", "postgresql"):
        raise ConfigError(f"database: {url.get_backend_name()} is not supported; use {allowed}")
    return database


def _number(cfg: DictConfig, key: str, minimum: float = 0.0, strict: bool = True) -> float:
    value = OmegaConf.select(cfg, key)
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value < minimum or (strict and value == minimum):
        bound = f"> {minimum:g}" if strict else f">= {minimum:g}"
        raise ConfigError(f"{key} must be a number {bound}, got {value!r}")
    return float(value)


def practice_tasks(cfg: DictConfig, world) -> list[PracticeTask]:
    """The practice tasks with their optima and shown towers under ``world``'s physics, from the project's files.

    A practice task whose optimum, or whose buildable tower at ``practice.tolerance``, is not stored stops the
    server with the command that computes it. A trial passes when the tower stands and reaches beyond its
    ground block by at least ``practice.threshold`` x as much as the shown tower does: measured from what the
    ground block alone reaches, since any tower that stands reaches that, and against a tower a person can
    build, not the optimum, which may need exact placements.
    """
    from omegaconf import OmegaConf

    from overhang_framework.experiment.towers import COMMAND, check_tolerance, load_towers, tower_key
    from overhang_framework.geometry import Action
    from overhang_framework.optimum import load_optima, optimum_key, DATA_FILE
    from overhang_framework.tasks import parse_tasks

    tasks = parse_tasks(list(cfg.practice.sequences), list(cfg.practice.ids), prefix="practice")
    tolerance = check_tolerance(OmegaConf.select(cfg, "practice.tolerance"))
    optima, towers = load_optima(DATA_FILE), load_towers()
    seqs = ",".join("[" + ",".join(map(str, t.sequence)) + "]" for t in tasks)
    ids = ",".join(t.id for t in tasks)

    def replay(task, actions):
        state = world.initial_state(task)
        for x, layer in actions:
            state = world.successor(state, Action(float(x), int(layer)))
        return [[b.width, b.x, b.layer] for b in state.geometry.blocks], round(world.overhang(state.geometry), 9)

    out = []
    for task in tasks:
        row = optima.get(optimum_key(task, world))
        if row is None:
            raise ConfigError(
                f"practice task {task.id} has no stored optimum under world.physics={world.physics_name}; compute them "
                f"with: python -m overhang_framework.optimum tasks=custom 'tasks.sequences=[{seqs}]' "
                f"'tasks.ids=[{ids}]' world.physics={world.physics_name}")
        shown = towers.get(tower_key(task, world, tolerance))
        if shown is None:
            raise ConfigError(
                f"practice task {task.id} has no stored buildable tower under world.physics={world.physics_name} "
                f"with practice.tolerance={tolerance:g}; compute them with: {COMMAND} "
                f"world.physics={world.physics_name} practice.tolerance={tolerance:g} "
                f"'practice.sequences=[{seqs}]' 'practice.ids=[{ids}]'")
        if not shown["actions"]:
            raise ConfigError(f"practice task {task.id} has no tower that stands with every placement off by "
                              f"{tolerance:g}; choose a smaller practice.tolerance or another sequence")
        tower, _ = replay(task, row["actions"])
        shown_tower, shown_reward = replay(task, shown["actions"])
        _, ground = replay(task, [])
        # a reward to compare with the 0.1 grid of overhangs: rounded, so 1.35 is not 1.3499999999999999
        pass_reward = round(ground + float(cfg.practice.threshold) * (shown_reward - ground), 9)
        out.append(PracticeTask(task, float(row["optimum"]), tower, shown_tower, float(shown_reward), tolerance,
                                float(pass_reward)))
    return out


def consent_text(path, contact: str = "", minutes: float = 20) -> tuple[str, str]:
    """The consent page's HTML (from ``path``, or the shipped text when None), with ``@contact@`` replaced by
    ``contact`` (HTML-escaped) and ``@duration@`` by ``minutes``, and its version: ``sha256:`` and the first 16 hex
    digits of the SHA-256 of the text as participants see it."""
    import hashlib
    import html

    file = Path(str(path)) if path else CONSENT_FILE
    try:
        text = file.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"consent_file: cannot read {file} ({getattr(err, 'strerror', None) or err}); give an "
                          "HTML file of the consent text, or null for the shipped one") from None
    if not text.strip():
        raise ConfigError(f"consent_file: {file} is empty; give an HTML file of the consent text")
    text = text.replace("@contact@", html.escape(contact or "the researcher")).replace("@duration@", f"{minutes:g}")
    return text, "sha256:" + hashlib.sha256(text.encode("utf-8")).hexdigest()[:16]


def load_settings(overrides: Sequence[str] = (), cfg: Optional[DictConfig] = None,
                  need_admin_token: bool = True) -> Settings:
    """Checked :class:`Settings` of ``conf/serve.yaml`` with ``overrides`` (or of a composed ``cfg``).

    ``need_admin_token=False`` is for commands that read the database directly (the export, reissuing a
    token): they answer to whoever can read the database, not to the HTTP API's admin token.
    """
    from overhang_framework.plugins import plain as _params
    from overhang_framework.plugins import Registry
    from overhang_framework.tasks import tasks_from_config

    cfg = compose(overrides) if cfg is None else cfg
    world_cfg = _params(cfg.world)
    try:
        world = Registry().create("world", world_cfg)
    except ValueError as err:
        raise ConfigError(f"world: {err}") from None
    tasks = tasks_from_config(cfg.tasks)
    conditions = list(cfg.conditions or [])
    limits = time_limits(cfg.get("time_limits"))
    allowed = ("time_limited", "unconstrained", *limits)
    if not conditions or any(c not in allowed for c in conditions) or len(set(conditions)) != len(conditions):
        raise ConfigError(f"conditions must be a non-empty list of distinct names from {', '.join(allowed)} "
                          f"(another condition needs its entry in time_limits), got {conditions!r}")
    run_dir = Path(str(cfg.run_dir))
    database = database_url(cfg.database, run_dir)
    token = cfg.admin_token or os.environ.get(ADMIN_ENV)
    if not token and need_admin_token:
        raise ConfigError(f"no admin token: set admin_token=... or the environment variable {ADMIN_ENV}")
    if token and len(str(token)) < MIN_ADMIN_TOKEN:
        raise ConfigError(f"the admin token must have at least {MIN_ADMIN_TOKEN} characters, got {len(str(token))} "
                          "(one to use: openssl rand -hex 24)")
    max_attempts = OmegaConf.select(cfg, "practice.max_attempts")
    if max_attempts is not None and (isinstance(max_attempts, bool) or not isinstance(max_attempts, int)
                                     or max_attempts < 1):
        raise ConfigError(f"practice.max_attempts must be a whole number >= 1 or null (no limit), "
                          f"got {max_attempts!r}")
    public_url = cfg.get("public_url")
    if public_url is not None and not str(public_url).startswith(("http://", "https://")):
        raise ConfigError(f"public_url must start with http:// or https:// (or be null), got {public_url!r}")
    threshold = OmegaConf.select(cfg, "practice.threshold")
    if isinstance(threshold, bool) or not isinstance(threshold, (int, float)) or not 0 <= threshold <= 1:
        raise ConfigError(f"practice.threshold must be a number in [0, 1], got {threshold!r}")
    port = cfg.port
    if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port < 65536:
        raise ConfigError(f"port must be a whole number in [0, 65535], got {port!r}")
    practice_ids = {str(i) for i in cfg.practice.ids}
    overlap = practice_ids & {t.id for t in tasks}
    if overlap:
        raise ConfigError(f"practice task ids {sorted(overlap)} are also main tasks; practice is excluded from the "
                          "stimulus pool")
    main_seqs = {t.sequence for t in tasks}
    practice = practice_tasks(cfg, world)
    for p in practice:
        if p.task.sequence in main_seqs:
            raise ConfigError(f"practice task {p.task.id} has the sequence of a main task; practice is excluded "
                              "from the stimulus pool")
    web_dir = Path(str(cfg.web_dir)) if cfg.web_dir else None
    forwarded = forwarded_ips(cfg.get("forwarded_allow_ips"))
    counts = {}
    for key, minimum in (("workers", 1), ("physics_processes", 0)):
        value = cfg.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ConfigError(f"{key} must be a whole number >= {minimum}, got {value!r}")
        counts[key] = value
    duration, durations = consent_durations(cfg.get("duration"), cfg.get("durations"), conditions, limits)
    consents = {c: consent_text(cfg.get("consent_file"), str(cfg.contact or ""), durations[c]) for c in conditions}
    consent_html, consent_version = study_consent(consents)
    allow_change = cfg.get("allow_settings_change")
    if not isinstance(allow_change, bool):
        raise ConfigError(f"allow_settings_change must be true or false, got {allow_change!r}")
    source = cfg.get("source")
    if source not in ("human", "simulated"):
        raise ConfigError(f"source must be human or simulated (a pilot), got {source!r}")
    return Settings(
        decline_url=str(cfg.get("decline_url") or "/declined"), source=source, consent_html=consent_html, consent_version=consent_version, consents=consents, durations=durations, duration=duration,
        consent_file=None if cfg.get("consent_file") is None else str(cfg.get("consent_file")),
        allow_settings_change=allow_change,
        world=world_cfg, tasks=tasks, practice=practice, practice_threshold=float(threshold),
        practice_max_attempts=max_attempts, conditions=conditions,
        time_limit=_number(cfg, "time_limit"), time_grace=_number(cfg, "time_grace", strict=False),
        database=str(database), admin_token=str(token or ""), completion_url=str(cfg.completion_url),
        screen_out_url=str(cfg.screen_out_url), contact=str(cfg.contact or ""),
        public_url=str(public_url).rstrip("/") if public_url else None,
        bonus_per_unit=_number(cfg, "bonus_per_unit", strict=False), currency=str(cfg.currency),
        mouse_hz=_number(cfg, "mouse_hz"), animation_fps=_number(cfg, "animation_fps"), seed=int(cfg.seed),
        run_dir=run_dir, web_dir=web_dir, host=str(cfg.host), port=int(port), **counts,
        keep_alive=_number(cfg, "keep_alive"), forwarded_allow_ips=forwarded,
        time_limits={c: limits[c] for c in conditions if c in limits})


def consent_durations(default, value, conditions: Sequence[str],
                      limits: Mapping[str, Optional[float]] = {}) -> tuple[float, dict[str, float]]:
    """``duration`` (``default``) and each condition's expected duration in minutes: its entry of ``durations``
    (``value``), else ``duration``. A duration is a number > 0; an entry names a condition of the study, or one of
    ``time_limits`` (a level not served now, whose participants keep it), else it is refused in one line."""
    def minutes(where: str, v) -> float:
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
            raise ConfigError(f"{where} must be a number of minutes > 0, got {v!r}")
        return float(v)

    base = minutes("duration", default)
    value = OmegaConf.to_container(value) if OmegaConf.is_config(value) else (value or {})
    if not isinstance(value, dict):
        raise ConfigError(f"durations must map condition names to minutes, got {value!r}")
    known = list(dict.fromkeys([*conditions, *limits, "time_limited", "unconstrained"]))
    own = {}
    for name, v in value.items():
        if name not in known:
            raise ConfigError(f"durations: {name!r} is not a condition of the study (its conditions and time_limits: "
                              f"{', '.join(known)}); remove it with '~durations.{name}'")
        own[name] = minutes(f"durations.{name}", v)
    return base, {**own, **{c: own.get(c, base) for c in conditions}}


def study_consent(consents: Mapping[str, tuple[str, str]]) -> tuple[str, str]:
    """The study's consent text and version, from each condition's: the shared one when every condition shows the
    same text; else the first condition's text, and a version of them all (``sha256:`` and 16 hex digits of the
    conditions' versions in order), so that a change to any condition's text changes it."""
    import hashlib

    texts = list(consents.values())
    if len({v for _, v in texts}) <= 1:
        return texts[0]
    joined = ";".join(f"{c}={v}" for c, (_, v) in consents.items())
    return texts[0][0], "sha256:" + hashlib.sha256(joined.encode("utf-8")).hexdigest()[:16]


def time_limits(value) -> dict:
    """``time_limits`` checked: a mapping of condition names (letters, digits and ``_``, not the two built-in
    ones) to seconds > 0 or null (no limit)."""
    import re

    value = OmegaConf.to_container(value) if OmegaConf.is_config(value) else (value or {})
    if not isinstance(value, dict):
        raise ConfigError(f"time_limits must map condition names to seconds or null, got {value!r}")
    out = {}
    for name, seconds in value.items():
        if not isinstance(name, str) or not re.fullmatch(r"[a-z][a-z0-9_]{0,39}", name) \
                or name in ("time_limited", "unconstrained"):
            raise ConfigError(f"time_limits: {name!r} is not a name for a condition: lowercase letters, digits and _ "
                              "(at most 40), other than time_limited (its limit is time_limit) and unconstrained")
        if seconds is not None and (isinstance(seconds, bool) or not isinstance(seconds, (int, float))
                                    or not seconds > 0):
            raise ConfigError(f"time_limits.{name} must be a number of seconds > 0 or null (no limit), "
                              f"got {seconds!r}")
        out[name] = None if seconds is None else float(seconds)
    return out


def forwarded_ips(value) -> str:
    """``forwarded_allow_ips`` checked, as the comma-separated text uvicorn reads: addresses or networks, or ``*``."""
    import ipaddress

    items = [str(v).strip() for v in value] if isinstance(value, (list, tuple)) or OmegaConf.is_list(value) \
        else [s.strip() for s in str(value if value is not None else "").split(",")]
    items = [i for i in items if i]
    for item in items:
        if item == "*":
            continue
        try:
            ipaddress.ip_network(item, strict=False)
        except ValueError:
            raise ConfigError(f"forwarded_allow_ips must list addresses or networks of the reverse proxy "
                              f"(127.0.0.1, 10.0.0.0/8, ...) or be '*', got {item!r}") from None
    if not items:
        raise ConfigError("forwarded_allow_ips must name at least one address (127.0.0.1: a proxy on this machine)")
    return ",".join(items)

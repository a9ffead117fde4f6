"""The experiment's HTTP API (FastAPI): sessions, placements, the end, and the admin export.

The routes and their bodies are documented in ``docs/experiment.md``. Each
placement is checked against the participant's position (derived from what is
stored) and the world's rules, then run through the world's physics and stored
under its unique key (participant, phase, trial, attempt, step). Every refusal
is ``{"error": "one line"}`` with a 4xx status, and nothing is written.

The server keeps the clock. A step's decision time starts when the server first
hands the step out: a step within a trial in the previous placement's reply, a
trial's first step when the page starts it (``POST /api/steps/start``). A reload
continues that clock. The time a placement took is the server's (its arrival
less that start), stored beside the page's own measurement; in ``time_limited``
a placement that arrives after the limit plus ``time_grace`` is stored as a
timeout.
"""

from __future__ import annotations

import datetime as dt
import hmac
import json
import math
import os
import re
import secrets
import time
from contextlib import asynccontextmanager
from urllib.parse import urlencode
from dataclasses import asdict, dataclass
from typing import Annotated, Callable, Literal, Mapping, Optional, Sequence

import numpy as np
from fastapi import Depends, FastAPI, Header, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse
from pydantic import BaseModel, ConfigDict, Field, field_validator
from sqlalchemy.exc import SQLAlchemyError
from starlette.exceptions import HTTPException as StarletteHTTPException

from overhang_framework import rules
from overhang_framework.version import __version__
from overhang_framework.experiment.forwarded import ForwardedHeaders
from overhang_framework.experiment.outcome import Outcomes
from overhang_framework.experiment.provenance import digest as settings_digest, study_settings
from overhang_framework.experiment.settings import Settings
from overhang_framework.experiment.store import (Conflict, Participant, Placement, SettingsChanged, Store,
                                                 database_reason, request_hash, token_hash, utc_iso)
from overhang_framework.geometry import MAX_LAYER, Action, Geometry, overhang
from overhang_framework.interfaces import Task

PARTICIPANT_ID = re.compile(r"^[A-Za-z0-9_.@:-]{1,200}$")
#: Wrong admin tokens one address may send within ``ADMIN_WINDOW`` seconds before it is refused (429) for the rest of
#: the window: with a token of at least 16 characters (``MIN_ADMIN_TOKEN``) guessing is hopeless. Each server process
#: counts its own.
ADMIN_GUESSES, ADMIN_WINDOW = 10, 60.0
#: The longest STUDY_ID or SESSION_ID a link may carry (the database's columns).
MAX_PARAM = 200
#: The largest request body the server reads, in bytes (a placement's 36,000 mouse samples fit in about 2 MB).
MAX_BODY = 4 * 2 ** 20
#: What a refusal without words of its own tells a participant, by its status.
PAGE_WORDS = {
    401: "This page has lost its session with the study. Please open the study again from the link you were given",
    403: "This page's session is not valid for the study any more. Please open the study again from the link "
         "you were given",
    409: "This page is out of step with the study's server. Please reload the page",
    410: "This part of the study is closed",
    422: "The page sent the study's server something it could not take. Please reload the page",
}
#: What a participant is asked to do when a link is not one the study can take.
USE_YOUR_LINK = "Please open the study from the link you were given"
#: The most mouse samples or dwell entries one placement may carry (10 minutes at 60 Hz).
MAX_SAMPLES = 36_000
#: A page's timeout may reach the server this much before the step's time limit (seconds): the page counts
#: down from the time left the server sent, so its timeout arrives after the limit, less clock jitter.
EARLY_TIMEOUT = 0.25


class Refused(Exception):
    """A request refused with ``status`` and a one-line ``message`` (``extra``: more keys of the reply)."""

    def __init__(self, status: int, message: str, /, **extra):
        super().__init__(message)
        self.status, self.message, self.extra = status, message, extra


class SessionIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    params: dict[str, str] = Field(default_factory=dict)
    # a pilot's simulated participant (experiment pilot sends it): stored as source simulated, left out of a
    # default export of a study of people
    simulated: bool = False


class ConsentIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    version: str = Field(max_length=100)


class StepIn(BaseModel):
    model_config = ConfigDict(extra="forbid")
    phase: Literal["practice", "main"]
    trial: int = Field(ge=1)
    attempt: int = Field(default=1, ge=1)
    step: int = Field(ge=1)


class PlacementIn(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    phase: Literal["practice", "main"]
    trial: int = Field(ge=1)
    attempt: int = Field(default=1, ge=1)
    step: int = Field(ge=1)
    x: Optional[float] = None
    layer: Optional[int] = None
    timed_out: bool = False
    decision_time: float = Field(ge=0)
    #: A pilot's simulated participant only: the seconds its planner computed before the decision began (the
    #: simulator's cost on this machine, not the participant's), taken off the server's clock.
    simulator_time: float = Field(default=0.0, ge=0)
    trajectory: list[tuple[float, float, float]] = Field(default_factory=list, max_length=MAX_SAMPLES)
    dwell: list[tuple[float, int, float]] = Field(default_factory=list, max_length=MAX_SAMPLES)

    @field_validator("trajectory")
    @classmethod
    def _times_go_forward(cls, value):
        times = [t for t, _, _ in value]
        if any(t < 0 for t in times) or any(b < a for a, b in zip(times, times[1:])):
            raise ValueError("times must start at 0 or later and never go back")
        return value

    @field_validator("dwell")
    @classmethod
    def _dwell_non_negative(cls, value):
        if any(s < 0 or layer < 0 for _, layer, s in value):
            raise ValueError("layers and seconds must be >= 0")
        return value


@dataclass
class Position:
    """Where a participant is: the next placement's phase, trial, attempt and step, and the tower it goes on."""

    phase: str
    trial: int
    attempt: int
    step: int
    tower: list
    total_reward: float


def _tower_after(sequence, rows) -> list:
    tower = [[float(sequence[0]), 0.0, 0]]
    tower += [[r.width, r.x, r.layer] for r in rows if not r.timed_out]
    return tower


def total_reward(last_steps) -> float:
    """The sum of the rewards of the trials whose last steps (placements) are ``last_steps`` and are over.
    Rewards lie on the 0.1 grid of overhangs: the sum is rounded back onto it (16.8, not 16.800000000000004)."""
    return round(sum(r.reward or 0.0 for r in last_steps if r.trial_over), 9)


def position(settings: Settings, participant: Participant, rows: list[Placement],
             tasks: Optional[Sequence[Task]] = None) -> Position:
    """The position after ``rows`` (the participant's placements).

    ``phase`` is ``practice``, ``main``, ``done``, or ``screened_out`` once the participant was screened
    out (recorded when a practice attempt used up ``practice_max_attempts``: a later change of that setting
    moves nobody in or out; ``trial`` and ``attempt`` then name the last attempt). ``tasks``: the participant's
    main tasks (default :func:`main_tasks`).
    """
    groups: dict[tuple, list[Placement]] = {}
    for r in sorted(rows, key=lambda r: (r.phase, r.trial, r.attempt, r.step)):
        groups.setdefault((r.phase, r.trial, r.attempt), []).append(r)
    total = total_reward(g[-1] for (phase, _, _), g in groups.items() if phase == "main")
    if participant.screened_out_at is not None:
        last = max((key for key in groups if key[0] == "practice"), default=("practice", 1, 1))
        return Position("screened_out", last[1], last[2], 0, [], total)
    for k, practice in enumerate(settings.practice, 1):
        attempt = 1
        while True:
            done = groups.get(("practice", k, attempt), [])
            if done and done[-1].trial_over:
                if done[-1].passed:
                    break
                attempt += 1
                continue
            return Position("practice", k, attempt, len(done) + 1, _tower_after(practice.task.sequence, done), total)
    tasks = main_tasks(settings, participant) if tasks is None else tasks
    for t, task in enumerate(tasks, 1):
        done = groups.get(("main", t, 1), [])
        if not (done and done[-1].trial_over):
            return Position("main", t, 1, len(done) + 1, _tower_after(task.sequence, done), total)
    return Position("done", len(tasks), 1, 0, [], total)


def main_tasks(settings: Settings, participant: Participant, started: Optional[Mapping] = None) -> list[Task]:
    """The participant's main tasks in their order: those of ``started`` (the study's settings when they started,
    :func:`started_under`) when given, else of ``settings``."""
    if started is not None:
        by_id = {i: Task(i, tuple(float(w) for w in widths)) for i, widths in started.get("tasks", [])}
    else:
        by_id = {t.id: t for t in settings.tasks}
    missing = [i for i in participant.order if i not in by_id]
    if missing:
        raise Refused(500, f"participant {participant.id}'s trials name tasks the server no longer has "
                           f"({', '.join(missing)}); serve with the tasks the study started with")
    return [by_id[i] for i in participant.order]


def _utc(when) -> dt.datetime:
    """A stored time as an aware UTC datetime (SQLite gives them back naive)."""
    when = dt.datetime.fromisoformat(when) if isinstance(when, str) else when
    return when if when.tzinfo is not None else when.replace(tzinfo=dt.timezone.utc)


def started_under(study, participant: Participant) -> dict:
    """The study's settings when ``participant`` started: those the first settings change after their start
    replaced (kept in the study's history), else the study's settings now."""
    began = _utc(participant.created_at)
    for event in study.history or []:
        if event.get("what") == "settings" and _utc(event["at"]) > began:
            return event["previous"]["settings"]
    return study.settings


def public_base(settings: Settings, request: Optional[Request] = None, store: Optional[Store] = None) -> str:
    """The address participants open, without a trailing slash: ``public_url=`` when set; else, within a
    request, the address the request came to (through a trusted proxy: the one the participant opened,
    :mod:`~overhang_framework.experiment.forwarded`); else the one stored with the study in ``store`` (the
    ``public_url`` it was served with, else the host and port it last listened on); else ``http://host:port``."""
    if settings.public_url:
        return settings.public_url
    if request is not None:
        return str(request.base_url).rstrip("/")
    study = store.study() if store is not None else None
    if study is not None:
        return study.public_url or study.address
    return f"http://{settings.host}:{settings.port}"


def begin_study(settings: Settings, store: Store):
    """The study's stored record, made or checked against ``settings`` (:meth:`Store.begin_study`); a change of
    the settings that is not allowed is one :class:`~overhang_framework.errors.ConfigError` line listing it."""
    from overhang_framework.errors import ConfigError
    from overhang_framework.experiment.provenance import hashes, study_settings
    from overhang_framework.version import versions

    try:
        return store.begin_study(study_settings(settings), hashes(settings), versions(),
                                 f"http://{settings.host}:{settings.port}", settings.public_url,
                                 allow_change=settings.allow_settings_change)
    except SettingsChanged as err:
        consent = any(c.startswith("consent_version:") for c in err.changes)
        note = (" (the consent text changed: it includes the contact= and the session's duration=, so a new "
                "contact, duration, durations or consent_file changes it)" if consent else "")
        raise ConfigError(f"the study in this database runs with other settings ({'; '.join(err.changes)}){note}; serve "
                          "it with the settings it started with, or add allow_settings_change=true to change them "
                          "(the change is recorded with the study)") from None


def resume_link(settings: Settings, participant: Participant, token: str, base: Optional[str] = None) -> str:
    """The address that resumes ``participant``'s session with ``token`` in any browser (``base``: the
    address participants open, :func:`public_base`)."""
    base = base or public_base(settings)
    if participant.study_id is not None or participant.session_id is not None:
        params = {"PROLIFIC_PID": participant.id, "STUDY_ID": participant.study_id or "",
                  "SESSION_ID": participant.session_id or ""}
    else:
        params = {"participant": participant.id}
    return f"{base}/?{urlencode({**params, 'token': token})}"


def unknown_participant(store: Store, pid: str) -> Refused:
    """The refusal of a request about participant ``pid``, whom the study does not hold: which it does."""
    known = [p.id for p in store.participants()]
    shown = ", ".join(known[:10]) + (", ..." if len(known) > 10 else "")
    return Refused(404, f"no participant {pid!r}; the study has {len(known)}" + (f": {shown}" if known else ""))


def reissue(settings: Settings, store: Store, pid: str, base: Optional[str] = None) -> tuple[str, str]:
    """A new session token for participant ``pid`` (the old one stops working) and its resume link (starting
    with ``base``, by default :func:`public_base`)."""
    participant = store.participant(pid)
    if participant is None:
        raise unknown_participant(store, pid)
    token = secrets.token_urlsafe(24)
    participant = store.set_token(pid, token)
    return token, resume_link(settings, participant, token, base or public_base(settings, store=store))


def withdraw(store: Store, pid: str) -> dict:
    """Delete participant ``pid`` and everything stored of them (:meth:`Store.withdraw`); what was deleted."""
    deleted = store.withdraw(pid)
    if deleted is None:
        raise unknown_participant(store, pid)
    study = store.study()
    return {"participant": pid, "deleted": deleted, "withdrawn": study.withdrawn if study is not None else 1}


def create_app(settings: Settings, store: Optional[Store] = None, outcomes: Optional[Outcomes] = None,
               clock: Callable[[], float] = time.time) -> FastAPI:
    """The FastAPI app of the experiment described by ``settings``.

    ``store`` defaults to the database ``settings.database`` names, ``outcomes`` to the world's physics,
    ``clock`` (seconds, shared by every server process) to the system's wall clock; the front end in
    ``settings.web_dir`` is served at ``/`` when given.
    """
    own_store = store is None
    store = store or Store(settings.database)
    study = begin_study(settings, store)
    # what every placement stored by this server carries: the code's version and the settings' hashes
    provenance = {"framework_version": study.framework_version, "commit": study.commit,
                  "settings_hash": study.settings_hash, "tasks_hash": study.tasks_hash}
    outcomes = outcomes or Outcomes(settings.world, fps=settings.animation_fps, processes=settings.physics_processes)
    in_force = json.loads(json.dumps(study_settings(settings)))  # as the study stores them
    kept: set[str] = set()

    first_settings: dict[str, dict] = {}
    first_tasks: dict[str, list[Task]] = {}

    def started(p: Participant) -> dict:
        """The study's settings when ``p`` started (:func:`started_under`; the same whatever changes later)."""
        if p.id not in first_settings:
            first_settings[p.id] = started_under(store.study(), p)
        return first_settings[p.id]

    def tasks_of(p: Participant) -> list[Task]:
        """``p``'s main tasks, those of the settings they started under: an allowed change of the tasks moves
        nobody already playing."""
        if p.id not in first_tasks:
            first_tasks[p.id] = main_tasks(settings, p, started(p))
        return first_tasks[p.id]

    def played_hash(p: Participant) -> str:
        """The hash of the settings ``p`` plays under: the study's, with what they started with kept through an
        allowed change (their level, even when it was dropped since; its time limit; their tasks); settings other
        than the study's are kept in the store under it."""
        level = p.condition
        now = (settings.time_limit if level == "time_limited" else None if level == "unconstrained"
               else settings.time_limits.get(level))
        in_study = level in settings.conditions and (level in ("time_limited", "unconstrained")
                                                     or level in settings.time_limits)
        same_tasks = started(p).get("tasks") == in_force.get("tasks")
        if in_study and same_tasks and (level == "unconstrained" or p.time_limit == now):
            return provenance["settings_hash"]
        played = json.loads(json.dumps(in_force))
        if level not in played["conditions"]:
            played["conditions"] = [*played["conditions"], level]
        if level == "time_limited":
            played["time_limit"] = p.time_limit
        elif level != "unconstrained":
            played["time_limits"] = {**played.get("time_limits", {}), level: p.time_limit}
        if not same_tasks:
            played["tasks"] = started(p)["tasks"]
        h = settings_digest(played)
        if h not in kept:
            store.keep_settings(h, played)
            kept.add(h)
        return h

    @asynccontextmanager
    async def lifespan(_app):
        outcomes.start()
        yield
        outcomes.close()
        if own_store:
            store.close()  # SQLite: what its write-ahead log holds goes into the database file

    app = FastAPI(title="Overhang Tower experiment", version="1", lifespan=lifespan)
    app.state.store, app.state.settings, app.state.outcomes = store, settings, outcomes
    app.add_middleware(ForwardedHeaders, trusted=settings.forwarded_allow_ips)

    @app.middleware("http")
    async def _arrival(request: Request, call_next):
        # a placement's time is taken as it arrives, not after it waited for a thread or the database
        request.state.arrived = clock()
        return await call_next(request)

    @app.exception_handler(Refused)
    async def _refused(_request: Request, err: Refused):
        extra = err.extra if "message" in err.extra else {**err.extra, **for_participant(
            PAGE_WORDS.get(err.status, "The study's server could not take this step. Please reload the page"),
            settings)}
        return JSONResponse({"error": err.message, **extra}, status_code=err.status)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, err: StarletteHTTPException):
        path, status = request.url.path, err.status_code
        if path.startswith("/api") and status in (404, 405):
            # behind the front end's mount at /, an API path may reach the static files: decide by the routes
            allowed = sorted({m for route in app.routes if getattr(route, "path_regex", None) is not None
                              and getattr(route, "methods", None) and route.path_regex.match(path)
                              for m in route.methods} - {"HEAD"})
            status = 405 if allowed and request.method not in allowed else 404
            message = (f"{request.method} is not allowed on {path}; use {' or '.join(allowed)}" if status == 405
                       else f"no such path: {path}; the API's routes are in docs/experiment.md")
            return JSONResponse({"error": message}, status_code=status)
        if "text/html" in request.headers.get("accept", "") and status == 404:
            return HTMLResponse(info_page("Page not found", "<p>There is no page at this address. Please use the "
                                          "link you were given to take part.</p>"), status_code=404)
        message = f"no such path: {path}" if status == 404 else str(err.detail)
        return JSONResponse({"error": message}, status_code=status, headers=getattr(err, "headers", None))

    @app.exception_handler(RequestValidationError)
    async def _invalid(_request: Request, err: RequestValidationError):
        return JSONResponse({"error": _one_line(err), **for_participant(
            "The page sent the study's server something it could not read. Please reload the page", settings)},
            status_code=422)

    @app.exception_handler(SQLAlchemyError)
    async def _database(request: Request, err: SQLAlchemyError):
        import logging

        logging.getLogger("overhang_framework.experiment").error("%s %s: the database failed: %s", request.method,
                                                                  request.url.path, database_reason(err))
        return JSONResponse({"error": "the database cannot be reached or failed; GET /api/health says more",
                             "reason": "unavailable", **for_participant(
                                 "The study's server cannot store your answers just now. Please wait a minute and "
                                 "try again; nothing you did so far is lost", settings)}, status_code=503)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, err: Exception):
        import logging

        logging.getLogger("overhang_framework.experiment").exception("%s %s failed", request.method,
                                                                      request.url.path)
        return JSONResponse({"error": f"the server failed on {request.method} {request.url.path}: "
                                      f"{type(err).__name__}; its log has the traceback", "reason": "server_error",
                             **for_participant("The study's server had a problem with this step. Please wait a "
                                               "moment and try again", settings)}, status_code=500)

    app.add_middleware(BodyLimit, limit=MAX_BODY, reply=lambda: {
        "error": f"the request body is larger than the server takes ({MAX_BODY} bytes)", "reason": "too_large",
        **for_participant("The page sent more than the study's server takes. Please reload the page", settings)})

    def participant_of(authorization: Annotated[Optional[str], Header()] = None) -> Participant:
        token = _bearer(authorization)
        if token is None:
            raise Refused(401, "no session token: send Authorization: Bearer TOKEN as issued by POST /api/sessions")
        found = store.by_token(token)
        if found is None:
            raise Refused(403, "unknown session token")
        return found

    wrong_tokens: dict[str, list[float]] = {}

    def admin_token_is(token: str, request: Request) -> bool:
        """Whether ``token`` is the admin token; an address that sent :data:`ADMIN_GUESSES` wrong ones within
        :data:`ADMIN_WINDOW` seconds is refused (429) until the first of them is that old, whatever it sends."""
        who = request.client.host if request.client else "?"
        now = clock()
        recent = [t for t in wrong_tokens.get(who, []) if now - t < ADMIN_WINDOW]
        if len(recent) >= ADMIN_GUESSES:
            wait = ADMIN_WINDOW - (now - recent[0])
            raise Refused(429, f"{len(recent)} wrong admin tokens from this address in {ADMIN_WINDOW:.0f} s; try again "
                               f"in {math.ceil(wait)} s")
        if hmac.compare_digest(token.encode(), settings.admin_token.encode()):
            return True
        wrong_tokens[who] = [*recent, now]
        return False

    def admin(request: Request, x_admin_token: Annotated[Optional[str], Header()] = None) -> None:
        if not x_admin_token:
            raise Refused(401, "no admin token: send X-Admin-Token")
        if not admin_token_is(x_admin_token, request):
            raise Refused(403, "wrong admin token")

    def time_limit_of(p: Participant) -> Optional[float]:
        """The participant's time limit, as stored when they started (a restart with other settings keeps it)."""
        return p.time_limit

    def clock_state(p: Participant, pos: Position, issued: Optional[float], now: float) -> Optional[dict]:
        """The clock of the step at ``pos``: null when the step has not been handed out yet."""
        if pos.phase not in ("practice", "main") or issued is None:
            return None
        elapsed = max(0.0, now - issued)
        limit = time_limit_of(p)
        return {"phase": pos.phase, "trial": pos.trial, "attempt": pos.attempt, "step": pos.step,
                "elapsed": round(elapsed, 3),
                "time_left": None if limit is None else round(max(0.0, limit - elapsed), 3)}

    def current_clock(p: Participant, pos: Position) -> Optional[dict]:
        if pos.phase not in ("practice", "main"):
            return None
        return clock_state(p, pos, store.clock(p.id, pos.phase, pos.trial, pos.attempt, pos.step), clock())

    def session_payload(p: Participant, token: Optional[str]) -> dict:
        pos = position(settings, p, store.steps(p.id), tasks_of(p))
        out = {
            "participant": p.id, "condition": p.condition, "time_limit": time_limit_of(p),
            "time_grace": settings.time_grace,
            "grid": {"half_width": 4.0, "height": 8.0, "block_height": 0.6, "max_layer": MAX_LAYER},
            "mouse_hz": settings.mouse_hz, "bonus_per_unit": settings.bonus_per_unit, "currency": settings.currency,
            "practice_threshold": settings.practice_threshold,
            "practice_max_attempts": settings.practice_max_attempts,
            "practice": [{"trial": k, "task_id": pt.task.id, "sequence": list(pt.task.sequence)}
                         for k, pt in enumerate(settings.practice, 1)],
            "trials": [{"trial": t} for t in range(1, len(p.order) + 1)],
            "position": asdict(pos), "clock": current_clock(p, pos), "completed": p.completed_at is not None,
            "contact": settings.contact,
            "consent": dict(zip(("html", "version"), settings.consent_of(p.condition)),
                            given=p.consented_at is not None),
        }
        if token is not None:
            out["token"] = token
        if p.completed_at is not None:
            out.update(completion_url=settings.completion_url, bonus=p.bonus)
        if pos.phase == "screened_out":
            out["screen_out_url"] = settings.screen_out_url
        return out

    @app.post("/api/sessions")
    def start(body: SessionIn, request: Request, authorization: Annotated[Optional[str], Header()] = None,
              x_admin_token: Annotated[Optional[str], Header()] = None):
        params = body.params
        if body.simulated and not (x_admin_token and admin_token_is(x_admin_token, request)):
            raise Refused(403, "a simulated session needs the study's admin token (X-Admin-Token): only a pilot the "
                               "lab runs marks its participants simulated")
        pid = params.get("PROLIFIC_PID") or params.get("participant")
        if not pid:
            raise Refused(422, "no participant: the page's URL needs PROLIFIC_PID (with STUDY_ID and SESSION_ID) "
                               "or participant", reason="bad_link", **for_participant(
                                   f"This link does not say who you are. {USE_YOUR_LINK}", settings))
        if not PARTICIPANT_ID.match(pid):
            raise Refused(422, "a participant id is 1 to 200 letters, digits or _ . @ : -", reason="bad_link",
                          **for_participant(f"The participant id in this link is not one the study can take. "
                                            f"{USE_YOUR_LINK}", settings))
        long = [k for k in ("STUDY_ID", "SESSION_ID") if len(params.get(k) or "") > MAX_PARAM]
        if long:
            raise Refused(422, f"{' and '.join(long)} longer than {MAX_PARAM} characters", reason="bad_link",
                          **for_participant(f"This link is not one the study can take. {USE_YOUR_LINK}", settings))
        token = _bearer(authorization)
        known = store.participant(pid)
        if (known is not None and (token is None or not hmac.compare_digest(token_hash(token), known.token_hash))) \
                or (known is None and store.withdrew(pid)):
            # one answer whether they are half way, finished or withdrawn: the id alone says nothing of whether or how
            # someone took part (their session token does: with it, a finished participant sees their end page; a
            # withdrawn one has none, and the researcher who deleted them can tell them why they cannot come back)
            raise Refused(403, f"participant {pid} already has a session, held by another browser or an earlier "
                               "link; the researcher can issue a new link (experiment reissue)",
                          reason="session_elsewhere", contact=settings.contact)
        if known is not None:
            return JSONResponse(session_payload(known, token), status_code=200)
        token = secrets.token_urlsafe(24)

        def newcomer(counts: dict[str, int]) -> Participant:
            """The participant in a condition with the fewest so far (counted in the transaction that stores them)."""
            fewest = min(counts.values())
            tied = [c for c in settings.conditions if counts[c] == fewest]
            rng = np.random.default_rng([settings.seed, sum(counts.values()), *map(ord, pid)])
            condition = tied[int(rng.integers(len(tied)))]
            order = [settings.tasks[i].id for i in rng.permutation(len(settings.tasks))]
            return Participant(id=pid, study_id=params.get("STUDY_ID"), session_id=params.get("SESSION_ID"),
                               token_hash=token_hash(token), condition=condition, order=order,
                               time_limit=settings.limit_of(condition),
                               source=source)

        source = "simulated" if body.simulated or settings.source == "simulated" else "human"
        p = store.add_newcomer(settings.conditions, newcomer, source)
        if p is None:
            raise Refused(409, f"participant {pid} was started by another request at the same moment")
        return JSONResponse(session_payload(p, token), status_code=201)

    @app.get("/api/session")
    def current(p: Participant = Depends(participant_of)):
        return session_payload(p, None)

    @app.post("/api/consent")
    def consent(body: ConsentIn, p: Participant = Depends(participant_of)):
        version = settings.consent_of(p.condition)[1]
        if p.consented_at is None and body.version != version:
            raise Refused(409, f"the consent text has changed (version {version}, the page showed "
                               f"{body.version}); reload the page to read it")
        p = store.consent(p.id, version)
        return {"consent_version": p.consent_version, "consented_at": utc_iso(p.consented_at)}

    @app.post("/api/decline")
    def decline(p: Participant = Depends(participant_of)):
        if not store.decline(p.id):
            raise Refused(409, "the participant has agreed already; to withdraw, ask the researcher "
                               f"({settings.contact})")
        return {"decline_url": settings.decline_url}

    def consented(p: Participant) -> None:
        if p.consented_at is None:
            raise Refused(403, "no consent is recorded for this participant: POST /api/consent first",
                          reason="no_consent")

    @app.post("/api/steps/start")
    def start_step(body: StepIn, p: Participant = Depends(participant_of)):
        consented(p)
        pos = position(settings, p, store.steps(p.id), tasks_of(p))
        if pos.phase not in ("practice", "main"):
            raise Refused(409, f"nothing to start: the participant's phase is {pos.phase}")
        if (body.phase, body.trial, body.attempt, body.step) != (pos.phase, pos.trial, pos.attempt, pos.step):
            raise Refused(409, f"out of order: the next step is {pos.phase} trial {pos.trial} attempt {pos.attempt} "
                               f"step {pos.step}, not {body.phase} trial {body.trial} attempt {body.attempt} "
                               f"step {body.step}")
        now = clock()
        issued = store.start_clock(p.id, pos.phase, pos.trial, pos.attempt, pos.step, now)
        task = settings.practice[pos.trial - 1].task if pos.phase == "practice" else tasks_of(p)[pos.trial - 1]
        return {"position": asdict(pos), "clock": clock_state(p, pos, issued, now),
                "task": {"task_id": task.id, "sequence": list(task.sequence)}}

    @app.post("/api/placements")
    def place(body: PlacementIn, request: Request, p: Participant = Depends(participant_of)):
        digest = request_hash(body.model_dump(mode="json"))
        rows = store.steps(p.id)
        key = (body.phase, body.trial, body.attempt, body.step)
        stored = next((r for r in rows if (r.phase, r.trial, r.attempt, r.step) == key), None)
        if stored is not None:
            if stored.request_hash != digest:
                raise Refused(409, f"{body.phase} trial {body.trial} step {body.step} is already stored with a "
                                   "different placement")
            return fresh_clock(p, store.find(p.id, *key).response)
        consented(p)
        pos = position(settings, p, rows, tasks_of(p))
        if pos.phase == "done":
            raise Refused(409, "every trial is over; nothing more can be placed")
        if pos.phase == "screened_out":
            raise Refused(409, "the practice's attempts are used up; nothing more can be placed",
                          screen_out_url=settings.screen_out_url)
        expected = (pos.phase, pos.trial, pos.attempt, pos.step)
        if (body.phase, body.trial, body.attempt, body.step) != expected:
            raise Refused(409, f"out of order: the next placement is {pos.phase} trial {pos.trial} attempt "
                               f"{pos.attempt} step {pos.step}, not {body.phase} trial {body.trial} attempt "
                               f"{body.attempt} step {body.step}")
        if body.phase == "practice":
            practice = settings.practice[pos.trial - 1]
            task = practice.task
        else:
            practice, task = None, tasks_of(p)[pos.trial - 1]
        width = task.sequence[pos.step]
        limit = time_limit_of(p)
        limited = limit is not None
        if body.timed_out:
            if not limited:
                raise Refused(422, f"condition {p.condition} has no time limit, so no placement can time out")
            if body.x is not None or body.layer is not None:
                raise Refused(422, "a timed-out placement has x and layer null")
        elif body.x is None or body.layer is None:
            raise Refused(422, "a placement needs x and layer (or timed_out: true)")
        issued = store.clock(p.id, pos.phase, pos.trial, pos.attempt, pos.step)
        if issued is None:
            raise Refused(409, f"{pos.phase} trial {pos.trial} step {pos.step} has not been started: "
                               "POST /api/steps/start first")
        if body.simulator_time and (p.source or "human") != "simulated":
            raise Refused(422, "simulator_time is a pilot's: only a simulated participant's placement may carry it")
        server_time = round(max(0.0, request.state.arrived - issued - body.simulator_time), 3)
        late = bool(limited and not body.timed_out and server_time > limit + settings.time_grace)
        if body.timed_out and server_time < limit - EARLY_TIMEOUT:
            raise Refused(422, f"timed_out too early: the step has run {server_time:.2f} s of its "
                               f"{limit:g} s on the server's clock")
        timed_out = bool(body.timed_out or late)
        geometry = Geometry.from_tuples(pos.tower)
        if timed_out:
            stable, level, poses = None, None, [[[b.x, b.z, 0.0] for b in geometry.blocks]]
        else:
            reason = rules.illegal_reason(geometry, width, Action(float(body.x), int(body.layer)))
            if reason is not None:
                raise Refused(422, f"illegal placement of the {width:g} block at x={body.x:g}, layer {body.layer}: "
                                   f"{reason}")
            geometry = rules.place(geometry, width, Action(float(body.x), int(body.layer)))
            result = outcomes(geometry)
            stable, level, poses = result.stable, round(overhang(geometry), 9), result.poses
        last = pos.step == len(task.sequence) - 1
        trial_over = bool(timed_out or not stable or last)
        reward = (0.0 if timed_out or not stable else float(level)) if trial_over else None
        passed = None
        response: dict = {"stable": stable, "overhang": level, "reward": reward, "trial_over": trial_over,
                          "timed_out": timed_out, "late": late, "server_time": server_time,
                          "frames": {"fps": settings.animation_fps, "poses": poses}}
        if practice is not None and trial_over:
            passed = bool(reward >= practice.pass_reward - 1e-9)
            response.update(optimum=practice.optimum, shown_tower=practice.shown_tower,
                            shown_reward=practice.shown_reward, pass_reward=practice.pass_reward, passed=passed)
        record = Placement(
            participant_id=p.id, phase=body.phase, trial=body.trial, attempt=body.attempt, step=body.step,
            task_id=task.id, sequence=list(task.sequence), width=width,
            x=None if timed_out else body.x, layer=None if timed_out else body.layer,
            timed_out=timed_out, decision_time=body.decision_time, server_time=server_time,
            late_action=[body.x, body.layer] if late else None,
            trajectory=[list(s) for s in body.trajectory], dwell=[list(d) for d in body.dwell],
            tower_before=pos.tower, stable=stable, overhang=level, reward=reward, trial_over=trial_over,
            passed=passed, request_hash=digest, response={},
            **{**provenance, "settings_hash": played_hash(p)})
        attempts = settings.practice_max_attempts
        if passed is False and attempts is not None and pos.attempt >= attempts:
            after = Position("screened_out", pos.trial, pos.attempt, 0, [], pos.total_reward)
        else:
            after = position(settings, p, [*rows, record], tasks_of(p))
        response.update(total_reward=after.total_reward, position=asdict(after), clock=None)
        if after.phase == "screened_out":
            response["screen_out_url"] = settings.screen_out_url
        record.response = response
        try:
            stored = store.add_placement(record)
        except Conflict as err:
            raise Refused(409, str(err)) from None
        return fresh_clock(p, stored.response)

    def fresh_clock(p: Participant, response: dict) -> dict:
        """A placement's reply with the clock of the step it hands out: a step within the same trial starts
        when its reply is first sent (a retry gets the clock as it is now); a trial's first step is started by
        the page. A reply that screens the participant out records that (once; a retry finds it recorded)."""
        nxt = Position(**response["position"])
        if nxt.phase == "screened_out":
            store.screen_out(p.id)
        if response["trial_over"] or nxt.phase not in ("practice", "main"):
            return response
        now = clock()
        issued = store.start_clock(p.id, nxt.phase, nxt.trial, nxt.attempt, nxt.step, now)
        return {**response, "clock": clock_state(p, nxt, issued, now)}

    @app.post("/api/finish")
    def finish(p: Participant = Depends(participant_of)):
        pos = position(settings, p, store.steps(p.id), tasks_of(p))
        if pos.phase == "screened_out":
            raise Refused(409, "the participant was screened out in the practice; there is nothing to finish",
                          screen_out_url=settings.screen_out_url)
        if pos.phase != "done":
            raise Refused(409, f"not finished: the next placement is {pos.phase} trial {pos.trial} step {pos.step}")
        bonus = round(pos.total_reward * settings.bonus_per_unit, 2)
        done = store.complete(p.id, pos.total_reward, bonus)
        return {"completion_url": settings.completion_url, "bonus": done.bonus, "total_reward": done.total_reward,
                "currency": settings.currency}

    @app.get("/api/admin/export", dependencies=[Depends(admin)])
    def export(include_simulated: bool = False):
        from overhang_framework.experiment.export import export_jsonl

        text, _ = export_jsonl(store, include_simulated=include_simulated)
        return PlainTextResponse(text, media_type="application/x-ndjson")

    @app.get("/api/admin/study", dependencies=[Depends(admin)])
    def study_record():
        from overhang_framework.experiment.export import study_json

        return study_json(store)

    @app.post("/api/admin/participants/{pid}/withdraw", dependencies=[Depends(admin)])
    def withdraw_participant(pid: str):
        return withdraw(store, pid)

    @app.post("/api/admin/participants/{pid}/reissue", dependencies=[Depends(admin)])
    def reissue_token(pid: str, request: Request):
        token, link = reissue(settings, store, pid, public_base(settings, request))
        return {"participant": pid, "token": token, "resume_url": link}

    @app.get("/api/admin/participants", dependencies=[Depends(admin)])
    def participants():
        rows = []
        for p in store.participants():
            pos = position(settings, p, store.steps(p.id), tasks_of(p))
            rows.append({"participant": p.id, "study_id": p.study_id, "session_id": p.session_id,
                         "condition": p.condition, "phase": pos.phase, "trial": pos.trial, "attempt": pos.attempt,
                         "total_reward": pos.total_reward, "screened_out": p.screened_out_at is not None,
                         "completed": p.completed_at is not None, "bonus": p.bonus,
                         "tokens_issued": p.tokens_issued or 1})
        return rows

    @app.get("/api/health")
    def health():
        """Whether this server process answers and reaches the database: for a proxy's or a monitor's check."""
        reason = store.ping()
        body = {"status": "ok" if reason is None else "unavailable", "database": reason is None,
                "version": __version__, "workers": settings.workers, "pid": os.getpid()}
        if reason is not None:
            body["error"] = f"the database does not answer: {reason}"
        return JSONResponse(body, status_code=200 if reason is None else 503, headers={"Cache-Control": "no-store"})

    @app.get("/complete", response_class=HTMLResponse)
    def complete():
        return info_page("Thank you", "<p>Thank you for taking part. Your answers are saved; you can close this "
                                      "tab.</p>")

    @app.get("/declined", response_class=HTMLResponse)
    def declined():
        return info_page("Thank you", "<p>You chose not to take part. Nothing about you is kept; you can close "
                                      "this tab.</p>")

    @app.get("/screened-out", response_class=HTMLResponse)
    def screened_out():
        return info_page("Thank you", "<p>Thank you for your time. The study needs the practice towers to be "
                                      "passed, so it ends here for you. Your practice is saved; you can close "
                                      "this tab.</p>")

    if settings.web_dir is not None:
        import html

        from fastapi.staticfiles import StaticFiles

        page = (settings.web_dir / "index.html").read_text(encoding="utf-8")
        # the lab's contact in the page itself: an error met before the server answered names it too
        page = page.replace('<meta charset="utf-8" />', '<meta charset="utf-8" />\n    <meta name="overhang-contact" '
                            f'content="{html.escape(settings.contact or "", quote=True)}" />', 1)

        @app.get("/", response_class=HTMLResponse, include_in_schema=False)
        def index():
            return HTMLResponse(page, headers={"Cache-Control": "no-cache"})

        app.mount("/", StaticFiles(directory=str(settings.web_dir), html=True), name="web")
    return app


def info_page(title: str, body_html: str) -> str:
    """A page of the experiment's own look, for what the server shows outside the task."""
    return f"""<!doctype html>
<html lang="en"><head><meta charset="utf-8"><meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title><link rel="icon" href="data:,">
<style>
html, body {{ margin: 0; font-family: system-ui, -apple-system, "Segoe UI", sans-serif; color: #1e293b;
  background: #f8fafc; }}
main {{ max-width: 34rem; margin: 5rem auto; padding: 2rem 2.5rem; background: #ffffff; border: 1px solid #e2e8f0;
  border-radius: 10px; box-shadow: 0 1px 3px rgba(15, 23, 42, 0.08); line-height: 1.6; font-size: 1.1rem; }}
h1 {{ margin-top: 0; font-size: 1.6rem; text-align: center; }}
</style></head>
<body><main><h1>{title}</h1>{body_html}</main></body></html>
"""


def _bearer(authorization: Optional[str]) -> Optional[str]:
    if not authorization:
        return None
    scheme, _, token = authorization.partition(" ")
    return token.strip() if scheme.lower() == "bearer" and token.strip() else None


def for_participant(sentence: str, settings: Settings, when: str = "If this keeps happening") -> dict:
    """The keys of a refusal a participant may meet: ``message``, a sentence in their words ending with whom to
    contact, and ``contact``."""
    contact = settings.contact or "the researcher"
    return {"message": f"{sentence}. {when}, please contact {contact}.", "contact": settings.contact}


class BodyLimit:
    """Answers 413 (JSON ``reply()``) to a request whose body is larger than ``limit`` bytes, by its
    Content-Length or, without one, once what arrived passes the limit; the body is not read further."""

    def __init__(self, app, limit: int, reply: Callable[[], dict]):
        self.app, self.limit, self.reply = app, int(limit), reply

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        length = dict(scope.get("headers") or []).get(b"content-length")
        if length is not None and length.isdigit() and int(length) > self.limit:
            return await JSONResponse(self.reply(), status_code=413)(scope, receive, send)
        seen = 0
        over = False

        async def counted():
            nonlocal seen, over
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    over = True
                    raise BodyTooLarge()
            return message

        async def unless_over(message):
            if not over:  # the app's answer to a body it could not finish reading is replaced
                await send(message)

        try:
            await self.app(scope, counted, unless_over)
        except BodyTooLarge:
            over = True
        if over:
            await JSONResponse(self.reply(), status_code=413)(scope, receive, send)


class BodyTooLarge(Exception):
    """A request body passed :data:`MAX_BODY` while it was read."""


def _one_line(err: RequestValidationError) -> str:
    first = err.errors()[0]
    where = ".".join(str(part) for part in first.get("loc", ()) if part != "body")
    msg = first.get("msg", "invalid request")
    if first.get("type") == "json_invalid":
        return "the request body is not valid JSON"
    return f"field '{where}': {msg}" if where else msg

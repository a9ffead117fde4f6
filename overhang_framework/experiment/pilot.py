"""A pilot before people: ``python -m overhang_framework.experiment pilot --out DIR [OPTIONS] [OVERRIDES...]``.

A cohort of simulated participants (the ``participants`` command's config: ``cohort=small seed=1``,
``world.*``, ``predictor.*``, ``planner.*``, ``conditions.*``) takes part in the experiment as HTTP
clients of a running server, as the page does: ``POST /api/sessions`` with a participant id, ``POST
/api/consent`` with the version of the consent text the session holds, the practice until passed (or the attempts are used up), then each main trial, every step started with
``POST /api/steps/start`` or handed out by the previous placement's reply, every placement a
``POST /api/placements``, and ``POST /api/finish``. Each decision is the participant's planner on the
tower the server reports (:func:`overhang_framework.behaviour.participants.decide`, the offline
simulation's own step), and the client waits the decision's simulated time, times ``--time-scale``,
before it posts, so the server's clock measures it.

Without ``--url`` the pilot starts the experiment's server itself (the API of
``python -m overhang_framework.experiment``, under uvicorn in a process of its own, on a free loopback
port), with ``run_dir`` ``DIR`` (its database ``DIR/experiment.sqlite``), the cohort's tasks, conditions
and world, and the time limit of the cohort's ``time_limited`` condition times the time scale;
``--serve KEY=VALUE`` adds any key of ``conf/serve.yaml`` (``workers=1``, ``database=URL``,
``practice.max_attempts=2``). With ``--url`` it takes part in that server's study as it is.

The server assigns each session its condition (balanced) and its order of the main tasks; the pilot
gives each session the cohort's next participant of that condition, who does the tasks in the server's
order. The main trials draw from the participant's behaviour generator as the offline simulation does
(the practice from a generator of its own), so the stored placements are those of
``simulate_participant(..., order=the server's order)``: docs/experiment.md, "A pilot before people".

``DIR`` gets ``participants.csv`` (the server's participant id, the cohort's participant and its true
parameters, whether the practice screened it out), ``run.json`` (the generating config, which the fit
reads beside ``participants.csv``), ``decisions.jsonl`` (each decision as the client made it: the grid
action, lapse, predictor calls, the simulated time, what the server answered) and ``pilot.json`` (the
summary). Then ``export``, ``analyze`` and ``fit`` run on what the server stored.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import secrets
import socket
import subprocess
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from overhang_framework.errors import ConfigError, OverhangError

PROG = "python -m overhang_framework.experiment pilot"
#: The files the pilot writes into ``--out``.
CSV, RUN, DECISIONS, SUMMARY, SERVER_LOG = "participants.csv", "run.json", "decisions.jsonl", "pilot.json", "server.log"
#: Seconds the pilot waits for the server it started to answer.
SERVER_START_TIMEOUT = 180.0
#: Seconds an HTTP request may take (a placement runs the physics).
REQUEST_TIMEOUT = 120.0


class PilotError(OverhangError):
    """The pilot could not go on (a refusal of the server, a server that stopped); one line."""


class PilotStopped(Exception):
    """A pilot stopped (Ctrl-C, or a :class:`PilotError`) after it had opened sessions; its files are written."""

    def __init__(self, result: dict, cause: BaseException):
        super().__init__(str(cause))
        self.result, self.cause = result, cause


#: The phases of a participant who has nothing left to do.
FINISHED = ("done", "screened_out")


@dataclass
class Plan:
    """What the pilot runs: the checked participants config, the cohort's participants and tasks."""

    cfg: Any  # the composed participants config (no hydra node)
    checked: Any  # overhang_framework.behaviour.simulation.Checked
    participants: list
    tasks: list


def plan(overrides: Sequence[str]) -> Plan:
    """The participants config of ``overrides``, checked; one :class:`OverhangError` line otherwise."""
    from overhang_framework.behaviour.participants import cohort_tasks, draw_participants
    from overhang_framework.behaviour.simulation import CONFIG_NAME, check_config
    from overhang_framework.preflight import compose_checked

    cfg = compose_checked(list(overrides), config_name=CONFIG_NAME)
    checked = check_config(cfg)
    return Plan(cfg, checked, draw_participants(checked.cohort, checked.seed),
                cohort_tasks(checked.cohort, checked.tasks))


def _plain(node) -> Any:
    from omegaconf import OmegaConf

    return OmegaConf.to_container(node, resolve=True) if node is not None else None


def _override(key: str, value: Any) -> list[str]:
    """``key=value`` words (Hydra's grammar) for a plain value; a mapping gives one word per leaf."""
    if isinstance(value, dict) and value:
        return [w for k, v in value.items() for w in _override(f"{key}.{k}", v)]
    return [f"{key}={json.dumps(value)}"]


def server_overrides(p: Plan, time_scale: float, run_dir: Path, port: int) -> list[str]:
    """The ``conf/serve.yaml`` overrides of the pilot's own server: the cohort's world, tasks, conditions and
    time limits (scaled; a condition other than ``time_limited`` and ``unconstrained`` by ``time_limits``), the
    pilot's seed; :class:`ConfigError` when the server cannot run the cohort."""
    cohort = p.checked.cohort
    specs = [s for s in cohort.conditions if s.n > 0]
    if len({s.n for s in specs}) > 1:
        counts = ", ".join(f"{s.name}: {s.n}" for s in specs)
        raise ConfigError(f"the server assigns conditions balanced, so a pilot's cohort has as many participants in "
                          f"each condition; cohort {cohort.name!r} has {counts} (set cohort.participants.NAME=N)")
    limited = next((s for s in specs if s.name == "time_limited"), None)
    words = _override("world", _plain(p.cfg.world))
    words += ["tasks=custom", "tasks.sequences=" + json.dumps([list(t.sequence) for t in p.tasks]),
              "tasks.ids=" + json.dumps([t.id for t in p.tasks]),
              "conditions=[" + ",".join(s.name for s in specs) + "]",
              f"seed={p.checked.seed}", f"run_dir={run_dir}", f"port={port}", "host=127.0.0.1",
              "source=simulated"]  # the study's records say who took part
    if limited is not None and limited.time_limit is not None:
        words.append(f"time_limit={limited.time_limit * time_scale!r}")
    for spec in specs:  # any other condition (a graded-budget study's levels) with its own limit
        if spec.name not in ("time_limited", "unconstrained"):
            limit = "null" if spec.time_limit is None else repr(spec.time_limit * time_scale)
            words.append(f"+time_limits.{spec.name}={limit}")
    return words


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    """The experiment's API in a uvicorn process of its own (the app the ``serve`` command's workers run)."""

    def __init__(self, overrides: Sequence[str], port: int, log_path: Path, workers: int):
        from overhang_framework.experiment.settings import ADMIN_ENV, SETTINGS_ENV

        self.url = f"http://127.0.0.1:{port}"
        self.admin_token = secrets.token_urlsafe(18)
        env = {**os.environ, SETTINGS_ENV: json.dumps(list(overrides)), ADMIN_ENV: self.admin_token}
        self.log = open(log_path, "ab")
        self.process = subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "overhang_framework.experiment.__main__:app_factory", "--factory",
             "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning", "--workers", str(workers)],
            env=env, stdout=self.log, stderr=subprocess.STDOUT)
        self.log_path = log_path

    def wait_ready(self, timeout: float = SERVER_START_TIMEOUT) -> None:
        import httpx

        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                tail = self.log_path.read_text(errors="replace").strip().splitlines()[-1:] or ["(no output)"]
                raise PilotError(f"the pilot's server stopped with exit code {self.process.returncode}: {tail[0]} "
                                 f"(its log: {self.log_path})")
            try:
                httpx.get(self.url + "/api/session", timeout=2.0)
                return
            except httpx.HTTPError:
                time.sleep(0.2)
        self.stop()
        raise PilotError(f"the pilot's server did not answer within {timeout:g} s (its log: {self.log_path})")

    def stop(self) -> None:
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        self.log.close()


@dataclass
class Taker:
    """One session of the study and the cohort's participant who takes part in it."""

    pid: str
    session: dict
    participant: Any = None
    phase: str = "practice"
    placements: int = 0
    timeouts: int = 0
    practice_attempts: int = 0
    decisions: list = field(default_factory=list)
    error: Optional[str] = None


class Client:
    """One participant's HTTP client: the requests the page makes, each refusal a :class:`PilotError`."""

    def __init__(self, url: str, pid: str):
        import httpx

        self.http = httpx.Client(base_url=url.rstrip("/"), timeout=REQUEST_TIMEOUT)
        self.pid, self.token = pid, None

    def post(self, path: str, body: dict, extra: Optional[dict] = None) -> dict:
        import httpx

        headers = {"Authorization": f"Bearer {self.token}"} if self.token else {}
        headers.update(extra or {})
        try:
            reply = self.http.post(path, json=body, headers=headers)
        except httpx.HTTPError as err:
            raise PilotError(f"participant {self.pid}: {path} failed: {err}") from None
        try:
            data = reply.json()
        except ValueError:
            data = {"error": reply.text[:200]}
        if reply.status_code >= 400:
            raise PilotError(f"participant {self.pid}: the server refused {path} ({reply.status_code}): "
                             f"{data.get('error', data)}")
        return data

    def close(self) -> None:
        self.http.close()


def state_of(world, task, tower: Sequence[Sequence[float]]):
    """The decision state of ``task`` with the tower the server reports (its ground block first)."""
    from overhang_framework.geometry import Action

    state = world.initial_state(task)
    for _, x, layer in tower[1:]:
        state = world.successor(state, Action(float(x), int(layer)))
    return state


class Pilot:
    """The cohort of ``p`` as clients of the server at ``url``."""

    def __init__(self, p: Plan, url: str, time_scale: float = 1.0, timeouts: str = "page", prefix: str = "pilot",
                 stop: Optional[threading.Event] = None, admin_token: Optional[str] = None):
        self.p, self.url, self.time_scale, self.timeouts, self.prefix = p, url, time_scale, timeouts, prefix
        self.admin_token = admin_token  # marks the pilot's sessions simulated on the server
        self.stop = stop or threading.Event()
        self.lock = threading.Lock()
        #: Every session opened so far, whatever became of it (what a stopped pilot leaves on the server).
        self.takers: list[Taker] = []
        #: The participant id of every session the server made, in order (some may have no taker yet).
        self.opened: list[str] = []

    # -- sessions --------------------------------------------------------------------------------------------

    def check_study(self) -> None:
        """Refuse, before any session is opened, a cohort whose conditions are not the study's: the server assigns
        every newcomer one of its conditions in turn, so each must have participants in the cohort, and each of
        the cohort's must be one of the server's."""
        import httpx

        try:
            reply = httpx.get(self.url.rstrip("/") + "/api/admin/study", headers={"X-Admin-Token": self.admin_token or ""},
                              timeout=REQUEST_TIMEOUT)
        except httpx.HTTPError as err:
            raise PilotError(f"the server at {self.url} did not answer: {err}") from None
        if reply.status_code != 200:
            raise PilotError(f"the server refused to say its study ({reply.status_code}): "
                             f"{reply.json().get('error') if 'json' in reply.headers.get('content-type', '') else reply.text[:200]}")
        served = list((((reply.json().get("study") or {}).get("settings")) or {}).get("conditions") or [])
        ours = [s.name for s in self.p.checked.cohort.conditions if s.n]
        if served and (set(served) - set(ours) or set(ours) - set(served)):
            raise PilotError(f"the study serves the conditions {', '.join(served)}, and the cohort has participants "
                             f"in {', '.join(ours) or 'none'}: give the cohort participants in each of the study's "
                             f"conditions and no other (cohort.participants.<condition>=N); no session was opened")

    def open_sessions(self) -> list[Taker]:
        """A session for each participant of the cohort, one after another, each given the cohort's next
        participant of the condition the server assigned."""
        self.check_study()
        cohort = self.p.checked.cohort
        free = {s.name: [q for q in self.p.participants if q.condition == s.name] for s in cohort.conditions}
        takers = self.takers
        for k in range(1, len(self.p.participants) + 1):
            pid = f"{self.prefix}-{k:03d}"
            client = Client(self.url, pid)
            try:
                try:
                    session = client.post("/api/sessions", {"params": {"participant": pid}, "simulated": True},
                                          {"X-Admin-Token": self.admin_token or ""})
                except PilotError as err:
                    if "already has a session" in str(err) or "has finished the study" in str(err):
                        raise PilotError(f"{pid} is in this study already (an earlier pilot's participant): give this "
                                         f"pilot ids of its own with --prefix (e.g. --prefix {self.prefix}2)") from None
                    raise
                self.opened.append(pid)
                client.token = session["token"]
                if not session["consent"]["given"]:  # "I agree" on the consent page the server sent
                    client.post("/api/consent", {"version": session["consent"]["version"]})
            finally:
                client.close()
            condition = session["condition"]
            if not free.get(condition):
                have = ", ".join(f"{s.name}: {s.n}" for s in cohort.conditions)
                raise PilotError(f"the server assigned {pid} to {condition}, but the cohort's participants of "
                                 f"{condition} are all taken ({have}); the server balances the conditions over "
                                 "everyone it has: pilot a fresh study")
            takers.append(Taker(pid, session, free[condition].pop(0)))
        return takers

    # -- one participant ---------------------------------------------------------------------------------------

    def take_part(self, taker: Taker, on_event: Callable[[str, Taker], None] = lambda *_: None) -> Taker:
        """``taker``'s participant does the practice and the main trials through the API."""
        from overhang_framework.behaviour.participants import (Agents, decide, participant_rngs, practice_rng)
        from overhang_framework.interfaces import Task
        from overhang_framework.plugins import Registry

        checked, participant, seed = self.p.checked, taker.participant, self.p.checked.seed
        cohort = checked.cohort
        spec = next(s for s in cohort.conditions if s.name == participant.condition)
        registry = Registry()
        world = registry.create("world", _plain(self.p.cfg.world))
        value = registry.create("value", _plain(self.p.cfg.value), world=world)
        agents = Agents(registry, world, _plain(self.p.cfg.predictor), _plain(self.p.cfg.planner), cohort)
        predictor, planner = agents.build(participant)
        main_rng = participant_rngs(seed, participant.index)[1]
        main_rng.permutation(len(self.p.tasks))  # its own order, drawn as offline; the server's is the one played
        rngs = {"main": main_rng, "practice": practice_rng(seed, participant.index)}
        client = Client(self.url, taker.pid)
        client.token = taker.session["token"]
        session = taker.session
        position, clock, received = session["position"], session.get("clock"), time.monotonic()
        tasks: dict[tuple, Task] = {}
        try:
            while position["phase"] in ("practice", "main") and not self.stop.is_set():
                key = {k: position[k] for k in ("phase", "trial", "attempt", "step")}
                if clock is None or any(clock.get(k) != v for k, v in key.items()) or \
                        (key["phase"], key["trial"], key["attempt"]) not in tasks:
                    reply = client.post("/api/steps/start", key)
                    received = time.monotonic()
                    clock = reply["clock"]
                    tasks[(key["phase"], key["trial"], key["attempt"])] = Task(
                        reply["task"]["task_id"], tuple(float(w) for w in reply["task"]["sequence"]))
                task = tasks[(key["phase"], key["trial"], key["attempt"])]
                state = state_of(world, task, position["tower"])
                time_left = clock.get("time_left")
                limit = None if (self.timeouts != "page" or time_left is None) else time_left / self.time_scale
                planning = time.monotonic()
                choice = decide(participant, spec, cohort, state, world, predictor, planner, value,
                                rngs[key["phase"]], limit)
                # the simulator's planning is this machine's cost, not the participant's: it is said to the server
                # (simulator_time), which takes it off its clock, and the participant's time is waited after it
                planning = time.monotonic() - planning
                wait = (time_left if choice.timed_out else choice.seconds * self.time_scale)
                pause = received + planning + wait - time.monotonic()
                if pause > 0:
                    self.stop.wait(pause)
                body = {**key, "x": choice.x, "layer": None if choice.timed_out else choice.action.layer,
                        "timed_out": choice.timed_out,
                        "decision_time": round(max(0.0, time.monotonic() - received - planning), 3),
                        "simulator_time": round(planning, 3), "trajectory": [], "dwell": []}
                reply = client.post("/api/placements", body)
                received = time.monotonic()
                taker.placements += 1
                taker.timeouts += bool(reply["timed_out"])
                taker.decisions.append({
                    "participant": taker.pid, "cohort_participant": participant.id, **key, "task_id": task.id,
                    "grid_x": choice.action.x, "layer": choice.action.layer, "x": choice.x, "lapse": choice.lapsed,
                    "predictor_calls": choice.predictor_calls, "depth_completed": choice.depth_completed,
                    "simulated_time": choice.seconds, "waited": round(wait, 3), "claimed_timeout": choice.timed_out,
                    "planning_seconds": round(planning, 3),
                    "timed_out": reply["timed_out"], "late": reply.get("late"), "server_time": reply["server_time"],
                    "stable": reply["stable"], "reward": reply["reward"], "passed": reply.get("passed")})
                if key["phase"] == "practice" and reply["trial_over"]:
                    taker.practice_attempts += 1
                position, clock = reply["position"], reply.get("clock")
                if key["phase"] == "main" and reply["trial_over"]:
                    on_event("trial", taker)
            taker.phase = position["phase"]
            if taker.phase == "done":
                client.post("/api/finish", {})
            on_event(taker.phase, taker)
        finally:
            client.close()
        return taker

    def run(self, concurrency: int, progress: bool = True) -> list[Taker]:
        """Every participant of the cohort, ``concurrency`` at a time; the first failure stops the others."""
        from overhang_framework.progress import progress_bar

        takers = self.open_sessions()
        # the server's count of main trials (a server of another study may give more than the cohort's tasks)
        bar = progress_bar(total=sum(len(t.session.get("trials") or self.p.tasks) for t in takers),
                           desc="main trials", unit="trial",
                           disable=not progress, miniters=1, mininterval=0.5, dynamic_ncols=True)
        counts: Counter = Counter()

        def on_event(what: str, taker: Taker) -> None:
            with self.lock:
                if what == "trial":
                    bar.update(1)
                else:
                    counts[what] += 1
                bar.set_postfix_str(f"{counts['done']} done, {counts['screened_out']} screened out, "
                                    f"{len(takers)} participants")

        def one(taker: Taker) -> Taker:
            try:
                return self.take_part(taker, on_event)
            except Exception as err:  # noqa: BLE001 - every participant's failure stops the pilot with its line
                taker.error = str(err) if isinstance(err, OverhangError) else f"participant {taker.pid}: {err!r}"
                self.stop.set()
                return taker

        pool = ThreadPoolExecutor(max_workers=max(1, min(concurrency, len(takers))))
        try:
            done = list(pool.map(one, takers))
        except KeyboardInterrupt:
            self.stop.set()  # each participant stops at its next step; then the pool is shut down
            raise
        finally:
            pool.shutdown(wait=True)
            bar.close()
        failed = [t for t in done if t.error]
        if failed:
            raise PilotError(failed[0].error)
        return done


def offline_twin(overrides: Sequence[str], records: Sequence[dict], table: dict) -> list[dict]:
    """The offline simulation's records of a pilot's participants, each doing the tasks in the server's order
    (read from the exported ``records``), under the server's participant ids; ``table`` is the pilot's
    ``participants.csv`` as ``{id: row}``. The export of a pilot equals these, the times apart (and rewards and
    overhangs, which the server rounds to 1e-9)."""
    from overhang_framework.behaviour.participants import simulate_participant

    p = plan(overrides)
    index = {t.id: k for k, t in enumerate(p.tasks)}
    by_index = {q.index: q for q in p.participants}
    out = []
    for pid, row in table.items():
        firsts = sorted((r["trial"], index[r["task_id"]]) for r in records
                        if r["participant"] == pid and r["step"] == 1)
        q = by_index[int(row["index"])]
        if q.id != row["cohort_id"] or q.condition != row["condition"]:
            raise ConfigError(f"participants.csv names {row['cohort_id']} ({row['condition']}) as cohort participant "
                              f"{row['index']}, but these overrides make it {q.id} ({q.condition})")
        sim = simulate_participant(q, p.checked.cohort, p.tasks, p.checked.models, p.checked.agents, p.checked.seed,
                                   order=[k for _, k in firsts])
        out += [{**r, "participant": pid} for r in sim]
    return out


#: What the server stores of a placement that the offline simulation also logs, alike (the times and rounding apart).
SAME = ("participant", "condition", "task_id", "sequence", "trial", "step", "width", "x", "layer", "tower_before",
        "stable", "timed_out")


def placements_alike(exported: Sequence[dict], offline: Sequence[dict]) -> tuple[int, int]:
    """How many of the ``exported`` placements equal their ``offline`` twin in :data:`SAME`, with the reward
    within 2e-9; and how many there are."""
    key = lambda r: (r["participant"], r["trial"], r["step"])  # noqa: E731
    twins = {key(r): r for r in offline}
    alike = 0
    for r in exported:
        o = twins.get(key(r))
        if o is not None and all(r[k] == o[k] for k in SAME) and (
                (r["reward"] is None and o["reward"] is None) or
                (r["reward"] is not None and o["reward"] is not None and abs(r["reward"] - o["reward"]) <= 2e-9)):
            alike += 1
    return alike, len(exported)


# -- outputs --------------------------------------------------------------------------------------------------

def participants_table(takers: Sequence[Taker]) -> str:
    """``participants.csv``: the server's participant id, the cohort's participant, its true parameters, and
    whether the practice screened it out (the columns the fit reads as the truth)."""
    import csv
    import io

    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    with_switch = any(t.participant.switch is not None for t in takers)
    fields = ["id", "cohort_id", "index", "condition", "sigma", "depth", "beta", "lapse"] + \
        (["switch"] if with_switch else []) + ["screened_out", "practice_attempts"]
    writer.writerow(fields)
    for t in takers:
        q = t.participant
        row = {"id": t.pid, "cohort_id": q.id, "index": q.index, "condition": q.condition, "sigma": q.sigma,
               "depth": q.depth, "beta": q.beta, "lapse": q.lapse, "switch": q.switch,
               "screened_out": t.phase == "screened_out", "practice_attempts": t.practice_attempts}
        writer.writerow(["" if row[f] is None else (repr(float(row[f])) if isinstance(row[f], float) else row[f])
                         for f in fields])
    return out.getvalue()


def summary(takers: Sequence[Taker], seconds: float, url: str, time_scale: float, timeouts: str) -> dict:
    by_condition = {}
    for t in takers:
        c = by_condition.setdefault(t.participant.condition, Counter())
        c["participants"] += 1
        c["finished"] += t.phase == "done"
        c["screened_out"] += t.phase == "screened_out"
        c["placements"] += t.placements
        c["timeouts"] += t.timeouts
        c["practice_attempts"] += t.practice_attempts
    return {"server": url, "time_scale": time_scale, "timeouts": timeouts, "seconds": round(seconds, 1),
            "participants": len(takers), "finished": sum(t.phase == "done" for t in takers),
            "screened_out": sum(t.phase == "screened_out" for t in takers),
            "conditions": {k: dict(v) for k, v in by_condition.items()}}


def format_summary(s: dict) -> str:
    lines = [f"{'condition':<16}{'people':>8}{'finished':>10}{'screened':>10}{'practice':>10}{'placed':>8}"
             f"{'timeouts':>10}"]
    for name, c in s["conditions"].items():
        lines.append(f"{name:<16}{c['participants']:>8}{c['finished']:>10}{c['screened_out']:>10}"
                     f"{c['practice_attempts']:>10}{c['placements']:>8}{c['timeouts']:>10}")
    lines.append("(practice: attempts at the practice towers; placed: placements of the practice and the main trials, "
                 "where export counts the main trials')")
    return "\n".join(lines)


# -- the command ----------------------------------------------------------------------------------------------

def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog="""examples:
  python -m overhang_framework.experiment pilot --out runs/pilot cohort=small seed=1
  python -m overhang_framework.experiment pilot --out runs/pilot --url http://127.0.0.1:8000 cohort=small
  python -m overhang_framework.experiment pilot --out runs/quick --time-scale 0.05 --serve workers=1 \\
      cohort=small
then:
  python -m overhang_framework.experiment export run_dir=runs/pilot --out runs/pilot/log.jsonl
  python -m overhang_framework.analyze runs/pilot/log.jsonl --out runs/pilot/analysis
  python -m overhang_framework.fit runs/pilot/log.jsonl --out runs/pilot/fit""")
    ap.add_argument("overrides", nargs="*", help="keys of the participants command's config (cohort=small seed=1)")
    ap.add_argument("--out", required=True, metavar="DIR",
                    help="the pilot's files; without --url also the server's run_dir (its database)")
    ap.add_argument("--url", help="a running experiment server to take part in (default: start one)")
    ap.add_argument("--time-scale", type=float, default=1.0, metavar="S",
                    help="wait S x each simulated decision time, and (own server) S x the time limit; only 1 is "
                         "a faithful pilot (default 1)")
    ap.add_argument("--timeouts", choices=("page", "server"), default="page",
                    help="page: a decision slower than the time left is posted as timed_out when it runs out, as "
                         "the page does; server: the placement is posted when the decision is made, and the "
                         "server's clock decides (default page)")
    ap.add_argument("--concurrency", type=int, default=8, metavar="N",
                    help="participants taking part at once (default 8)")
    ap.add_argument("--serve", action="append", default=[], metavar="KEY=VALUE",
                    help="a key of conf/serve.yaml for the pilot's own server (repeatable)")
    ap.add_argument("--prefix", default="pilot", help="participant ids are PREFIX-001, ... (default pilot)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    return ap


def check(args, port: int = 0) -> tuple[Plan, Optional[list[str]], Any]:
    """The pilot of ``args`` (parsed by :func:`parser`) checked before anything is written or requested: its plan,
    and without ``--url`` the overrides of its own server (on ``port``) and their settings, checked as the server
    checks them."""
    from overhang_framework.experiment.api import PARTICIPANT_ID
    from overhang_framework.preflight import check_writable

    if not (args.time_scale > 0 and math.isfinite(args.time_scale)):
        raise ConfigError(f"--time-scale must be a number > 0, got {args.time_scale!r}")
    if args.concurrency < 1:
        raise ConfigError(f"--concurrency must be a whole number >= 1, got {args.concurrency}")
    if not PARTICIPANT_ID.match(f"{args.prefix}-001"):
        raise ConfigError(f"--prefix must be letters, digits or _ . @ : -, got {args.prefix!r}")
    if args.url and args.serve:
        raise ConfigError("--serve sets up the pilot's own server; leave it out with --url")
    if args.url and not str(args.url).startswith(("http://", "https://")):
        raise ConfigError(f"--url must start with http:// or https://, got {args.url!r}")
    from overhang_framework.experiment.settings import ADMIN_ENV

    if args.url and not os.environ.get(ADMIN_ENV):
        raise ConfigError(f"a pilot of a running study needs its admin token in the environment variable {ADMIN_ENV}, "
                          "so that the server stores the pilot's participants as simulated")
    out = Path(args.out)
    check_writable(out, "--out DIR")
    if (out / CSV).exists() or (out / "experiment.sqlite").exists():
        raise ConfigError(f"{out} holds an earlier pilot ({CSV} or experiment.sqlite); give another --out")
    p = plan(args.overrides)
    if args.url:
        return p, None, None
    from overhang_framework.experiment.settings import load_settings

    words = server_overrides(p, args.time_scale, out.resolve(), port) + list(args.serve)
    return p, words, load_settings(words, need_admin_token=False)  # every mistake in one line, before it starts


def run(args) -> dict:
    """The pilot of ``args`` (parsed by :func:`parser`); its summary. Config mistakes raise before any request."""
    from overhang_framework.experiment.settings import ADMIN_ENV
    from overhang_framework.results import atomic_write_json, atomic_write_text
    from overhang_framework.rundir import result_config

    out = Path(args.out)
    p, words, settings = check(args, free_port() if not args.url else 0)
    server = None
    if args.url:
        url = args.url
    else:
        from overhang_framework.experiment.store import Store

        out.mkdir(parents=True, exist_ok=True)
        Store(settings.database).close()  # the tables, made once before the server processes open the database
        server = Server(words, settings.port, out / SERVER_LOG, settings.workers)
        url = server.url
    started = time.monotonic()
    pilot = Pilot(p, url, args.time_scale, args.timeouts, args.prefix,
                  admin_token=server.admin_token if server is not None else os.environ.get(ADMIN_ENV))

    def write(takers: Sequence[Taker], stopped: Optional[str] = None) -> dict:
        result = summary(takers, time.monotonic() - started, url, args.time_scale, args.timeouts)
        if stopped is not None:  # every session the server opened, one without a taker yet included
            finished = {t.pid for t in takers if t.phase in FINISHED}
            result.update(stopped=stopped, opened=len(pilot.opened),
                          unfinished=[pid for pid in pilot.opened if pid not in finished])
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / DECISIONS, "".join(json.dumps(d) + "\n" for t in takers for d in t.decisions))
        atomic_write_json(out / RUN, {"config": result_config(_plain(p.cfg)), "pilot": {
            "server": url, "time_scale": args.time_scale, "timeouts": args.timeouts}})
        atomic_write_json(out / SUMMARY, result)
        atomic_write_text(out / CSV, participants_table(takers))
        return result

    try:
        if server is not None:
            server.wait_ready()
        takers = pilot.run(args.concurrency, progress=not args.no_progress and p.checked.progress)
    except (KeyboardInterrupt, PilotError) as err:
        # what the server holds of the pilot is said, and the pilot's files hold who they were
        if pilot.opened:
            result = write(pilot.takers, "interrupted" if isinstance(err, KeyboardInterrupt) else str(err))
            raise PilotStopped(result, err) from None
        raise
    finally:
        if server is not None:
            server.stop()
    return write(takers)


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        result = run(args)
    except PilotStopped as stopped:
        left = stopped.result["unfinished"]
        where = "its own server's database" if not args.url else args.url
        what = (f"{len(left)} participant(s) unfinished ({', '.join(left[:3])}{', ...' if len(left) > 3 else ''}), "
                "stored as simulated" if left else "no participant unfinished")
        first = "interrupted" if isinstance(stopped.cause, KeyboardInterrupt) else f"error: {stopped.cause}"
        print(f"{first}: {stopped.result['opened']} session(s) were opened; {where} keeps what their participants "
              f"placed, {what}; {Path(args.out) / CSV} and {Path(args.out) / DECISIONS} say who they were",
              file=sys.stderr)
        return 130 if isinstance(stopped.cause, KeyboardInterrupt) else 1
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2 if isinstance(err, ConfigError) or not isinstance(err, PilotError) else 1
    except KeyboardInterrupt:
        print("interrupted before the server opened any session: nothing was stored", file=sys.stderr)
        return 130
    print(format_summary(result))
    where = f"run_dir={args.out}" if not args.url else f"--url {args.url}"
    print(f"{result['participants']} participants ({result['finished']} finished, {result['screened_out']} screened "
          f"out in the practice) in {result['seconds']:.0f} s; the log: python -m overhang_framework.experiment "
          f"export {where} --include-simulated --out {Path(args.out) / 'log.jsonl'}")
    return 0

"""Load test of the experiment server: ``python -m overhang_framework.bench.experiment_load``.

    python -m overhang_framework.bench.experiment_load [--participants 100] [--pace 2.5] [--duration 120]
        [--database URL] [--workers 2] [--physics-processes 1] [--threads 0] [--out figures.json]
        [OVERRIDES...]

Starts the experiment's API (``create_app`` of :mod:`overhang_framework.experiment.api`, no front end)
under uvicorn in a subprocess on a free loopback port, then lets ``--participants`` simulated
participants (asyncio, ``httpx.AsyncClient``) do the task through the real HTTP API at once, each
placing a block every ``--pace`` seconds on average, for ``--duration`` seconds; then it stops by itself.

Each participant starts a session (``POST /api/sessions`` with ``participant=load-<k>``), plays the
practice trials with the optimal towers the session shows (they pass), then the main trials with
legal placements drawn at random with a bias toward the centre of the tower's top (a mix of towers
that stand and towers that fall, like people), moving on when ``trial_over``; a participant who
finishes (``POST /api/finish``) is replaced by a new one. Think times are seeded draws (``--think``:
uniform 0..2*pace, or exponential with mean pace; in the time-limited condition an exponential draw
beyond the limit becomes a timeout sent at the limit). Each request carries a mouse trajectory at the
session's ``mouse_hz``, as the page sends. A fraction ``--retry`` of the placements is sent twice, as
a browser's retry of the identical request: half once the answer came, half while the first is still
being served; the answer must be the same and nothing may be stored twice.

It reports the throughput (placements/s), the latency of a placement (request to full response,
physics included: p50/p95/p99/max), separately for towers that stood and that fell, the server's CPU
(its process and workers, from /proc), the client's, and what the rest of the machine was doing;
then it reads the database with :class:`~overhang_framework.experiment.store.Store` and checks that
every acknowledged placement is stored, and none twice. The server's own timings (each request, each
store call, each physics call, by verdict) are reported beside the client's, to show where time goes.
``--out`` writes the figures as JSON.
Exit status 1 when the integrity check fails (and with ``--require-p95 MS`` when p95 is over it).

OVERRIDES are keys of ``conf/serve.yaml`` for the server (``'tasks.only=[paper00,paper01]'``,
``conditions=[unconstrained]``); ``admin_token`` and ``database`` are set by the benchmark.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

#: The project's target for the p95 latency of a placement, in milliseconds.
TARGET_P95_MS = 500.0
ADMIN_TOKEN = "load-test-admin-token"
SERVER_ENV = "OVERHANG_LOAD_SERVER"
MODULE = "overhang_framework.bench.experiment_load"


# ----------------------------------------------------------------------------------------------------------
# the server, in its own process


def _server_app():
    """The app the benchmark's server serves (a uvicorn factory; its settings come from ``$OVERHANG_LOAD_SERVER``).

    It is the experiment's app with its requests, store calls and outcomes timed (each call's seconds); each
    server process writes its timings to ``timings_dir`` when it stops.
    """
    from overhang_framework.experiment.api import create_app
    from overhang_framework.experiment.settings import load_settings

    spec = json.loads(os.environ[SERVER_ENV])
    settings = load_settings(spec["overrides"])
    settings.web_dir = None
    timings: dict = defaultdict(list)
    store = _timed_store(settings.database, timings)
    outcomes = _timed_outcomes(settings, int(spec.get("physics_processes", 0)), timings)
    outcomes.start()
    app = create_app(settings, store=store, outcomes=outcomes)
    if spec.get("switch_interval"):
        sys.setswitchinterval(float(spec["switch_interval"]))

    async def _started():
        if spec.get("threads"):
            import anyio.to_thread

            anyio.to_thread.current_default_thread_limiter().total_tokens = int(spec["threads"])

    def _stopped():
        if spec.get("timings_dir"):
            from overhang_framework.results import atomic_write_json

            atomic_write_json(Path(spec["timings_dir"]) / f"timings-{os.getpid()}.json",
                              {k: list(v) for k, v in timings.items()})
        outcomes.close()

    app.router.on_startup.append(_started)
    app.router.on_shutdown.append(_stopped)

    @app.middleware("http")
    async def _time_requests(request, call_next):
        t0 = time.perf_counter()
        response = await call_next(request)
        if request.url.path.startswith("/api/"):
            timings[f"request {request.method} {request.url.path}"].append(time.perf_counter() - t0)
        return response

    return app


def _timed(fn, name: str, timings: dict):
    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            timings[name].append(time.perf_counter() - t0)

    return wrapper


def _timed_store(database: str, timings: dict):
    from overhang_framework.experiment.store import Store

    store = Store(database)
    for name in ("by_token", "participant", "find", "placements", "add_placement", "add_newcomer"):
        setattr(store, name, _timed(getattr(store, name), f"store.{name}", timings))
    return store


def _timed_outcomes(settings, processes: int, timings: dict):
    from overhang_framework.experiment.outcome import Outcomes

    class TimedOutcomes(Outcomes):
        """Outcomes that time each call, by the verdict."""

        def __call__(self, geometry):
            t0 = time.perf_counter()
            out = super().__call__(geometry)
            timings["physics " + ("stood" if out.stable else "fell")].append(time.perf_counter() - t0)
            return out

    return TimedOutcomes(settings.world, fps=settings.animation_fps, processes=processes)


def _serve(argv: Sequence[str]) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.experiment_load serve")
    ap.add_argument("--port", type=int, required=True)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--threads", type=int, default=0, help="anyio's thread pool size (0: its default, 40)")
    ap.add_argument("--physics-processes", type=int, default=0)
    ap.add_argument("--keep-alive", type=float, default=75.0)
    ap.add_argument("--switch-interval", type=float, default=0.0)
    ap.add_argument("--timings-dir", help="each server process writes its timings here when it stops")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args(argv)
    import uvicorn

    os.environ[SERVER_ENV] = json.dumps({"overrides": args.overrides, "physics_processes": args.physics_processes,
                                         "threads": args.threads, "switch_interval": args.switch_interval,
                                         "timings_dir": args.timings_dir})
    # keep-alive longer than a think time: else uvicorn may close an idle connection just as the client reuses it
    uvicorn.run(f"{MODULE}:_server_app", factory=True, host="127.0.0.1", port=args.port, workers=args.workers,
                log_level="warning", access_log=False, timeout_keep_alive=args.keep_alive)
    return 0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServerProcess:
    """The experiment server under uvicorn in a subprocess on a free loopback port."""

    def __init__(self, database: str, overrides: Sequence[str] = (), workers: int = 1, threads: int = 0,
                 physics_processes: int = 0, keep_alive: float = 75.0, switch_interval: float = 0.0,
                 log: Optional[Path] = None):
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.timings_dir = tempfile.mkdtemp(prefix="overhang-load-timings-")
        cmd = [sys.executable, "-m", MODULE, "serve", "--port", str(self.port), "--workers", str(workers),
               "--timings-dir", self.timings_dir,
               "--threads", str(threads), "--physics-processes", str(physics_processes),
               "--keep-alive", str(keep_alive), "--switch-interval", str(switch_interval), "--",
               f"admin_token={ADMIN_TOKEN}", f"database={database}", *overrides]
        self._log = open(log, "w") if log else subprocess.DEVNULL
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=self._log if log else subprocess.PIPE,
                                     start_new_session=True)

    def wait_ready(self, timeout: float = 120.0) -> None:
        import httpx

        end = time.monotonic() + timeout
        while time.monotonic() < end:
            if self.proc.poll() is not None:
                err = self.proc.stderr.read().decode(errors="replace") if self.proc.stderr else ""
                raise RuntimeError(f"the server exited with status {self.proc.returncode}: {err.strip()[-2000:]}")
            try:
                if httpx.get(self.url + "/complete", timeout=2.0).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"the server did not answer on {self.url} within {timeout:g} s")

    def timings(self) -> dict:
        """The server's own timings (ms) by what was timed (requests, store calls, physics), once it has stopped."""
        import shutil

        raw: dict = defaultdict(list)
        for path in Path(self.timings_dir).glob("timings-*.json"):
            for k, v in json.loads(path.read_text()).items():
                raw[k] += v
        shutil.rmtree(self.timings_dir, ignore_errors=True)
        return {k: {**_pct(v), "total_s": round(float(np.sum(v)), 2)} for k, v in sorted(raw.items())}

    def pids(self) -> list[int]:
        """The server's process and its descendants (uvicorn workers, physics processes)."""
        return [self.proc.pid, *descendants(self.proc.pid)]

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        if self._log is not subprocess.DEVNULL:
            self._log.close()


# ----------------------------------------------------------------------------------------------------------
# CPU from /proc (no psutil)

_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def _proc_stat(pid: int) -> Optional[tuple[int, str, float]]:
    """(parent pid, command name, user+system CPU seconds) of ``pid``, or None when it is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    name = text[text.index("(") + 1:text.rindex(")")]
    fields = text[text.rindex(")") + 2:].split()
    return int(fields[1]), name, (int(fields[11]) + int(fields[12])) / _TICK


def all_processes() -> dict[int, tuple[int, str, float]]:
    out = {}
    for entry in Path("/proc").iterdir() if Path("/proc").is_dir() else ():
        if entry.name.isdigit():
            st = _proc_stat(int(entry.name))
            if st is not None:
                out[int(entry.name)] = st
    return out


def descendants(pid: int, table: Optional[dict] = None) -> list[int]:
    table = all_processes() if table is None else table
    children: dict[int, list[int]] = defaultdict(list)
    for p, (ppid, _, _) in table.items():
        children[ppid].append(p)
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def machine_busy() -> Optional[tuple[float, float]]:
    """(busy, total) CPU seconds of the whole machine since boot, from /proc/stat."""
    try:
        first = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
    except OSError:
        return None
    v = [int(x) / _TICK for x in first]
    idle = v[3] + (v[4] if len(v) > 4 else 0.0)
    total = sum(v[:8])
    return total - idle, total


class CpuMeter:
    """CPU seconds of the server's processes, this process and everything else between two snapshots."""

    def __init__(self, server: ServerProcess):
        self.server = server
        self.start = self._snapshot()

    def _snapshot(self) -> dict:
        table = all_processes()
        server = {self.server.proc.pid, *descendants(self.server.proc.pid, table)}
        return {"t": time.monotonic(), "table": table, "server": server, "machine": machine_busy(),
                "client": sum(os.times()[:2]), "load": os.getloadavg() if hasattr(os, "getloadavg") else None}

    def server_seconds(self, snap: Optional[dict] = None) -> float:
        snap = snap or self._snapshot()
        now = sum(snap["table"][p][2] for p in snap["server"] if p in snap["table"])
        before = sum(self.start["table"][p][2] for p in snap["server"] if p in self.start["table"])
        return now - before

    def report(self) -> dict:
        end = self._snapshot()
        wall = end["t"] - self.start["t"]
        server = self.server_seconds(end)
        client = end["client"] - self.start["client"]
        ours = end["server"] | {os.getpid()}
        others = []
        for pid, (_, name, cpu) in end["table"].items():
            if pid in ours:
                continue
            before = self.start["table"].get(pid)
            used = cpu - (before[2] if before and before[1] == name else 0.0)
            if used > 0.05 * wall:
                others.append({"pid": pid, "name": name, "cpu_seconds": round(used, 2),
                               "cores": round(used / wall, 3)})
        others.sort(key=lambda o: -o["cpu_seconds"])
        machine = None
        if end["machine"] and self.start["machine"]:
            busy = end["machine"][0] - self.start["machine"][0]
            machine = {"busy_cores": round(busy / wall, 3),
                       "other_cores": round(max(0.0, busy - server - client) / wall, 3)}
        return {"wall_seconds": round(wall, 2), "cores": os.cpu_count(),
                "server_cpu_seconds": round(server, 2), "server_cores": round(server / wall, 3),
                "client_cpu_seconds": round(client, 2), "client_cores": round(client / wall, 3),
                "machine": machine, "other_busy_processes": others[:8],
                "loadavg_before": self.start["load"], "loadavg_after": end["load"]}


# ----------------------------------------------------------------------------------------------------------
# the participants


@dataclass
class LoadConfig:
    participants: int = 100
    pace: float = 2.5
    duration: float = 120.0
    think: str = "uniform"  # uniform 0..2*pace, or exponential with mean pace
    retry: float = 0.05
    seed: int = 0
    centre_bias: float = 0.8  # the sd (task units) of the Gaussian weight around the top's centre
    timeout: float = 60.0  # client timeout of a request, s
    prefix: str = "load"


@dataclass
class Record:
    """What the client saw: latencies, acknowledged keys, retries, errors."""

    latency: dict = field(default_factory=lambda: defaultdict(list))  # kind -> [s]
    acked: dict = field(default_factory=dict)  # (pid, phase, trial, attempt, step) -> (x, layer, timed_out)
    ack_times: list = field(default_factory=list)  # monotonic time of each acknowledgement
    retries: Counter = field(default_factory=Counter)
    errors: Counter = field(default_factory=Counter)
    error_samples: list = field(default_factory=list)
    sessions: int = 0
    finished: int = 0
    trials: Counter = field(default_factory=Counter)

    def error(self, what: str, detail: str) -> None:
        self.errors[what] += 1
        if len(self.error_samples) < 20:
            self.error_samples.append(f"{what}: {detail[:300]}")


def choose_action(tower: list, width: float, rng: np.random.Generator, bias: float) -> tuple[float, int]:
    """A legal placement of ``width`` on ``tower`` drawn at random, weighted toward the top's centre.

    The weight is a Gaussian (sd ``bias``) of the distance to the centre of the top layer's blocks, times 3
    on the layer just above the top (people build upward), so most blocks land near the middle and some
    overhang too far: a mix of towers that stand and fall.
    """
    from overhang_framework.geometry import Action, Geometry
    from overhang_framework.rules import is_legal, legal_xs

    geometry = Geometry.from_tuples(tower)
    xs, layers = legal_xs(geometry, width, 0.1)
    top = max(b.layer for b in geometry.blocks)
    centre = float(np.mean([b.x for b in geometry.blocks if b.layer == top]))
    weight = np.exp(-0.5 * ((xs - centre) / bias) ** 2) * np.where(layers == top + 1, 3.0, 1.0)
    i = int(rng.choice(len(xs), p=weight / weight.sum()))
    x, layer = float(xs[i]), int(layers[i])
    # people place at any x, not on the planners' grid (and a grid would make the verdict cache unrealistically hot)
    moved = round(x + float(rng.uniform(-0.05, 0.05)), 4)
    if is_legal(geometry, width, Action(moved, layer)):
        x = moved
    return x, layer


def trajectory(think: float, hz: float, x: float, layer: int, rng: np.random.Generator) -> tuple[list, list]:
    """A mouse trajectory ``[t, x, y]`` at ``hz`` over a decision of ``think`` s ending at the placement, and dwell."""
    n = max(1, int(think * hz))
    t = np.round(np.arange(n) / hz, 4)
    end = np.array([x, 0.6 * layer + 0.3])
    start = end + rng.normal(0, 1.5, 2)
    path = start + (end - start) * np.linspace(0, 1, n)[:, None] + rng.normal(0, 0.05, (n, 2))
    traj = [[float(a), round(float(b), 4), round(float(c), 4)] for a, (b, c) in zip(t, path)]
    dwell = [[round(x, 4), layer, round(min(think, 0.4), 4)]]
    return traj, dwell


class Participant:
    def __init__(self, client, cfg: LoadConfig, rec: Record, k: int, deadline: float, rng: np.random.Generator,
                 practice_towers: Sequence[list] = ()):
        self.client, self.cfg, self.rec, self.k = client, cfg, rec, k
        self.deadline, self.rng = deadline, rng
        self.practice_towers = list(practice_towers)  # the towers the practice shows: played as shown

    def think_time(self, limit: Optional[float]) -> tuple[float, bool]:
        """(seconds, timed out)."""
        if self.cfg.think == "exponential":
            t = float(self.rng.exponential(self.cfg.pace))
            if limit is not None and t > limit:
                return limit, True
            return t, False
        t = float(self.rng.uniform(0, 2 * self.cfg.pace))
        if limit is not None:
            t = min(t, limit)
        return t, False

    async def post(self, path: str, body: dict, token: Optional[str] = None):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        t0 = time.perf_counter()
        reply = await self.client.post(path, json=body, headers=headers)
        return reply, time.perf_counter() - t0

    async def run(self) -> None:
        generation = 0
        # people do not all arrive in the same instant
        await asyncio.sleep(float(self.rng.uniform(0, self.cfg.pace)))
        while time.monotonic() < self.deadline:
            pid = f"{self.cfg.prefix}-{self.k}" + (f".{generation}" if generation else "")
            generation += 1
            try:
                if await self.session(pid) == "deadline":
                    return
            except Exception as err:  # noqa: BLE001 - a client error is a finding, not a crash
                self.rec.error("client", f"{pid}: {type(err).__name__}: {err}")
                await asyncio.sleep(1.0)

    async def session(self, pid: str) -> str:
        """One participant from start to finish; "finished", "deadline" or "error"."""
        rec = self.rec
        reply, lat = await self.post("/api/sessions", {"params": {"participant": pid}})
        if reply.status_code != 201:
            rec.error(f"session {reply.status_code}", f"{pid}: {reply.text}")
            await asyncio.sleep(1.0)
            return "error"
        rec.latency["session"].append(lat)
        rec.sessions += 1
        s = reply.json()
        token, pos = s["token"], s["position"]
        reply, lat = await self.post("/api/consent", {"version": s["consent"]["version"]}, token)
        if reply.status_code != 200:
            rec.error(f"consent {reply.status_code}", f"{pid}: {reply.text}")
            return "error"
        limit = s["time_limit"]
        clock, sequence = None, None
        while pos["phase"] != "done":
            step = {k: pos[k] for k in ("phase", "trial", "attempt", "step")}
            if clock is None or {k: clock[k] for k in step} != step:  # a trial's first step: the page starts it
                reply, lat = await self.post("/api/steps/start", step, token)
                if reply.status_code != 200:
                    rec.error(f"start {reply.status_code}", f"{pid}: {reply.text}")
                    return "error"
                rec.latency["start"].append(lat)
                sequence = reply.json()["task"]["sequence"]  # a trial's blocks come with its first step
            think, timed_out = self.think_time(limit)
            if time.monotonic() + think >= self.deadline:
                return "deadline"
            await asyncio.sleep(think)
            if pos["phase"] == "practice":
                width, x, layer = self.practice_towers[pos["trial"] - 1][pos["step"]]
                timed_out = False  # practice is played as the shown tower shows
            else:
                width = sequence[pos["step"]]
                x, layer = choose_action(pos["tower"], width, self.rng, self.cfg.centre_bias)
            traj, dwell = trajectory(think, s["mouse_hz"], x, layer, self.rng)
            body = {"phase": pos["phase"], "trial": pos["trial"], "attempt": pos["attempt"], "step": pos["step"],
                    "x": None if timed_out else x, "layer": None if timed_out else layer, "timed_out": timed_out,
                    "decision_time": round(think, 4), "trajectory": [] if timed_out else traj,
                    "dwell": [] if timed_out else dwell}
            key = (pid, body["phase"], body["trial"], body["attempt"], body["step"])
            retry = self.rng.random() < self.cfg.retry
            early = retry and self.rng.random() < 0.5
            task = None
            if early:  # the browser retries while the first request is still being served
                task = asyncio.create_task(self._retry(body, token, float(self.rng.uniform(0.0, 0.05)), key,
                                                       "retry while in flight"))
            reply = None
            for tries in range(3):  # a dropped connection: the browser sends the identical request again
                try:
                    reply, lat = await self.post("/api/placements", body, token)
                    break
                except Exception as err:  # noqa: BLE001
                    rec.error("placement transport error (sent again)", f"{key}: {type(err).__name__}: {err}")
                    rec.retries["retry after transport error"] += 1
            if reply is None or reply.status_code != 200:
                if reply is not None:
                    rec.error(f"placement {reply.status_code}", f"{key}: {reply.text}")
                if task is not None and await task is not None:
                    rec.acked[key] = (body["x"], body["layer"], body["timed_out"])
                # resynchronise with what the server has
                again = await self.client.get("/api/session", headers={"Authorization": f"Bearer {token}"})
                if again.status_code != 200:
                    rec.error(f"session {again.status_code}", again.text)
                    return "error"
                pos, clock = again.json()["position"], None
                continue
            out = reply.json()
            rec.acked[key] = (body["x"], body["layer"], body["timed_out"])
            rec.ack_times.append(time.monotonic())
            kind = "timeout" if timed_out else ("stood" if out["stable"] else "fell")
            rec.latency[kind].append(lat)
            if pos["phase"] == "practice":
                rec.latency["practice"].append(lat)
            if retry:
                again = await task if task is not None else await self._retry(body, token, 0.0, key,
                                                                              "retry after answer")
                if again is not None:
                    same = _without_clock(again) == _without_clock(out)  # a retry's clock is the step's as it is now
                    rec.retries["identical" if same else "different answer"] += 1
                    if not same:
                        rec.error("retry answer differs", str(key))
            if out["trial_over"]:
                rec.trials[pos["phase"]] += 1
            pos, clock = out["position"], out.get("clock")
        reply, lat = await self.post("/api/finish", {}, token)
        if reply.status_code == 200:
            rec.finished += 1
            rec.latency["finish"].append(lat)
            return "finished"
        rec.error(f"finish {reply.status_code}", reply.text)
        return "error"

    async def _retry(self, body: dict, token: str, delay: float, key, kind: str) -> Optional[dict]:
        """Send ``body`` again (after ``delay`` s); the answer, or None when refused."""
        rec = self.rec
        if delay:
            await asyncio.sleep(delay)
        rec.retries[kind] += 1
        try:
            reply, lat = await self.post("/api/placements", body, token)
        except Exception as err:  # noqa: BLE001
            rec.error("retry exception", f"{key}: {type(err).__name__}: {err}")
            return None
        if reply.status_code != 200:
            rec.retries["refused"] += 1
            rec.error(f"{kind} {reply.status_code}", f"{key}: {reply.text}")
            return None
        rec.latency["retry"].append(lat)
        return reply.json()


def _without_clock(reply: dict) -> dict:
    return {k: v for k, v in reply.items() if k != "clock"}


async def _drive(url: str, cfg: LoadConfig, rec: Record, progress=None, cpu: Optional[CpuMeter] = None,
                 practice_towers: Sequence[list] = ()) -> float:
    import httpx

    limits = httpx.Limits(max_connections=2 * cfg.participants + 10, max_keepalive_connections=2 * cfg.participants)
    async with httpx.AsyncClient(base_url=url, timeout=cfg.timeout, limits=limits) as client:
        start = time.monotonic()
        deadline = start + cfg.duration
        seeds = np.random.SeedSequence(cfg.seed).spawn(cfg.participants)
        people = [Participant(client, cfg, rec, k, deadline, np.random.default_rng(seeds[k - 1]), practice_towers)
                  for k in range(1, cfg.participants + 1)]
        tasks = [asyncio.create_task(p.run()) for p in people]
        ticker = asyncio.create_task(_tick(start, deadline, rec, progress, cpu)) if progress is not None else None
        await asyncio.gather(*tasks)
        end = time.monotonic()
        if ticker:
            ticker.cancel()
        return end - start


async def _tick(start: float, deadline: float, rec: Record, bar, cpu: Optional[CpuMeter]) -> None:
    shown = 0
    last_cpu, last_t = (cpu.server_seconds(), time.monotonic()) if cpu else (0.0, time.monotonic())
    while True:
        await asyncio.sleep(1.0)
        now = time.monotonic()
        elapsed = int(min(now, deadline) - start)
        if elapsed > shown:
            bar.update(elapsed - shown)
            shown = elapsed
        recent = [v for k in ("stood", "fell") for v in rec.latency[k][-400:]]
        p95 = f"{1000 * np.percentile(recent, 95):.0f}" if recent else "-"
        server = ""
        if cpu:
            used = cpu.server_seconds()
            server = f", server {100 * (used - last_cpu) / (now - last_t):.0f}% CPU"
            last_cpu, last_t = used, now
        errors = sum(rec.errors.values())
        bar.set_postfix_str(f"{len(rec.ack_times)} placements, {sum(1 for t in rec.ack_times if t > now - 10) / 10:.1f}/s, "
                            f"p95 {p95} ms{server}, {errors} errors")


# ----------------------------------------------------------------------------------------------------------
# the check against the database


def integrity(database: str, rec: Record, prefix: str) -> dict:
    """Every acknowledged placement stored exactly once, as sent."""
    from overhang_framework.experiment.store import Store

    store = Store(database)
    try:
        rows = [r for r in store.placements() if r.participant_id.startswith(prefix + "-")]
    finally:
        store.close()
    counts = Counter((r.participant_id, r.phase, r.trial, r.attempt, r.step) for r in rows)
    by_key = {(r.participant_id, r.phase, r.trial, r.attempt, r.step): r for r in rows}
    acked = set(rec.acked)
    missing = sorted(acked - set(counts))
    twice = sorted(k for k, n in counts.items() if n > 1)
    unacked = sorted(set(counts) - acked)
    differ = sorted(k for k in acked & set(by_key)
                    if (by_key[k].timed_out, by_key[k].x, by_key[k].layer) != (rec.acked[k][2], rec.acked[k][0],
                                                                                   rec.acked[k][1]))
    return {"acknowledged": len(acked), "stored_rows": len(rows), "stored_keys": len(counts),
            "missing": len(missing), "stored_twice": len(twice), "stored_not_acknowledged": len(unacked),
            "stored_differently": len(differ),
            "ok": not missing and not twice and not differ,
            "examples": {"missing": [list(k) for k in missing[:5]], "twice": [list(k) for k in twice[:5]],
                         "differ": [list(k) for k in differ[:5]]}}


# ----------------------------------------------------------------------------------------------------------
# the run


def _pct(values: Sequence[float]) -> dict:
    if not len(values):
        return {"n": 0}
    ms = 1000 * np.asarray(values)
    p50, p95, p99 = np.percentile(ms, [50, 95, 99])
    return {"n": int(len(ms)), "mean": round(float(ms.mean()), 1), "p50": round(float(p50), 1),
            "p95": round(float(p95), 1), "p99": round(float(p99), 1), "max": round(float(ms.max()), 1)}


def _machine_snapshot() -> dict:
    out: dict = {"loadavg": os.getloadavg() if hasattr(os, "getloadavg") else None}
    try:
        top = subprocess.run(["top", "-bn1", "-w", "200"], capture_output=True, text=True, timeout=10).stdout
        out["top"] = [line for line in top.splitlines()[:14] if line.strip()]
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def run_load(cfg: LoadConfig, database: Optional[str] = None, overrides: Sequence[str] = (), workers: int = 1,
             threads: int = 0, physics_processes: int = 0, keep_alive: float = 75.0, switch_interval: float = 0.0,
             quiet: bool = False,
             server_log: Optional[Path] = None) -> dict:
    """Run the load test and return its figures (see the module docstring)."""
    from overhang_framework.progress import progress_bar

    tmp = None
    if database is None:
        tmp = tempfile.TemporaryDirectory(prefix="overhang-load-")
        database = f"sqlite:///{Path(tmp.name) / 'experiment.sqlite'}"
    else:
        cfg.prefix = f"{cfg.prefix}{int(time.time())}"  # a database that may hold an earlier run's participants
    from overhang_framework.experiment.settings import load_settings

    practice_towers = [pt.shown_tower for pt in load_settings(list(overrides), need_admin_token=False).practice]
    before = _machine_snapshot()
    server = ServerProcess(database, overrides, workers=workers, threads=threads,
                           physics_processes=physics_processes, keep_alive=keep_alive,
                           switch_interval=switch_interval, log=server_log)
    try:
        server.wait_ready()
        rec = Record()
        cpu = CpuMeter(server)
        bar = progress_bar(total=int(cfg.duration), desc="load test", unit="s", disable=quiet, file=sys.stderr)
        try:
            wall = asyncio.run(_drive(server.url, cfg, rec, bar, cpu, practice_towers))
        finally:
            bar.close()
        usage = cpu.report()
    finally:
        server.stop()
    server_ms = server.timings()
    after = _machine_snapshot()
    check = integrity(database, rec, cfg.prefix)
    if tmp is not None:
        tmp.cleanup()
    placed = [v for k in ("stood", "fell", "timeout") for v in rec.latency[k]]
    physics = rec.latency["stood"] + rec.latency["fell"]
    lat = {"placement": _pct(physics), "stood": _pct(rec.latency["stood"]), "fell": _pct(rec.latency["fell"]),
           "timeout": _pct(rec.latency["timeout"]), "practice": _pct(rec.latency["practice"]),
           "retry": _pct(rec.latency["retry"]), "session": _pct(rec.latency["session"]),
           "start": _pct(rec.latency["start"]),
           "finish": _pct(rec.latency["finish"])}
    p95 = lat["placement"].get("p95")
    retries = dict(rec.retries)
    return {
        "config": {**asdict(cfg), "database": database.split("://")[0], "workers": workers, "threads": threads,
                   "physics_processes": physics_processes, "keep_alive": keep_alive, "switch_interval": switch_interval,
                   "overrides": list(overrides)},
        "machine": {"platform": platform.platform(), "python": platform.python_version(), "cores": os.cpu_count(),
                    "before": before, "after": after},
        "wall_seconds": round(wall, 2),
        "placements": len(placed), "placements_per_second": round(len(placed) / wall, 2),
        "stood": len(rec.latency["stood"]), "fell": len(rec.latency["fell"]), "timeouts": len(rec.latency["timeout"]),
        "sessions": rec.sessions, "finished": rec.finished, "trials_over": dict(rec.trials),
        "latency_ms": lat, "server_ms": server_ms, "cpu": usage, "retries": retries, "errors": dict(rec.errors),
        "error_samples": rec.error_samples, "integrity": check,
        "target_p95_ms": TARGET_P95_MS, "target_met": p95 is not None and p95 <= TARGET_P95_MS,
    }


def table(f: dict) -> str:
    c = f["config"]
    lines = [f"experiment load test: {c['participants']} participants, a block every {c['pace']:g} s on average "
             f"({c['think']}), {c['duration']:g} s, {c['database']}, {c['workers']} uvicorn worker(s), "
             f"threads {c['threads'] or 'default'}, physics processes {c['physics_processes']}",
             f"placements acknowledged  {f['placements']}  ({f['placements_per_second']:.2f}/s; "
             f"{f['stood']} stood, {f['fell']} fell, {f['timeouts']} timeouts); sessions {f['sessions']}, "
             f"finished {f['finished']}",
             "", f"{'latency (ms)':<28}{'n':>7}{'p50':>9}{'p95':>9}{'p99':>9}{'max':>9}"]
    names = {"placement": "placement (physics incl.)", "stood": "  tower stood", "fell": "  tower fell",
             "timeout": "timeout (no physics)", "practice": "practice placements", "retry": "retries",
             "session": "session start", "start": "trial start (clock)", "finish": "finish"}
    for key, label in names.items():
        s = f["latency_ms"][key]
        if s["n"]:
            lines.append(f"{label:<28}{s['n']:>7}{s['p50']:>9.1f}{s['p95']:>9.1f}{s['p99']:>9.1f}{s['max']:>9.1f}")
    if f.get("server_ms"):
        lines += ["", f"{'inside the server (ms)':<28}{'n':>7}{'p50':>9}{'p95':>9}{'p99':>9}{'max':>9}{'total s':>9}"]
        for key, s in f["server_ms"].items():
            if s["n"]:
                lines.append(f"{key[:28]:<28}{s['n']:>7}{s['p50']:>9.1f}{s['p95']:>9.1f}{s['p99']:>9.1f}{s['max']:>9.1f}"
                             f"{s['total_s']:>9.1f}")
    u = f["cpu"]
    lines += ["", f"server CPU   {u['server_cores']:.2f} cores ({100 * u['server_cores'] / (u['cores'] or 1):.0f}% of "
                  f"{u['cores']}) over {u['wall_seconds']:.0f} s",
              f"client CPU   {u['client_cores']:.2f} cores (this load generator, same machine)"]
    if u["machine"]:
        lines.append(f"machine      {u['machine']['busy_cores']:.2f} cores busy, {u['machine']['other_cores']:.2f} "
                     f"of them neither server nor client")
    if u["other_busy_processes"]:
        lines.append("  other busy: " + ", ".join(f"{o['name']} ({o['pid']}) {o['cores']:.2f}"
                                                  for o in u["other_busy_processes"][:4]))
    la, lb = f["machine"]["before"]["loadavg"], f["machine"]["after"]["loadavg"]
    if la and lb:
        lines.append(f"load average before {la[0]:.2f} {la[1]:.2f} {la[2]:.2f}; after {lb[0]:.2f} {lb[1]:.2f} {lb[2]:.2f}")
    r = f["retries"]
    i = f["integrity"]
    lines += ["", f"retries      {sum(v for k, v in r.items() if k.startswith('retry'))} sent "
                  f"({r.get('retry after answer', 0)} after the answer, {r.get('retry while in flight', 0)} while in "
                  f"flight): {r.get('identical', 0)} identical answers, {r.get('different answer', 0)} different, "
                  f"{r.get('refused', 0)} refused",
              f"errors       {sum(f['errors'].values())}" + (f" {f['errors']}" if f["errors"] else ""),
              f"integrity    {'OK' if i['ok'] else 'FAILED'}: {i['acknowledged']} acknowledged, {i['stored_keys']} "
              f"stored ({i['stored_rows']} rows); missing {i['missing']}, stored twice {i['stored_twice']}, stored "
              f"differently {i['stored_differently']}, stored but never acknowledged {i['stored_not_acknowledged']}"]
    p95 = f["latency_ms"]["placement"].get("p95")
    lines.append(f"target       p95 <= {f['target_p95_ms']:g} ms: "
                 + ("no placements" if p95 is None else f"{'met' if f['target_met'] else 'NOT met'} ({p95:.0f} ms)"))
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["serve"]:
        return _serve(argv[1:])
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.experiment_load",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--participants", type=int, default=100, help="simulated participants at once (default 100)")
    ap.add_argument("--pace", type=float, default=2.5, help="mean seconds between two placements (default 2.5)")
    ap.add_argument("--duration", type=float, default=120.0, help="seconds of load (default 120)")
    ap.add_argument("--think", choices=("uniform", "exponential"), default="uniform",
                    help="think-time distribution: uniform 0..2*pace (default) or exponential with mean pace")
    ap.add_argument("--retry", type=float, default=0.05, help="fraction of placements sent twice (default 0.05)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--database", help="SQLAlchemy URL (default: a fresh SQLite file, removed afterwards)")
    ap.add_argument("--workers", type=int, default=2, help="uvicorn worker processes (default 2, as the server)")
    ap.add_argument("--threads", type=int, default=0, help="the server's thread pool size (default: anyio's 40)")
    ap.add_argument("--physics-processes", type=int, default=1, metavar="N",
                    help="compute the physics in pools of N processes for the verdicts and N for the motions "
                         "(Outcomes(processes=N)); default 1, as the server; 0: in the request threads")
    ap.add_argument("--keep-alive", type=float, default=75.0,
                    help="the server's HTTP keep-alive timeout, s (default 75; uvicorn's own default, 5, is shorter "
                         "than a think time, and a connection closed as it is reused drops the request)")
    ap.add_argument("--switch-interval", type=float, default=0.0, metavar="S",
                    help="the server's sys.setswitchinterval (default: Python's 0.005)")
    ap.add_argument("--server-log", help="write the server's output here")
    ap.add_argument("--require-p95", type=float, metavar="MS", help="exit 1 when the placement p95 is over MS")
    ap.add_argument("--out", help="also write the figures as JSON to this file")
    ap.add_argument("--quiet", action="store_true", help="no progress line")
    ap.add_argument("overrides", nargs="*", help="keys of conf/serve.yaml for the server")
    args = ap.parse_args(argv)
    if args.participants < 1 or args.pace <= 0 or args.duration <= 0 or not 0 <= args.retry <= 1:
        ap.error("--participants >= 1, --pace > 0, --duration > 0 and --retry in [0, 1]")
    cfg = LoadConfig(participants=args.participants, pace=args.pace, duration=args.duration, think=args.think,
                     retry=args.retry, seed=args.seed)
    figures = run_load(cfg, args.database, args.overrides, workers=args.workers, threads=args.threads,
                       physics_processes=args.physics_processes, keep_alive=args.keep_alive,
                       switch_interval=args.switch_interval, quiet=args.quiet,
                       server_log=Path(args.server_log) if args.server_log else None)
    print(table(figures))
    if args.out:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.out, figures)
    if not figures["integrity"]["ok"]:
        return 1
    if args.require_p95 is not None and not (figures["latency_ms"]["placement"].get("p95", float("inf"))
                                             <= args.require_p95):
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

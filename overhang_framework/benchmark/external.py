"""An agent in any language: a program that speaks JSON Lines over its stdin and stdout.

The benchmark starts the program once (and again after it crashed or hung), writes one JSON object
per line to its stdin and reads one line back per decision. The protocol, with an example agent in
Python and one in JavaScript, is docs/benchmark-protocol.md:

* ``{"type": "decision", ...}``: the task id, the whole sequence, the step, the tower, the legal
  placements (and the path of a PNG of the scene, with ``agent.render=true``). The program answers
  with one line, ``{"x": ..., "layer": ...}``, one of the legal placements.
* ``{"type": "end", ...}``: the episode's reward and reason. Nothing is answered.

A crash, no answer within ``timeout`` seconds, a line that is not such an object, or a placement
that is not legal ends the episode with reward 0 and the reason; the next episode goes on (with a
new process when the old one died or hung). What the program writes to stderr goes to ``agent.log``
(up to :data:`LOG_CAP` bytes a run; the rest is counted and dropped).

A program may exit between episodes: whether it is found dead before the next episode's first
decision or dies while that decision is being sent, a new process gets that decision, so the outcome
never depends on timing. A program that stops during an episode (after its first decision) has
crashed, however fast it stopped.
"""

from __future__ import annotations

import json
import os
import queue
import subprocess
import threading
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.benchmark.agents import Agent, AgentFailed, Choice, on_grid
from overhang_framework.errors import OverhangError
from overhang_framework.geometry import Action
from overhang_framework.interfaces import State, Task, World

PROTOCOL = "overhang-tower-jsonl/1"
#: The most ``agent.log`` keeps of what the program writes to stderr, in bytes.
LOG_CAP = 10 * 2 ** 20
#: How long :func:`check_starts` waits for a program that exits at once.
START_WAIT = 1.0


class CommandAgent(Agent):
    """The external program ``command`` (a list of words, as for :class:`subprocess.Popen`)."""

    counts_calls = False

    def __init__(self, world: World, command: Sequence[str], timeout: float = 30.0, render: bool = False,
                 workdir: Optional[Path] = None, cwd: Optional[str] = None):
        if isinstance(command, str) or not command or not all(isinstance(w, str) for w in command):
            raise ValueError(f"agent.command must be a list of words, e.g. [node, examples/agents/centre.js], "
                             f"got {command!r}")
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or timeout <= 0:
            raise ValueError(f"agent.timeout must be a number of seconds > 0, got {timeout!r}")
        self.world = world
        self.command = list(command)
        self.timeout = float(timeout)
        self.render = bool(render)
        self.workdir = Path(workdir or ".")
        self.cwd = cwd
        self.proc: Optional[subprocess.Popen] = None
        self.lines: "queue.Queue[Optional[str]]" = queue.Queue()
        self.restarts = 0
        self._answered = False  # whether the program has answered any decision of the run
        self._fresh = False
        self._stderr: Optional[threading.Thread] = None
        self._renderer = None
        self._log = None
        self._seed = 0

    # ------------------------------------------------------------------ the process

    def _spawn(self) -> None:
        self.workdir.mkdir(parents=True, exist_ok=True)
        if self._log is None:
            self._log = CappedLog(self.workdir / "agent.log")
        try:
            self.proc = subprocess.Popen(self.command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=subprocess.PIPE, cwd=self.cwd, bufsize=0)
        except OSError as err:
            self.proc = None
            raise AgentFailed(f"agent could not start: {' '.join(self.command)}: {err.strerror or err}") from None
        self.lines = queue.Queue()
        self._fresh = True
        threading.Thread(target=_pump, args=(self.proc.stdout, self.lines), daemon=True).start()
        self._stderr = threading.Thread(target=self._log.pump, args=(self.proc.stderr,), daemon=True)
        self._stderr.start()

    def _alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def _stop(self) -> None:
        if self.proc is not None:
            try:
                self.proc.kill()
            except OSError:
                pass
            self._reap()

    def _send(self, message: dict) -> bool:
        """Write one line to the program; False when it cannot be written (the program died)."""
        try:
            self.proc.stdin.write((json.dumps(message) + "\n").encode())
            self.proc.stdin.flush()
            return True
        except (BrokenPipeError, OSError, ValueError, AttributeError):
            return False

    def _died(self, step: int) -> AgentFailed:
        code = self._reap()
        if not self._answered:  # it never got as far as one answer: it cannot play, so the run stops
            raise ProgramFailed(f"agent.command exited (exit code {code}) before it answered anything: "
                                f"{' '.join(self.command)}{self._last_words()}")
        return AgentFailed(f"agent crashed at placement {step} (exit code {code}); see agent.log")

    def _reap(self) -> Optional[int]:
        """Wait for the dead program (its stderr written to the log); its exit code."""
        code = self.proc.wait() if self.proc is not None else None
        if self._stderr is not None:
            self._stderr.join(timeout=5)
            self._stderr = None
        self.proc = None
        self.restarts += 1
        return code

    # ------------------------------------------------------------------ the protocol

    def start(self, task: Task, seed: int, budget: Optional[float]) -> None:
        self._seed = int(seed)
        self._budget = budget

    def choose(self, state: State, task: Task, step: int, budget: Optional[float]) -> Choice:
        if self.proc is not None and not self._alive():
            if step > 1:  # it stopped during the episode
                raise self._died(step)
            self._reap()  # it exited between episodes
        if self.proc is None:
            self._spawn()
        elif step == 1:
            self._fresh = False
        message = decision_message(self.world, state, task, step, self._seed, budget,
                                   image=self._image(state, task, step) if self.render else None)
        line = self._ask(message, step)
        if line is None and step == 1 and not self._fresh:
            # it exited after the last episode's end, while the first decision was being sent
            self._reap()
            self._spawn()
            line = self._ask(message, step)
        if line is None:
            raise self._died(step)
        self._fresh = False
        self._answered = True
        action = _parse(line, step)
        chosen, why = on_grid(state, action, self.world)
        if chosen is None:
            raise AgentFailed(f"{why} (placement {step})")
        return Choice(chosen, None)

    def _last_words(self) -> str:
        """``: `` and the last line the program wrote to stderr (from ``agent.log``), or ''."""
        try:
            tail = (self.workdir / "agent.log").read_bytes()[-2000:].decode(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return f": {tail[-1].strip()[:200]}" if tail else ""

    def _ask(self, message: dict, step: int) -> Optional[str]:
        """Send ``message`` and wait for one line: the line, or ``None`` when the program is gone."""
        if not self._send(message):
            return None
        try:
            return self.lines.get(timeout=self.timeout)
        except queue.Empty:
            self._stop()
            raise AgentFailed(f"agent gave no answer within {self.timeout:g} s at placement {step}") from None

    def end(self, task: Task, seed: int, record: dict) -> None:
        if self._alive():
            self._send(end_message(task, seed, record))

    def close(self) -> None:
        if self.proc is not None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired, ValueError):
                self.proc.kill()
                self.proc.wait()
            self.proc = None
        if self._stderr is not None:
            self._stderr.join(timeout=5)
            self._stderr = None
        if self._log is not None:
            self._log.close()
            self._log = None

    def _image(self, state: State, task: Task, step: int) -> Path:
        """A PNG of the scene before placement ``step`` (the raster renderer, the CNN's view)."""
        from PIL import Image

        from overhang_framework.render import make_renderer, to_uint8

        if self._renderer is None:
            self._renderer = make_renderer({"name": "raster", "size": [128, 128]})
        path = self.workdir / "images" / f"{task.id}-s{self._seed}-{step}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        Image.fromarray(to_uint8(self._renderer.render(state.geometry))).save(tmp, format="PNG")
        os.replace(tmp, path)
        return path.resolve()


def decision_message(world: World, state: State, task: Task, step: int, seed: int, budget: Optional[float],
                     image: Optional[Path] = None) -> dict:
    """The ``decision`` message of placement ``step`` in ``state``, as the program is sent it."""
    message = {"type": "decision", "protocol": PROTOCOL, "task_id": task.id, "sequence": list(task.sequence),
               "seed": int(seed), "step": step, "width": state.next_width,
               "tower": [[b.width, b.x, b.layer] for b in state.geometry.blocks],
               "legal": [[a.x, a.layer] for a in world.legal_actions(state)], "budget": budget}
    if image is not None:
        message["image"] = str(image)
    return message


def end_message(task: Task, seed: int, record: dict) -> dict:
    """The ``end`` message of an episode whose record is ``record``."""
    return {"type": "end", "protocol": PROTOCOL, "task_id": task.id, "seed": int(seed),
            "reward": record["reward"], "stood": record["stood"], "reason": record["reason"]}


#: The protocol document's example: task, seed and the placements before the decision it shows.
EXAMPLE = ("w231321", 0, ((0.4, 1),))


def example_messages(world: Optional[World] = None) -> tuple[dict, dict]:
    """The protocol document's example decision (with ``agent.render=true``) and the end message of that
    episode when it goes on centred on the highest layer, as the benchmark builds them."""
    from overhang_framework.benchmark.agents import play
    from overhang_framework.benchmark.splits import task as task_of
    from overhang_framework.plugins import Registry

    world = world or Registry().create("world", {"name": "overhang"})
    task_id, seed, placed = EXAMPLE
    task = task_of(task_id)
    state = world.initial_state(task)
    for x, layer in placed:
        state = world.step(state, Action(x, layer))
    step = len(placed) + 1
    decision = decision_message(world, state, task, step, seed, None,
                                image=Path("/abs/path/run/images") / f"{task_id}-s{seed}-{step}.png")

    class Prefix(Agent):
        def choose(self, state, task, k, budget):
            if k <= len(placed):
                return Choice(Action(*placed[k - 1]), None)
            legal = world.legal_actions(state)  # centred on the highest layer, as centre.js plays
            return Choice(min(legal, key=lambda a: (-a.layer, abs(a.x))), None)

    record = play(Prefix(), world, task, seed)
    return decision, end_message(task, seed, record)


class ProgramFailed(OverhangError):
    """The program exited before it answered any decision of the run: it cannot play (a missing file or
    module, a syntax error), so the run stops with one line rather than scoring every episode as a fault."""


class CappedLog:
    """``agent.log``: what the program writes to stderr, appended up to :data:`LOG_CAP` bytes in all; past
    the cap one line says how much more was written, and it is dropped."""

    def __init__(self, path: Path, cap: int = LOG_CAP):
        self.path, self.cap = Path(path), int(cap)
        self.fh = open(self.path, "ab")
        self.written = self.fh.tell()
        self.dropped = 0
        self.lock = threading.Lock()

    def write(self, data: bytes) -> None:
        with self.lock:
            room = max(0, self.cap - self.written)
            if room:
                self.fh.write(data[:room])
                self.fh.flush()
                self.written += min(room, len(data))
            self.dropped += max(0, len(data) - room)

    def pump(self, stream) -> None:
        for chunk in iter(lambda: stream.read1(65536) if hasattr(stream, "read1") else stream.read(65536), b""):
            self.write(chunk)

    def close(self) -> None:
        with self.lock:
            if self.dropped:
                self.fh.write(f"\n[agent.log is capped at {self.cap} bytes: {self.dropped} more bytes of the "
                              f"program's stderr were dropped]\n".encode())
            self.fh.close()


def check_starts(command: Sequence[str], cwd: Optional[str] = None, wait: float = START_WAIT) -> Optional[str]:
    """Why the program ``command`` cannot play, in one line, or ``None``: it cannot be started, or it exits
    within ``wait`` seconds without having been sent anything (its stderr's last line is quoted)."""
    try:
        proc = subprocess.Popen(list(command), stdin=subprocess.PIPE, stdout=subprocess.DEVNULL,
                                stderr=subprocess.PIPE, cwd=cwd)
    except OSError as err:
        return f"agent.command cannot be started: {' '.join(command)}: {err.strerror or err}"
    try:
        code = proc.wait(timeout=wait)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        proc.stdin.close()
        proc.stderr.close()
        return None
    err = proc.stderr.read().decode(errors="replace").strip().splitlines()
    proc.stdin.close()
    proc.stderr.close()
    said = f": {err[-1].strip()[:200]}" if err else ""
    return f"agent.command exited (exit code {code}) before it answered anything: {' '.join(command)}{said}"


def _pump(stream, lines: "queue.Queue[Optional[str]]") -> None:
    """Feed the program's stdout into ``lines``, one line at a time, ``None`` at its end."""
    for raw in iter(stream.readline, b""):
        lines.put(raw.decode(errors="replace"))
    lines.put(None)


def _parse(line: str, step: int) -> Action:
    """The placement of one answer line, or :class:`AgentFailed` saying what is wrong with it."""
    shown = line.strip()[:80]
    try:
        answer = json.loads(line)
    except ValueError:
        raise AgentFailed(f"malformed answer at placement {step}: {shown!r} is not JSON; "
                          'answer one line like {"x": 0.3, "layer": 1}') from None
    if not isinstance(answer, dict) or "x" not in answer or "layer" not in answer:
        raise AgentFailed(f"malformed answer at placement {step}: {shown!r} lacks x or layer; "
                          'answer one line like {"x": 0.3, "layer": 1}')
    x, layer = answer["x"], answer["layer"]
    if isinstance(x, bool) or not isinstance(x, (int, float)) or isinstance(layer, bool) or not isinstance(layer, int):
        raise AgentFailed(f"malformed answer at placement {step}: x must be a number and layer a whole number, "
                          f"got {shown!r}")
    return Action(float(x), int(layer))

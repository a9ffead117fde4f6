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
new process when the old one died or hung). What the program writes to stderr goes to ``agent.log``.
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
from overhang_framework.geometry import Action
from overhang_framework.interfaces import State, Task, World

PROTOCOL = "overhang-tower-jsonl/1"


class CommandAgent(Agent):
    """The external program ``command`` (a list of words, as for :class:`subprocess.Popen`)."""

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
        self._renderer = None
        self._log = None
        self._seed = 0

    # ------------------------------------------------------------------ the process

    def _spawn(self) -> None:
        self.workdir.mkdir(parents=True, exist_ok=True)
        if self._log is None:
            self._log = open(self.workdir / "agent.log", "ab")
        try:
            self.proc = subprocess.Popen(self.command, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                         stderr=self._log, cwd=self.cwd, bufsize=0)
        except OSError as err:
            self.proc = None
            raise AgentFailed(f"agent could not start: {' '.join(self.command)}: {err.strerror or err}") from None
        self.lines = queue.Queue()
        threading.Thread(target=_pump, args=(self.proc.stdout, self.lines), daemon=True).start()

    def _alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def _stop(self) -> None:
        if self.proc is not None:
            try:
                self.proc.kill()
            except OSError:
                pass
            self.proc.wait()
            self.proc = None
            self.restarts += 1

    def _send(self, message: dict) -> bool:
        """Write one line to the program; False when it cannot be written (the program died)."""
        try:
            self.proc.stdin.write((json.dumps(message) + "\n").encode())
            self.proc.stdin.flush()
            return True
        except (BrokenPipeError, OSError, ValueError, AttributeError):
            return False

    def _died(self, step: int) -> AgentFailed:
        code = self.proc.wait() if self.proc is not None else None
        self.proc = None
        self.restarts += 1
        return AgentFailed(f"agent crashed at placement {step} (exit code {code}); see agent.log")

    # ------------------------------------------------------------------ the protocol

    def start(self, task: Task, seed: int, budget: Optional[float]) -> None:
        self._seed = int(seed)
        self._budget = budget

    def choose(self, state: State, task: Task, step: int, budget: Optional[float]) -> Choice:
        if not self._alive():
            if self.proc is not None:
                self._stop()
            self._spawn()
        legal = self.world.legal_actions(state)
        message = {"type": "decision", "protocol": PROTOCOL, "task_id": task.id, "sequence": list(task.sequence),
                   "seed": self._seed, "step": step, "width": state.next_width,
                   "tower": [[b.width, b.x, b.layer] for b in state.geometry.blocks],
                   "legal": [[a.x, a.layer] for a in legal], "budget": budget}
        if self.render:
            message["image"] = str(self._image(state, task, step))
        if not self._send(message):
            raise self._died(step)
        try:
            line = self.lines.get(timeout=self.timeout)
        except queue.Empty:
            self._stop()
            raise AgentFailed(f"agent gave no answer within {self.timeout:g} s at placement {step}") from None
        if line is None:
            raise self._died(step)
        action = _parse(line, step)
        chosen, why = on_grid(state, action, self.world)
        if chosen is None:
            raise AgentFailed(f"{why} (placement {step})")
        return Choice(chosen, None)

    def end(self, task: Task, seed: int, record: dict) -> None:
        if self._alive():
            self._send({"type": "end", "protocol": PROTOCOL, "task_id": task.id, "seed": int(seed),
                        "reward": record["reward"], "stood": record["stood"], "reason": record["reason"]})

    def close(self) -> None:
        if self.proc is not None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=5)
            except (OSError, subprocess.TimeoutExpired, ValueError):
                self.proc.kill()
                self.proc.wait()
            self.proc = None
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

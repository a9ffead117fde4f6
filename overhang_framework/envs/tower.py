"""``OverhangTower-v0``: the paper's task as a Gymnasium environment, backed by the World plugin."""

from __future__ import annotations

import numbers
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from overhang_framework.envs.spaces import TowerSpaces
from overhang_framework.geometry import MAX_LAYER, WIDTHS
from overhang_framework.interfaces import State, Task

REWARDS = ("paper", "shaped")
RANDOM = "random"  # tasks="random": a new sequence of random_length widths, drawn at each reset


def _tasks(tasks: str | None, sequences: Sequence[Any] | None) -> tuple[list[Task], str | None]:
    from overhang_framework.tasks import parse_tasks

    if tasks == RANDOM:
        if sequences is not None:
            raise ValueError("give tasks (a task set name) or sequences, not both")
        return [], None
    if sequences is not None:
        if tasks is not None:
            raise ValueError("give tasks (a task set name) or sequences, not both")
        seqs = list(sequences)
        if seqs and all(isinstance(w, numbers.Real) and not isinstance(w, bool) for w in seqs):
            seqs = [seqs]  # one sequence
        return parse_tasks(seqs, prefix="seq"), None
    return [], tasks or "paper20"


class OverhangTowerEnv(gym.Env):
    """Place the task's blocks one by one to maximise the overhang, as in the paper.

    Each episode is one task: the first block stands at the ground centre and
    every step places the next block of the sequence. The world is the World
    plugin ``world["name"]`` (default ``overhang``) composed as the main job
    composes it, with ``physics`` and the other ``world`` parameters as
    overrides, so its rules, verdicts and overhang are the models' own.

    Parameters:

    * ``tasks`` -- a task set of ``conf/tasks`` (``paper20``, ``example``, ...),
      or ``sequences`` -- one sequence of widths or a list of them. ``tasks="random"``
      draws a new sequence of ``random_length`` widths (uniform over 0.6, 1.2,
      1.8) at each reset: training on it leaves paper20 unseen for testing.
    * ``physics`` -- the world's physics (``tiered``, ``static`` or ``pybullet``).
    * ``resolution`` -- ``None``: x is continuous; a step in metres: x is rounded
      to that grid (the planners' action set at the world's ``0.1``).
    * ``reward`` -- ``paper``: the final overhang at the end of the sequence when
      every placement stood, else 0, all other rewards 0. ``shaped``: each
      placement that stands gives the overhang it gained, and a collapse or an
      illegal action costs ``failure_penalty``; a successful episode's return is
      then the paper's reward minus the first block's half width. It gives a
      learner credit for towers that stand part of the way, which the paper's
      reward does not.
    * ``observation`` -- ``arrays`` or ``image`` (see :mod:`overhang_framework.envs.spaces`);
      ``max_blocks`` -- the observation's padding (default: the longest task).
    * ``render_mode`` -- ``rgb_array``: :meth:`render` returns a ``(240, 400, 3)``
      uint8 picture of the tower, drawn as the reports draw towers.

    An illegal action (off the grid, unsupported, overlapping, malformed) ends
    the episode as a failure with reward 0 and ``info["illegal"]`` saying why;
    it never raises. ``reset(options={"task": id or index})`` chooses the task;
    otherwise it is drawn with the environment's generator, so
    ``reset(seed=s)`` fixes the episode.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 2}

    def __init__(self, tasks: str | None = None, sequences: Sequence[Any] | None = None,
                 physics: str = "tiered", resolution: float | None = None,
                 world: Mapping[str, Any] | None = None, reward: str = "paper",
                 observation: str = "arrays", max_blocks: int | None = None,
                 image_size: Sequence[int] = (32, 160), render_mode: str | None = None,
                 random_length: int = 6, failure_penalty: float = 1.0):
        from overhang_framework.config import compose_config
        from overhang_framework.plugins import Registry
        from overhang_framework.tasks import tasks_from_config

        if reward not in REWARDS:
            raise ValueError(f"unknown reward {reward!r}; allowed: {', '.join(REWARDS)}")
        if isinstance(failure_penalty, bool) or not isinstance(failure_penalty, int | float) \
                or not np.isfinite(failure_penalty) or failure_penalty < 0:
            raise ValueError(f"failure_penalty must be a finite number >= 0, got {failure_penalty!r}")
        self.failure_penalty = float(failure_penalty)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"unknown render_mode {render_mode!r}; allowed: rgb_array or None")
        if world is not None and not isinstance(world, Mapping):
            raise ValueError(f"world must be a mapping of world parameters, got {world!r}")
        task_list, task_set = _tasks(tasks, sequences)
        world = dict(world or {})
        if "physics" in world:
            raise ValueError("give the physics as physics=..., not inside world")
        overrides = [f"world={world.pop('name', 'overhang')}", f"world.physics={physics}"]
        if task_set is not None:
            from overhang_framework.config import group_options

            known = group_options("tasks")
            if task_set not in known or task_set == "custom":
                allowed = [k for k in known if k != "custom"] + [RANDOM]
                raise ValueError(f"unknown task set {task_set!r}; allowed: {', '.join(allowed)} "
                                 "(or sequences=[...] for your own)")
            overrides.append(f"tasks={task_set}")
        cfg = compose_config(overrides)
        if task_set is not None:
            task_list = tasks_from_config(cfg.tasks)
        from omegaconf import OmegaConf

        params = OmegaConf.to_container(cfg.world, resolve=True)
        params.update(world)
        self.world = Registry().create("world", params)
        self.tasks = task_list
        self.random_length = None
        if tasks == RANDOM:
            if isinstance(random_length, bool) or not isinstance(random_length, int) or random_length < 2:
                raise ValueError(f"random_length must be a whole number >= 2, got {random_length!r}")
            self.random_length = random_length
            self.tasks = [Task("random", (WIDTHS[0],) * random_length)]  # the shape of the tasks to come
        self.reward_mode = reward
        self.render_mode = render_mode
        longest = max(len(t.sequence) for t in self.tasks)
        if longest > MAX_LAYER + 1:
            too_long = next(t for t in self.tasks if len(t.sequence) == longest)
            raise ValueError(f"task {too_long.id} has {longest} blocks; at most {MAX_LAYER + 1} fit the grid")
        self.spaces = TowerSpaces(max_blocks=longest if max_blocks is None else max_blocks,
                                  observation=observation, resolution=resolution, image_size=tuple(image_size))
        for t in self.tasks:
            self.spaces.check_fits(len(t.sequence), t.id)
        self.observation_space = self.spaces.observation_space()
        self.action_space = self.spaces.action_space()
        self._renderer = self.spaces.renderer()
        self._stood = True
        self.task: Task | None = None
        self.state: State | None = None
        self._over = True

    # -- the episode ----------------------------------------------------------------------------

    def _choose_task(self, options: Mapping[str, Any] | None) -> Task:
        wanted = (options or {}).get("task")
        if self.random_length is not None:
            if wanted is not None:
                raise ValueError("tasks='random' draws its tasks; options['task'] cannot choose one")
            draw = self.np_random.integers(len(WIDTHS), size=self.random_length)
            return Task("random", tuple(WIDTHS[i] for i in draw))
        if wanted is None:
            return self.tasks[int(self.np_random.integers(len(self.tasks)))]
        if isinstance(wanted, (int, np.integer)) and not isinstance(wanted, bool):
            if not 0 <= wanted < len(self.tasks):
                raise ValueError(f"task index {wanted} is out of range; {len(self.tasks)} tasks (0 to "
                                 f"{len(self.tasks) - 1})")
            return self.tasks[int(wanted)]
        for t in self.tasks:
            if t.id == str(wanted):
                return t
        raise ValueError(f"unknown task {wanted!r}; known: {', '.join(t.id for t in self.tasks)}")

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.task = self._choose_task(options)
        self.state = self.world.initial_state(self.task)
        self._over = False
        self._stood = True
        return self._observe(), self._info(stable=True, illegal=None)

    def _observe(self) -> dict[str, np.ndarray]:
        return self.spaces.observe(self.state, self._renderer)

    def _info(self, stable: bool, illegal: str | None) -> dict:
        return {"task_id": self.task.id, "overhang": float(self.world.overhang(self.state.geometry)),
                "placed": len(self.state.geometry) - 1, "stable": stable, "illegal": illegal}

    def _potential(self) -> float:
        return float(self.world.overhang(self.state.geometry))

    def step(self, action):
        if self.state is None or self._over:
            raise RuntimeError("the episode is over; call reset() first")
        before = self._potential()
        placed, why = self.spaces.to_action(action)
        if placed is not None:
            why = self.world.illegal_reason(self.state, placed)
        if why is not None:
            self._over = True
            reward = -self.failure_penalty if self.reward_mode == "shaped" else 0.0
            return self._observe(), float(reward), True, False, self._info(stable=True, illegal=why)
        self.state = self.world.successor(self.state, placed)
        stable = bool(self.world.is_stable(self.state.geometry))
        self._stood = stable
        done = self.state.done or not stable
        self._over = done
        if self.reward_mode == "shaped":
            reward = self._potential() - before if stable else -self.failure_penalty
        else:
            reward = self.world.reward(self.state.geometry, True) if (done and stable) else 0.0
        return self._observe(), float(reward), done, False, self._info(stable=stable, illegal=None)

    # -- drawing --------------------------------------------------------------------------------

    def render(self):
        """The tower as the reports draw it (blocks red once it fell, the overhang marked), ``(240, 400, 3)`` uint8."""
        if self.render_mode != "rgb_array" or self.state is None:
            return None
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        from overhang_framework.geometry import BLOCK_HEIGHT
        from overhang_framework.report.build import draw_tower

        fig = Figure(figsize=(4.0, 2.4), dpi=100)
        canvas = FigureCanvasAgg(fig)
        ax = fig.add_axes((0.13, 0.12, 0.85, 0.86))
        draw_tower(ax, self.state.geometry, fell=not self._stood,
                   z_max=self.spaces.max_blocks * BLOCK_HEIGHT + 1.2)
        canvas.draw()
        return np.asarray(canvas.buffer_rgba())[..., :3].copy()

    def close(self):
        backend = getattr(self.world, "backend", None)
        close = getattr(backend, "close", None)
        if callable(close):
            close()
        super().close()

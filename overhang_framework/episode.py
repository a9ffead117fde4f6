"""Running one episode: plan, place, check stability, until the sequence ends or the tower falls."""

from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable, Iterator, Mapping, Optional, Sequence

import numpy as np

from overhang_framework.interfaces import Budget, Planner, Predictor, Task, Value, World
from overhang_framework.parallel import pool_map, tick
from overhang_framework.plugins import build_models
from overhang_framework.tasks import tasks_from_config


def episode_rng(seed: int, task_index: int, repeat: int) -> np.random.Generator:
    """The generator of one episode, independent of which other episodes run or in what order."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(task_index), int(repeat)]))


def run_episode(task: Task, world: World, predictor: Predictor, planner: Planner, value: Value,
                rng: np.random.Generator, time_limit: Optional[float] = None,
                on_step: Optional[Callable[[dict], None]] = None, call_limit: Optional[int] = None,
                on_charge: Optional[Callable[[Budget], None]] = None) -> dict:
    """Play ``task`` to its end and return the episode record (plain JSON-able data).

    The episode ends at the first collapse; the reward is the final overhang if
    the tower was stable after every placement and 0 otherwise. ``on_step`` is
    called with each placement's record as soon as it is made. Each decision
    gets a fresh :class:`Budget` of ``time_limit`` seconds and ``call_limit``
    predictor calls (``None``: no limit), observed by ``on_charge`` (see
    :attr:`Budget.observer`).
    """
    state = world.initial_state(task)
    steps = []
    stable_throughout = True
    while not state.done:
        budget = Budget(seconds=time_limit, predictor_calls=call_limit, observer=on_charge)
        started = time.perf_counter()
        decision = planner.plan(state, predictor, value, budget, rng)
        decision_time = time.perf_counter() - started
        state = world.step(state, decision.action)
        stable = world.is_stable(state.geometry)
        steps.append(
            {
                "width": state.geometry.blocks[-1].width,
                "x": decision.action.x,
                "layer": decision.action.layer,
                "predicted_stability": decision.predicted_stability,
                "choice_probability": decision.choice_probability,
                "choice_rank": decision.choice_rank,
                "stable": stable,
                "overhang": world.overhang(state.geometry),
                "decision_time": decision_time,
                "over_time_limit": time_limit is not None and decision_time > time_limit,
                "spend": dataclasses.asdict(decision.spend),
            }
        )
        if on_step is not None:
            on_step(steps[-1])
        if not stable:
            stable_throughout = False
            break
    return {
        "task_id": task.id,
        "sequence": list(task.sequence),
        "steps": steps,
        "stable_throughout": stable_throughout,
        "overhang": world.overhang(state.geometry),
        "reward": world.reward(state.geometry, stable_throughout),
    }


def play_run_episode(models: dict, task: Task, index: int, repeat: int, seed: int,
                     time_limit: Optional[float], call_limit: Optional[int],
                     on_step: Optional[Callable[[dict], None]] = None,
                     on_charge: Optional[Callable[[Budget], None]] = None) -> dict:
    """Episode ``(index, repeat)`` of a run, played with the run's built ``models`` and seeded from
    ``(seed, index, repeat)``; its record carries ``seed``, ``repeat`` and ``task_index``."""
    record = run_episode(task, models["world"], models["predictor"], models["planner"], models["value"],
                         episode_rng(seed, index, repeat), time_limit, on_step=on_step, call_limit=call_limit,
                         on_charge=on_charge)
    record.update({"seed": seed, "repeat": repeat, "task_index": index})
    return record


def _episode_setup(config: Mapping[str, Any]) -> tuple[dict, list]:
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(dict(config))
    return build_models(cfg), tasks_from_config(cfg.tasks)


def _episode_play(state: tuple[dict, list], job: tuple) -> tuple[dict, dict]:
    models, tasks = state
    index, repeat, seed, time_limit, call_limit = job
    record = play_run_episode(models, tasks[index], index, repeat, seed, time_limit, call_limit,
                              on_step=lambda step: tick())
    models["episodes_played"] = models.get("episodes_played", 0) + 1
    counters = {"world": models["world"].stats(), "predictor": getattr(models["predictor"], "stats", dict)(),
                "episodes_played": models["episodes_played"]}
    return record, counters


def play_episodes(config: Mapping[str, Any], todo: Sequence[tuple[int, int]], seed: int,
                  time_limit: Optional[float], call_limit: Optional[int], workers: int,
                  on_step: Callable[[], None], counters: Optional[dict] = None) -> Iterator[dict]:
    """Yield the record of every ``(task index, repeat)`` in ``todo`` as it finishes, played on
    ``workers`` processes; ``on_step`` is called once per placement made anywhere. ``counters``, when
    given, receives each worker's latest world and predictor stats by process id (see
    :func:`merge_stats`)."""
    jobs = [(index, repeat, seed, time_limit, call_limit) for index, repeat in todo]
    for _, (record, latest), pid in pool_map(_episode_setup, (dict(config),), _episode_play, jobs, workers, on_step):
        # a worker's counters only grow; results that finish together come in any order, so keep its latest
        played = latest.pop("episodes_played")
        if counters is not None and played >= counters.get(pid, {}).get("_played", 0):
            counters[pid] = {**latest, "_played": played}
        yield record

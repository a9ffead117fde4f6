"""Notes said before a run starts: settings known to be slow, and settings that mean less than they say.

A run prints each note once on stderr (and logs it) before its first
episode; nothing is refused. The figures come from the docs, where the
command that measured each one is named.
"""

from __future__ import annotations

from typing import Any, Sequence

from omegaconf import DictConfig

from overhang_framework.interfaces import Task


#: Minutes one paper20 task took with planner=mcts planner.iterations=400 on the tiered physics, 2 cores.
MCTS_MINUTES_PER_TASK_AT_400 = 2.5


def run_notes(cfg: DictConfig, tasks: Sequence[Task], models: dict[str, Any]) -> list[str]:
    """One line for each setting of ``cfg`` that a user should hear about before the run starts."""
    notes = []
    placements = max((len(t.sequence) - 1 for t in tasks), default=0)
    depth = cfg.planner.get("depth")
    if isinstance(depth, int) and not isinstance(depth, bool) and 0 < placements < depth:
        notes.append(f"planner.depth={depth} is more than the {placements} placements of the longest task: "
                     f"each decision searches to the end of its episode, which is what "
                     f"planner.depth={placements} does (the same choices, the same results)")
    if cfg.planner.get("name") == "optimal" and not _answers_from_stored_optima(cfg, tasks, models):
        physics = cfg.world.get("physics")
        cost = ("one task's optimum took from 13 s to 16 min to prove" if physics == "static" else
                "one paper20 task's optimum took from 1.5 to 21 min to prove")
        notes.append(f"planner=optimal proves each decision by exhaustive search over every remaining "
                     f"placement: with predictor={cfg.predictor.get('name')} and world.physics={physics}, "
                     f"{cost} on 2 cores (docs/planners.md); the bar shows each decision's predictor calls "
                     f"as it goes")
    if cfg.planner.get("name") == "mcts" and cfg.world.get("physics") != "static":
        iterations = cfg.planner.get("iterations")
        repeats = cfg.get("repeats", 1)
        if isinstance(iterations, int) and isinstance(repeats, int):
            minutes = MCTS_MINUTES_PER_TASK_AT_400 * iterations / 400 * len(tasks) * repeats
            if minutes >= 10:
                notes.append(f"planner=mcts planner.iterations={iterations} on world.physics="
                             f"{cfg.world.get('physics')}: about {minutes:.0f} min for {len(tasks) * repeats} "
                             f"episodes on 2 cores (iterations=400 took {MCTS_MINUTES_PER_TASK_AT_400:g} min a "
                             f"task, docs/planners.md); condition.call_limit or fewer iterations cost less")
    return notes


def _answers_from_stored_optima(cfg: DictConfig, tasks: Sequence[Task], models: dict[str, Any]) -> bool:
    """Whether the optimal planner replays stored optimal paths for every task (no search at all)."""
    if cfg.planner.get("stored") is False or not getattr(models["predictor"], "world_verdicts", False):
        return False
    from overhang_framework.optimum import optimal_moves
    from overhang_framework.search import state_key

    moves = optimal_moves(models["world"])
    return all(state_key(models["world"].initial_state(t)) in moves for t in tasks)

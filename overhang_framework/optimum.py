"""The optimum of a task: the best reward over the discretised action set, proved by search.

``OptimumSearch`` maximises ``prod_k p(s_k, a_k) * overhang(final tower)`` over
every remaining placement, exhaustively with branch and bound: a greedy
continuation gives a first achievable score, and a subtree is skipped only
when :func:`~overhang_framework.search.reach_bound` (geometry alone) proves it
cannot reach the best score found. States are memoised by their canonical
geometry and remaining widths, and a tower that is its own mirror image is
expanded on one side only. With the veridical predictor the result is the
best reward the task allows.

Optima are kept on disk, keyed by task sequence, physics and resolution, so
every later run and report can show reward / optimum without recomputing it::

    python -m overhang_framework.optimum                       # paper20 with the default world
    python -m overhang_framework.optimum tasks=example world.physics=static

writes (or completes) ``overhang_framework/data/optima.json``; ``--out FILE``
writes elsewhere.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.interfaces import Budget, Predictor, State, Task, World
from overhang_framework.plugins import Registry
from overhang_framework.results import atomic_write_json
from overhang_framework.physics.factory import SOLVER_SETTINGS  # noqa: F401  (result keys leave these out)
from overhang_framework.physics.factory import identity as _ident
from overhang_framework.search import (Expander, binary_verdicts, lookahead_value, reach_bound,  # noqa: F401
                                      root_scores, score_step, settled_scores)

DATA_FILE = Path(__file__).resolve().parent / "data" / "optima.json"




class _FinalOverhang:
    """Leaf value of the full-depth search: the final tower's overhang, with the geometric bound.

    No tighter physical bound is used: a block may be slid under an
    overhanging one and clamped there, so a placement can extend the tower by
    almost its whole width and still stand.
    """

    def __init__(self, world: World, lattice: bool = False):
        self.world = world
        self.inner = Registry().create("value", {"name": "overhang"}, world=world)
        self.lattice = lattice
        self._steps: dict = {}

    def __call__(self, state: State) -> float:
        return self.inner(state)

    def children_values(self, expansion):
        return expansion.overhang

    def step(self, state: State) -> float:
        """The lattice spacing of the overhangs reachable from ``state`` (0 without ``lattice``)."""
        if not self.lattice:
            return 0.0
        widths = tuple(sorted({b.width for b in state.geometry.blocks} | set(state.remaining)))
        step = self._steps.get(widths)
        if step is None:
            step = self._steps[widths] = score_step(getattr(self.world, "resolution", None) or 0.1, widths)
        return step

    def bound(self, state: State, depth: int) -> float:
        if not self.lattice:
            return self.inner.bound(state, depth)
        return reach_bound(self.world, state, depth, step=self.step(state))


class OptimumSearch:
    """Exhaustive search with bounds for the best ``prod p * final overhang`` from a state."""

    def __init__(self, world: World, predictor: Predictor, seed: int = 0, mirror: bool = True,
                 budget: Optional[Budget] = None, lattice: bool = True):
        self.world = world
        self.expander = Expander(world, predictor, Budget() if budget is None else _Unlimited(budget),
                                 seed=seed, mirror=mirror)
        # 0/1 verdicts times an overhang on the grid: scores lie on a lattice (search.score_step), so once
        # one is found only a whole step more counts, and each later block reaches one step less than its
        # width; ``lattice=False`` searches without either
        self.lattice = lattice and binary_verdicts(predictor)
        self.value = _FinalOverhang(world, lattice=self.lattice)
        self.memo: dict = {}

    def step(self, state: State) -> float:
        """The lattice spacing of the scores from ``state`` (0: none is used)."""
        return self.value.step(state)

    def greedy(self, state: State) -> float:
        """The score of the myopic continuation from ``state``: a score the optimum reaches or beats."""
        score = 1.0
        while not state.done:
            e = self.expander.expand(state, force=True)
            if not e.actions:
                return 0.0
            i = int(np.argmax(settled_scores(e, e.overhang, batch=self.expander.settle_batch)))
            if e.p_at(i) <= 0:
                return 0.0
            score *= e.p_at(i)
            state = e.children[i]
        return score * self.value(state)

    def value_of(self, state: State) -> float:
        """The optimum score from ``state`` to the end of its episode."""
        floor = self.greedy(state)
        return lookahead_value(self.expander, self.value, state, len(state.remaining), floor, self.memo,
                               prefetch=True, step=self.step(state), defer=self.lattice)

    def best_path(self, state: State) -> tuple[float, list]:
        """The optimum score from ``state`` and a sequence of actions that reaches it."""
        best = self.value_of(state)
        path = []
        target = best
        while not state.done and target > 0:
            depth = len(state.remaining)
            e = self.expander.expand(state, force=True)
            for i, (action, child) in enumerate(zip(e.actions, e.children)):
                bound = self.value.bound(child, depth - 1)
                if e.upper[i] <= 0 or (bound is not None and e.upper[i] * bound < target * (1 - 1e-9)):
                    continue
                p = e.p_at(i)
                if p <= 0:
                    continue
                v = lookahead_value(self.expander, self.value, child, depth - 1, target / p, self.memo,
                                    prefetch=True, step=self.step(child), defer=self.lattice)
                if p * v >= target * (1 - 1e-9):
                    path.append(action)
                    state, target = child, v
                    break
            else:  # pragma: no cover - the search found the optimum along some child
                raise RuntimeError("no child reaches the optimum found")
        return best, path

    def root_scores(self, state: State) -> np.ndarray:
        """The optimum score after each first action (exact for the best ones, below them for the rest)."""
        self.greedy(state)
        return root_scores(self.expander, self.value, state, len(state.remaining), exact_all=False,
                           memo=self.memo, prefetch=True)


class _Unlimited(Budget):
    """A budget the optimum ignores (it is the reference), keeping its start time for reports."""

    def __init__(self, budget: Budget):
        super().__init__(started=budget.started)


def physics_id(world: World) -> dict:
    """What a world's verdicts depend on: its physics and their parameters, and its resolution."""
    physics = getattr(world, "physics_name", type(world).__name__)
    params = dict(getattr(world, "backend_params", {}).get(physics, {}))
    return _ident(physics, params, getattr(world, "resolution", None))


def optimum_key(task: Task, world: World) -> str:
    """The disk-cache key of a task's optimum under a world's physics and resolution."""
    return sequence_key(task.sequence, physics_id(world))


def optimum_key_for(sequence: Sequence[float], world_config: dict) -> str:
    """:func:`optimum_key` from a run's resolved ``world`` config (as ``run.json`` holds it)."""
    physics = world_config.get("physics", "tiered")
    return sequence_key(sequence, _ident(physics, dict(world_config.get(physics) or {}), world_config.get("resolution")))


def sequence_key(sequence: Sequence[float], ident: dict) -> str:
    """A short, stable key of a block sequence with what else identifies a stored result (``ident``)."""
    ident = {"sequence": [round(w, 6) for w in sequence], **ident}
    return hashlib.sha256(json.dumps(ident, sort_keys=True, default=str).encode()).hexdigest()[:16]


def load_optima(path: Path | str | None = None) -> dict:
    """The optima kept in ``path`` (default: the project's optima file), by key."""
    return load_keyed(DATA_FILE if path is None else path, "optima")


def load_keyed(path: Path | str, section: str) -> dict:
    """The results kept under ``section`` in the JSON file ``path``, by key (empty when there is no file)."""
    path = Path(path)
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except ValueError as err:
        raise ValueError(f"{path} is not a JSON file of {section}: {err}") from None
    return data.get(section, {})


def task_optimum(task: Task, world: World, predictor: Optional[Predictor] = None,
                 path: Path | str | None = "default") -> dict:
    """The optimum of ``task`` (veridical predictor by default), from the optima file at ``path``
    (the project's by default; ``None``: always compute) or computed."""
    key = optimum_key(task, world)
    cached = load_optima(None if path == "default" else path).get(key) if path is not None else None
    if cached is not None:
        return cached
    if predictor is None:
        predictor = Registry().create("predictor", {"name": "veridical"}, world=world)
    started = time.perf_counter()
    search = OptimumSearch(world, predictor)
    best, path = search.best_path(world.initial_state(task))
    return {"task_id": task.id, "sequence": list(task.sequence), "optimum": best,
            "actions": [[a.x, a.layer] for a in path],
            "seconds": time.perf_counter() - started, "nodes_expanded": search.expander.stats.nodes_expanded,
            "leaves_pruned": search.expander.stats.leaves_pruned, **physics_id(world)}


def _solve(overrides: Sequence[str], index: int) -> tuple[str, dict]:
    """Worker: the optimum of task ``index`` of the config ``overrides`` compose to."""
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    cfg = compose_config([*overrides, "predictor=veridical"])
    task = tasks_from_config(cfg.tasks)[index]
    world = build_models(cfg)["world"]
    return optimum_key(task, world), task_optimum(task, world, path=None)


def optimal_moves(world: World, path: Path | str | None = None) -> dict:
    """The next optimal action of every state on the stored optimal paths of this world's physics and
    resolution, by canonical state key (what the optimal planner replays instead of searching).
    ``path`` defaults to the project's optima file."""
    from overhang_framework.geometry import Action
    from overhang_framework.search import state_key

    path = DATA_FILE if path is None else path
    ident = physics_id(world)
    moves = {}
    for row in load_optima(path).values():
        if {k: row.get(k) for k in ident} != json.loads(json.dumps(ident, default=str)) or "actions" not in row:
            continue
        state = world.initial_state(Task(row["task_id"], tuple(row["sequence"])))
        for x, layer in row["actions"]:
            action = Action(float(x), int(layer))
            moves[state_key(state)] = action
            state = world.successor(state, action)
    return moves


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m overhang_framework.optimum",
        description="Compute the optimum of every task of a task set (veridical predictor, the world's "
                    "physics and resolution) and keep it in the optima file; tasks already there are skipped.")
    parser.add_argument("overrides", nargs="*", help="config overrides, as for the main job (tasks=..., world....)")
    parser.add_argument("--out", default=str(DATA_FILE), help=f"optima file (default: {DATA_FILE})")
    parser.add_argument("--workers", type=int, default=1, help="tasks solved in parallel processes (default 1)")
    args = parser.parse_args(argv)
    if args.workers < 1:
        print(f"error: --workers must be a whole number >= 1, got {args.workers}", file=sys.stderr)
        return 2

    from concurrent.futures import ProcessPoolExecutor, as_completed

    from overhang_framework.progress import progress_bar

    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.errors import OverhangError
    from overhang_framework.preflight import check_command_line
    from overhang_framework.tasks import tasks_from_config

    try:
        check_command_line([*args.overrides, "--cfg", "job"])
        cfg = compose_config([*args.overrides, "predictor=veridical"])
        tasks = tasks_from_config(cfg.tasks)
        world = build_models(cfg)["world"]
        out = Path(args.out)
        optima = load_optima(out)
    except (OverhangError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    todo = [i for i, task in enumerate(tasks) if optimum_key(task, world) not in optima]
    bar = progress_bar(total=len(tasks), initial=len(tasks) - len(todo), desc="optima", unit="task", file=sys.stderr)
    command = "python -m overhang_framework.optimum " + " ".join(args.overrides)
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        futures = {pool.submit(_solve, list(args.overrides), i): i for i in todo}
        for future in as_completed(futures):
            key, row = future.result()
            row["command"] = command.strip()
            optima[key] = row
            atomic_write_json(out, {"optima": optima})  # each one kept as it lands
            bar.set_postfix_str(f"{row['task_id']} {row['optimum']:.2f}")
            bar.update(1)
    bar.close()
    for task in tasks:
        row = optima[optimum_key(task, world)]
        print(f"{task.id}  {' '.join(f'{w:.1f}' for w in task.sequence)}  optimum {row['optimum']:.3f}"
              f"  ({row['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

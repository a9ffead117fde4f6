"""The practice towers a person can build: the best tower that stays legal and stands with every placement off.

People place with continuous x (the page rounds the pointer's position to 0.001 units, at 30 to 72
pixels per unit); models place on the world's grid. A task's optimal tower often has blocks that touch
exactly or a block on a tipping edge: copied by hand, it is refused as an overlap or it falls. So the
practice feedback shows, for each practice task, the tower with the most overhang among the towers on
the world's grid that stay legal and stand after every placement when each placement's x is off by any
amount up to ``tolerance`` in either direction. Checked: every combination of ``-tolerance, 0,
+tolerance`` per placement, for every prefix (3 + 9 + 27 perturbed towers for a task of four blocks),
plus an exact interval check of the legality rules (``docs/experiment.md``, "The practice towers", says
why the corners decide).

:class:`BuildableSearch` visits paths best first with the optimum's machinery: children in the order of
their geometric bound, a child searched only when its untouched optimum
(:func:`~overhang_framework.search.lookahead_value`) beats the best buildable tower found, and the
perturbed towers judged only then, by the world's physics. A tower that passes is confirmed under the
reference (full-window PyBullet) before it is kept; one the reference refuses is passed over.

    python -m overhang_framework.experiment.practice                        # the practice tasks of conf/serve.yaml
    python -m overhang_framework.experiment.practice practice.tolerance=0.03 world.physics=pybullet

The overrides are those of ``conf/serve.yaml``. It writes (or completes)
``overhang_framework/data/practice_towers.json``, keyed by sequence, physics, resolution and tolerance
(``--out FILE`` writes elsewhere); the server reads it and will not start without the towers of its
practice tasks.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from overhang_framework.errors import ConfigError
from overhang_framework.experiment.towers import (  # noqa: F401  (the towers file's terms, shared with the server)
    COMMAND,
    DATA_FILE,
    MAX_TOLERANCE,
    check_tolerance,
    load_towers,
    tower_key,
)
from overhang_framework.geometry import EPS, Action, Block, Geometry, overlap_length
from overhang_framework.interfaces import State, Task, World
from overhang_framework.optimum import OptimumSearch, physics_id
from overhang_framework.search import TIE, lookahead_value

Judge = Callable[[list], np.ndarray]


def corner_offsets(placements: int, tolerance: float) -> list[tuple[float, ...]]:
    """Every combination of ``-tolerance, 0, +tolerance`` for ``placements`` placements (3 ** placements)."""
    return list(itertools.product((-tolerance, 0.0, tolerance), repeat=placements))


def shifted(blocks: Sequence[Block], offsets: Sequence[float]) -> list[Block]:
    """``blocks`` with each one's x moved by its offset (rounded to 1e-9, below the rules' contact tolerance)."""
    return [Block(b.width, round(b.x + d, 9) + 0.0, b.layer) for b, d in zip(blocks, offsets)]


def legal_throughout(ground: Block, placed: Sequence[Block], tolerance: float) -> Optional[str]:
    """Why the last of ``placed`` may be illegal for some offsets within ``tolerance``, or ``None``.

    Exact for overlaps: a pair of blocks of one layer never overlaps when the difference of their offsets
    (within ``[-2 tol, 2 tol]``, the ground block never moves) leaves them apart at both ends on the same
    side. For support it asks for one block below that supports the last block at both ends, which holds
    throughout (the overlap length is concave in the difference); that is sufficient, and on a grid whose
    step exceeds ``2 tol`` also necessary.
    """
    last = placed[-1]
    others = [(ground, 0.0)] + [(b, tolerance) for b in placed[:-1]]
    supported = False
    for b, spread in others:
        ends = (-tolerance - spread, tolerance + spread)
        if b.layer == last.layer:
            sides = {np.sign(last.x + d - b.x) for d in ends}
            if len(sides) > 1 or any(overlap_length(last.left + d, last.right + d, b.left, b.right) > EPS
                                     for d in ends):
                return f"the block at x={last.x:g} may overlap the block at x={b.x:g} in layer {last.layer}"
        elif b.layer == last.layer - 1:
            supported |= all(overlap_length(last.left + d, last.right + d, b.left, b.right) > EPS for d in ends)
    if not supported:
        return f"no block of layer {last.layer - 1} supports the block at x={last.x:g} for every offset"
    return None


def prefix_failure(ground: Block, placed: Sequence[Block], tolerance: float,
                   judges: Sequence[tuple[str, Judge]]) -> Optional[str]:
    """Why the tower ``ground + placed`` fails the tolerance check at its last placement, or ``None``.

    The earlier placements are taken as checked. Every combination of ``-tol, 0, +tol`` of the placed
    blocks must leave the last placement legal on the perturbed blocks before it and the perturbed tower
    standing under each judge (``(name, stable_batch)``).
    """
    from overhang_framework import rules

    why = legal_throughout(ground, placed, tolerance)
    if why:
        return why
    last = placed[-1]
    combos = corner_offsets(len(placed), tolerance)
    geometries = []
    for offsets in combos:
        blocks = [ground, *shifted(placed, offsets)]
        why = rules.illegal_reason(Geometry(tuple(blocks[:-1])), last.width, Action(blocks[-1].x, last.layer))
        if why:
            return f"offsets {_fmt(offsets)}: {why}"
        geometries.append(Geometry(tuple(blocks)))
    for name, judge in judges:
        stands = np.asarray(judge(geometries), dtype=bool)
        if not stands.all():
            return f"offsets {_fmt(combos[int(np.argmin(stands))])}: the tower falls under {name}"
    return None


def path_failure(world: World, task: Task, actions: Sequence[Action], tolerance: float,
                 judges: Sequence[tuple[str, Judge]]) -> Optional[str]:
    """Why the placements ``actions`` of ``task`` fail the tolerance check (the first failing prefix), or ``None``."""
    state = world.initial_state(task)
    ground, placed = state.geometry.blocks[0], []
    for k, action in enumerate(actions, 1):
        why = world.illegal_reason(state, action)
        if why is None:
            placed.append(Block(state.next_width, float(action.x), int(action.layer)))
            state = world.successor(state, action)
            why = prefix_failure(ground, placed, tolerance, judges)
        if why:
            return f"placement {k}: {why}"
    return None


def world_judge(world: World) -> tuple[str, Judge]:
    """The world's own verdicts, as a judge of :func:`prefix_failure`."""
    return f"world.physics={getattr(world, 'physics_name', type(world).__name__)}", world.stable_batch


def reference_judge(world: World) -> Optional[tuple[str, Judge]]:
    """The full-window PyBullet reference with the world's PyBullet parameters (cached), or ``None`` when the
    world's physics is the reference itself."""
    from overhang_framework.physics.factory import make_backend

    if getattr(world, "physics_name", None) == "pybullet":
        return None
    params = dict(getattr(world, "backend_params", {}).get("pybullet", {}))
    backend = make_backend("pybullet", cache=True, **params)
    return "the reference (world.physics=pybullet)", backend.stable_batch


@dataclass
class Buildable:
    """The best buildable tower of a task, and what finding it cost."""

    actions: list  # Action per placement; empty when no tower passes
    reward: float  # the final tower's overhang (0 when none passes)
    checked: int  # prefixes judged under the tolerance check by the world's physics
    confirmed: int  # complete towers judged by the reference
    rejected: int  # of those, the ones the reference refused
    seconds: float


class BuildableSearch:
    """The best tower of a task on the world's grid that passes the tolerance check, searched best first.

    ``reference`` confirms each tower before it is taken (default: :func:`reference_judge` of the world;
    ``False``: the world's verdicts alone).
    """

    def __init__(self, world: World, tolerance: float, reference=None):
        from overhang_framework.plugins import Registry

        self.world = world
        self.tolerance = check_tolerance(tolerance, "tolerance")
        predictor = Registry().create("predictor", {"name": "veridical"}, world=world)
        self.optimum = OptimumSearch(world, predictor)
        self.expander, self.value, self.memo = self.optimum.expander, self.optimum.value, self.optimum.memo
        self.judges = [world_judge(world)]
        if reference is None:
            reference = reference_judge(world)
        self.reference = reference or None

    def best(self, task: Task) -> Buildable:
        started = time.perf_counter()
        self._task = task
        self._best, self._path = 0.0, []
        self._checked = self._confirmed = self._rejected = 0
        state = self.world.initial_state(task)
        self._visit(state, state.geometry.blocks[0], [], [])
        return Buildable(list(self._path), self._best, self._checked, self._confirmed, self._rejected,
                         time.perf_counter() - started)

    def _beats(self, score: float) -> bool:
        return score > self._best * (1 + TIE) + 1e-12

    def _passes(self, ground: Block, placed: list) -> bool:
        self._checked += 1
        return prefix_failure(ground, placed, self.tolerance, self.judges) is None

    def _confirm(self, actions: list) -> bool:
        if self.reference is None:
            return True
        self._confirmed += 1
        ok = path_failure(self.world, self._task, actions, self.tolerance, [self.reference]) is None
        self._rejected += not ok
        return ok

    def _visit(self, state: State, ground: Block, placed: list, actions: list) -> None:
        depth = len(state.remaining)
        e = self.expander.expand(state, force=True)
        if not e.actions:
            return
        if depth == 1:
            bounds = np.asarray(e.overhang, dtype=float)  # the final tower's overhang
        else:
            bounds = np.array([self.value.bound(child, depth - 1) for child in e.children], dtype=float)
            e.look([i for i in range(len(e.actions)) if self._beats(bounds[i])])
        upper = e.upper
        for i in np.argsort(-(upper * bounds), kind="stable"):
            if not self._beats(upper[i] * bounds[i]):
                break  # the rest are no better
            if upper[i] <= 0 or e.p_at(i) <= 0:
                continue
            child, action = e.children[i], e.actions[i]
            if depth > 1 and not self._beats(lookahead_value(self.expander, self.value, child, depth - 1,
                                                             self._best, self.memo, prefetch=True)):
                continue  # even untouched, nothing from this child beats the best buildable tower
            block = Block(state.next_width, float(action.x), int(action.layer))
            if not self._passes(ground, [*placed, block]):
                continue
            if depth > 1:
                self._visit(child, ground, [*placed, block], [*actions, action])
            elif self._confirm([*actions, action]):
                self._best, self._path = float(bounds[i]), [*actions, action]
                return  # the other leaves of this state are no better


def buildable_row(task: Task, world: World, tolerance: float, optimum: Optional[float] = None,
                  reference=None) -> dict:
    """The stored form of ``task``'s buildable tower: placements, tower, reward, cost and the physics."""
    found = BuildableSearch(world, tolerance, reference).best(task)
    state = world.initial_state(task)
    for action in found.actions:
        state = world.successor(state, action)
    tower = [[b.width, b.x, b.layer] for b in state.geometry.blocks] if found.actions else []
    return {"task_id": task.id, "sequence": list(task.sequence), "tolerance": tolerance,
            "actions": [[a.x, a.layer] for a in found.actions], "tower": tower, "reward": found.reward,
            "optimum": optimum, "prefixes_checked": found.checked, "confirmed_by_reference": found.confirmed,
            "refused_by_reference": found.rejected, "seconds": found.seconds, **physics_id(world)}


def _fmt(offsets: Sequence[float]) -> str:
    return "(" + ", ".join(f"{d:+g}" for d in offsets) + ")"


def _world_and_tasks(overrides: Sequence[str]):
    from omegaconf import OmegaConf

    from overhang_framework.experiment.settings import compose
    from overhang_framework.plugins import Registry
    from overhang_framework.tasks import parse_tasks

    cfg = compose(overrides)
    try:
        world = Registry().create("world", OmegaConf.to_container(cfg.world, resolve=True))
    except ValueError as err:
        raise ConfigError(f"world: {err}") from None
    tolerance = check_tolerance(OmegaConf.select(cfg, "practice.tolerance"))
    tasks = parse_tasks(list(cfg.practice.sequences), list(cfg.practice.ids), prefix="practice")
    return world, tasks, tolerance


def parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    ap = argparse.ArgumentParser(
        prog=COMMAND,
        description="Find the best tower of each practice task that stays legal and stands with every placement "
                    "off by up to practice.tolerance (conf/serve.yaml), confirm it under the reference, and keep "
                    "it in the practice towers file; tasks already there are skipped.")
    ap.add_argument("overrides", nargs="*", help="overrides of conf/serve.yaml (practice.tolerance=..., world....)")
    ap.add_argument("--out", default=str(DATA_FILE), help=f"practice towers file (default: {DATA_FILE})")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(argv)

    from overhang_framework.errors import OverhangError
    from overhang_framework.optimum import task_optimum
    from overhang_framework.progress import progress_bar
    from overhang_framework.results import atomic_write_json

    try:
        world, tasks, tolerance = _world_and_tasks(args.overrides)
        out = Path(args.out)
        towers = load_towers(out)
    except (OverhangError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    todo = [t for t in tasks if tower_key(t, world, tolerance) not in towers]
    bar = progress_bar(total=len(tasks), initial=len(tasks) - len(todo), desc="practice towers", unit="task",
                       file=sys.stderr)
    command = " ".join([COMMAND, *args.overrides])
    for task in todo:
        bar.set_postfix_str(f"{task.id} searching")
        optimum = float(task_optimum(task, world)["optimum"])
        row = buildable_row(task, world, tolerance, optimum)
        row["command"] = command
        towers[tower_key(task, world, tolerance)] = row
        atomic_write_json(out, {"towers": towers})  # each one kept as it lands
        bar.set_postfix_str(f"{task.id} {row['reward']:.2f} of {optimum:.2f}")
        bar.update(1)
    bar.close()
    for task in tasks:
        row = towers[tower_key(task, world, tolerance)]
        opt = row["optimum"]
        blocks = " ".join(f"({w:g},{x:g},{layer})" for w, x, layer in row["tower"][1:]) or "none"
        print(f"{task.id}  {' '.join(f'{w:.1f}' for w in task.sequence)}  tolerance {tolerance:g}  reward "
              f"{row['reward']:.2f} of optimum {opt:.2f}  {blocks}  ({row['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The benchmark's task space, its stable task ids and its fixed splits.

A task is a sequence of block widths from {0.6, 1.2, 1.8}, the ground block first. Its id is the
sequence itself, each width written as its number of 0.6-wide units: ``w231321`` is
(1.2, 1.8, 0.6, 1.8, 1.2, 0.6). An id never changes and names the same task in every split, file and
version. The 6-block space has 3^6 = 729 tasks; the splits:

* ``paper20``: the 20 sequences of ``tasks=paper20``, a seeded draw made as the paper made its own
  (the paper does not list its sequences), kept for comparing with people;
* ``test``: 100 held-out 6-block tasks, none of paper20, drawn stratified by ground width and by
  difficulty, so that both are covered in proportion to the pool;
* ``train``: every other 6-block task, dealt into 5 folds stratified the same way, for agents that learn;
* ``cross``: 7-block tasks. No 6-block agent has planned a seventh placement: the tower is a layer
  taller, the horizon one step longer, and a policy that learned what to do at step 5 of 5 must now
  leave room for one more block. Drawn stratified by ground width.

Difficulty, for the draw, is measured once and kept in the splits file: the reward of the myopic
agent and of depth-2 lookahead, both with the veridical predictor under the static physics (a tenth
of a second per task), and the myopic agent's gap to depth 2, ``1 - myopic / depth2``. The draw
itself is a pure function of those numbers and the seed, so ``--check`` redraws it in a moment::

    python -m overhang_framework.benchmark.splits            # measure, draw, write the splits file
    python -m overhang_framework.benchmark.splits --check    # redraw from the kept measures and compare
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path
from typing import Iterable, Optional, Sequence

import numpy as np

from overhang_framework.errors import OverhangError
from overhang_framework.geometry import WIDTHS
from overhang_framework.interfaces import Task

DATA_FILE = Path(__file__).resolve().parent.parent / "data" / "benchmark_splits.json"
SEED = 20261128
N_TEST = 100
N_CROSS = 10
CROSS_LENGTH = 7
FOLDS = 5
SPLITS = ("test", "train", "cross", "paper20")
UNIT = 0.6


class SplitError(OverhangError, ValueError):
    """A split, task id or splits file that is not what the benchmark expects."""


def task_id(sequence: Sequence[float]) -> str:
    """The stable id of a block sequence: ``w`` and each width in units of 0.6 (``w231321``)."""
    digits = []
    for w in sequence:
        units = round(float(w) / UNIT)
        if units not in (1, 2, 3) or abs(units * UNIT - float(w)) > 1e-9:
            raise SplitError(f"width {w!r} is not one of {', '.join(map(str, WIDTHS))}")
        digits.append(str(units))
    if len(digits) < 2:
        raise SplitError(f"a task needs the ground block and at least one more, got {list(sequence)!r}")
    return "w" + "".join(digits)


def sequence_of(tid: str) -> tuple[float, ...]:
    """The block sequence of the task id ``tid`` (the inverse of :func:`task_id`)."""
    if not isinstance(tid, str) or len(tid) < 3 or tid[0] != "w" or any(c not in "123" for c in tid[1:]):
        raise SplitError(f"{tid!r} is not a task id; ids are 'w' and one digit 1-3 per block (0.6 units), "
                         "e.g. w231321")
    return tuple(round(int(c) * UNIT, 10) for c in tid[1:])


def task(tid: str) -> Task:
    """The :class:`Task` with id ``tid``."""
    return Task(tid, sequence_of(tid))


def task_space(length: int = 6) -> list[str]:
    """Every task id of ``length`` blocks, in order: 3 ** length of them."""
    return ["w" + "".join(d) for d in itertools.product("123", repeat=length)]


def paper20_sequences() -> list[list[float]]:
    """The sequences of ``tasks=paper20``, in its order."""
    from overhang_framework.config import compose_config

    return [list(map(float, s)) for s in compose_config(["tasks=paper20"]).tasks.sequences]


# ---------------------------------------------------------------------------------------------- difficulty

def measure(ids: Iterable[str], progress: bool = True) -> dict[str, dict]:
    """The difficulty measures of the tasks ``ids``: myopic and depth-2 rewards under the static
    physics (veridical predictor, argmax, seed 0), and the myopic gap ``1 - myopic / depth2``."""
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.episode import episode_rng, run_episode
    from overhang_framework.progress import progress_bar

    ids = list(ids)
    agents = {}
    for name, overrides in (("myopic", ["planner=myopic"]), ("depth2", ["planner=lookahead", "planner.depth=2"])):
        agents[name] = build_models(compose_config(["predictor=veridical", "world.physics=static", *overrides]))
    out = {}
    bar = progress_bar(total=len(ids), desc="difficulty", unit="task", disable=not progress)
    for tid in ids:
        row = {}
        for name, m in agents.items():
            record = run_episode(task(tid), m["world"], m["predictor"], m["planner"], m["value"], episode_rng(0, 0, 0))
            row[name] = round(float(record["reward"]), 6)
        row["gap"] = round(1.0 - row["myopic"] / row["depth2"], 6) if row["depth2"] > 0 else 1.0
        out[tid] = row
        bar.update(1)
    bar.close()
    return out


# ---------------------------------------------------------------------------------------------- the draw

def strata(ids: Sequence[str], measures: dict) -> dict[str, list[str]]:
    """``ids`` grouped by width mix (:func:`composition`), each group ordered by ground width, then
    difficulty (the myopic gap, when ``measures`` has it), then id."""
    groups: dict[str, list[str]] = {}
    for tid in ids:
        groups.setdefault(composition(tid), []).append(tid)
    key = lambda t: (t[1], measures[t]["gap"] if t in measures else 0.0, t)  # noqa: E731
    return {k: sorted(v, key=key) for k, v in sorted(groups.items())}


def stratified_draw(groups: dict[str, list[str]], n: int, rng: np.random.Generator) -> list[str]:
    """``n`` ids drawn without replacement: one from every group, the rest shared by group size (largest
    remainders first, ties by group order); within a group, systematically along its order from a random
    start, so each ground width and each part of the difficulty range gets its share."""
    total = sum(len(v) for v in groups.values())
    if not len(groups) <= n <= total:
        raise SplitError(f"cannot draw {n} tasks from {total} in {len(groups)} groups")
    keys = list(groups)
    sizes = np.array([len(groups[k]) for k in keys])
    exact = 1 + (n - len(keys)) * (sizes - 1) / max(1, int((sizes - 1).sum()))
    take = np.minimum(np.floor(exact).astype(int), sizes)
    for i in sorted(range(len(keys)), key=lambda i: (-(exact[i] - take[i]), i)):
        if take.sum() >= n:
            break
        if take[i] < sizes[i]:
            take[i] += 1
    drawn = []
    for k, m in zip(keys, take):
        members = groups[k]
        start = rng.random()
        drawn += [members[int((start + i) * len(members) / m)] for i in range(int(m))]
    return sorted(drawn)


def draw(measures: dict, paper20: Sequence[str], seed: int = SEED, n_test: int = N_TEST,
         n_cross: int = N_CROSS, cross_length: int = CROSS_LENGTH, folds: int = FOLDS) -> dict:
    """The splits from the kept difficulty ``measures`` of the 6-block tasks and the ``paper20`` ids."""
    rng = np.random.default_rng(seed)
    pool = [t for t in task_space(6) if t not in set(paper20)]
    test = stratified_draw(strata(pool, measures), n_test, rng)
    train = [t for t in pool if t not in set(test)]
    # dealt in turn along the width mixes, each mix's tasks in its order from a random fold
    order = [t for group in strata(train, measures).values() for t in group]
    offset = int(rng.integers(folds))
    fold_ids = [sorted(order[(k + offset) % folds::folds]) for k in range(folds)]
    cross = stratified_draw(_by_ground(task_space(cross_length)), n_cross, rng)
    return {"test": test, "train": fold_ids, "cross": cross, "paper20": list(paper20)}


def _by_ground(ids: Sequence[str]) -> dict[str, list[str]]:
    """``ids`` grouped by ground width, each group ordered by width mix, then id."""
    groups: dict[str, list[str]] = {}
    for tid in sorted(ids, key=lambda t: (composition(t), t)):
        groups.setdefault(tid[1], []).append(tid)
    return groups


# ---------------------------------------------------------------------------------------------- the file

def load(path: Path | str | None = None) -> dict:
    """The splits file (the package's by default), checked for its shape."""
    import json

    path = Path(DATA_FILE if path is None else path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise SplitError(f"no splits file at {path}; make it with python -m overhang_framework.benchmark.splits") from None
    except ValueError as err:
        raise SplitError(f"{path} is not a JSON splits file: {err}") from None
    missing = [k for k in ("seed", "splits", "measures") if k not in data]
    if missing or any(s not in data.get("splits", {}) for s in SPLITS):
        raise SplitError(f"{path} lacks {missing or [s for s in SPLITS if s not in data['splits']]}; "
                         f"a splits file has seed, measures and the splits {', '.join(SPLITS)}")
    return data


def split_ids(name: str, fold: Optional[int] = None, path: Path | str | None = None) -> list[str]:
    """The task ids of split ``name`` (``train``: every fold, or fold ``fold`` only)."""
    splits = load(path)["splits"]
    if name not in splits:
        raise SplitError(f"unknown split {name!r}; splits: {', '.join(SPLITS)}")
    if name == "train":
        if fold is None:
            return sorted(t for f in splits["train"] for t in f)
        if not 0 <= fold < len(splits["train"]):
            raise SplitError(f"train fold {fold} does not exist; folds are 0 to {len(splits['train']) - 1}")
        return list(splits["train"][fold])
    if fold is not None:
        raise SplitError(f"only the train split has folds, not {name!r}")
    return list(splits[name])


def split_tasks(name: str, fold: Optional[int] = None, path: Path | str | None = None) -> list[Task]:
    """The tasks of split ``name`` (see :func:`split_ids`)."""
    return [task(t) for t in split_ids(name, fold, path)]


def composition(tid: str) -> str:
    """The width mix of a task's placed blocks: how many 0.6, 1.2 and 1.8 (``"2-2-1"``)."""
    return "-".join(str(tid[2:].count(d)) for d in "123")


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.results import atomic_write_json

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.benchmark.splits",
                                     description="Measure the difficulty of every 6-block task, draw the "
                                                 "benchmark's splits with a fixed seed, and write the splits file.")
    parser.add_argument("--out", default=str(DATA_FILE), help=f"splits file (default: {DATA_FILE})")
    parser.add_argument("--seed", type=int, default=SEED, help=f"the draw's seed (default {SEED})")
    parser.add_argument("--check", action="store_true",
                        help="redraw from the file's kept measures and seed, and say whether the splits match")
    parser.add_argument("--redraw", action="store_true",
                        help="draw again from the file's kept measures (no measuring) and write the file")
    args = parser.parse_args(argv)
    if args.check:
        try:
            data = load(args.out)
        except SplitError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        again = draw(data["measures"], data["splits"]["paper20"], seed=data["seed"])
        if again != data["splits"]:
            print(f"error: the splits in {args.out} are not what seed {data['seed']} draws from its measures",
                  file=sys.stderr)
            return 1
        print(f"{args.out}: the splits are what seed {data['seed']} draws; " +
              ", ".join(f"{k} {len(split_ids(k, path=args.out))}" for k in SPLITS))
        return 0
    paper20 = [task_id(s) for s in paper20_sequences()]
    measures = load(args.out)["measures"] if args.redraw else measure(task_space(6))
    splits = draw(measures, paper20, seed=args.seed)
    data = {"description": "Overhang Tower benchmark splits; ids are 'w' and each width in 0.6 units, ground block first",
            "seed": args.seed, "command": "python -m overhang_framework.benchmark.splits",
            "difficulty": "myopic and depth-2 rewards (veridical predictor, static physics, seed 0); "
                          "gap = 1 - myopic / depth2",
            "splits": splits, "measures": measures}
    atomic_write_json(args.out, data)
    print(f"wrote {args.out}: " + ", ".join(f"{k} {len(split_ids(k, path=args.out))}" for k in SPLITS))
    return 0


if __name__ == "__main__":
    sys.exit(main())

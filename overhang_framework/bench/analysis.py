"""Speed of the behaviour analyses on a paper-size study: ``python -m overhang_framework.bench.analysis``.

Makes a synthetic log of the paper's size (43 time-limited and 38 unconstrained participants, every
paper20 task, 5 placements each) and runs every analysis of ``python -m overhang_framework.analyze`` on
it, Fig. 4 with the veridical, IPE and CNN predictors included, printing the wall time of each and in
total.

The synthetic participants place legal, random but plausible blocks: at each step a legal grid action
whose centre rests over a block of the layer below (when there is one) and after which the tower
stands under the static physics, chosen by a softmax over the tower's overhang after it (unconstrained
participants reach out more, time-limited ones stack more); its x then moves by N(0, 0.03) where it
stays legal, and the world's physics says whether the tower stands (one batched call per step for every
trial). Time-limited participants time out on 2% of decisions. This is a load for the benchmark, not a
model of people.
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import Action, overhang

#: condition -> (participants, softmax beta on overhang, preference for higher layers, decision-time median s)
CONDITIONS = {"time_limited": (43, 2.0, 1.0, 2.3), "unconstrained": (38, 4.0, 0.3, 6.0)}


def _supported(geometry, width: float, action: Action) -> bool:
    below = [b for b in geometry.blocks if b.layer == action.layer - 1]
    return any(b.left - 1e-9 <= action.x <= b.right + 1e-9 for b in below)


def synthetic_log(world, tasks, seed: int = 0, conditions=CONDITIONS, time_limit: float = 5.0,
                  timeout_rate: float = 0.02, judge=None, noise: float = 0.03) -> list[dict]:
    """Records of a synthetic study: every participant of ``conditions`` does every task of ``tasks`` once.

    Candidates are those that ``judge`` (a world; default ``world``) says stand; the chosen x then moves by
    N(0, ``noise``), so some towers fall under ``world``'s physics (the log's ground truth)."""
    from overhang_framework.check import stable_batch

    rng = np.random.default_rng(seed)
    trials = []
    for condition, (n, beta, up, median) in conditions.items():
        for i in range(n):
            participant = f"{condition[0]}{i + 1:02d}"
            for t, task in enumerate(rng.permutation(len(tasks))):
                trials.append({"participant": participant, "condition": condition, "task": tasks[task],
                               "trial": t + 1, "state": world.initial_state(tasks[task]), "beta": beta, "up": up,
                               "median": median, "records": [], "alive": True})
    steps = max(len(t.sequence) for t in tasks) - 1
    judge = judge or world
    for _ in range(steps):
        active = [tr for tr in trials if tr["alive"] and not tr["state"].done]
        options = []
        for tr in active:
            state = tr["state"]
            legal = world.legal_actions(state)
            options.append([a for a in legal if _supported(state.geometry, state.next_width, a)] or legal)
        candidates = [world.successor(tr["state"], a).geometry for tr, opts in zip(active, options) for a in opts]
        judged = iter(stable_batch(judge, candidates) if candidates else [])
        chosen = []
        for tr, opts in zip(active, options):
            state = tr["state"]
            ok = [next(judged) for _ in opts]
            base = {"log_version": 1, "participant": tr["participant"], "condition": tr["condition"],
                    "task_id": tr["task"].id, "sequence": list(tr["task"].sequence), "trial": tr["trial"],
                    "step": len(state.geometry.blocks), "width": state.next_width,
                    "tower_before": [[b.width, b.x, b.layer] for b in state.geometry.blocks], "source": "simulated"}
            if tr["condition"] == "time_limited" and rng.random() < timeout_rate:
                tr["records"].append({**base, "x": None, "layer": None, "stable": None, "overhang": None,
                                      "reward": 0.0, "decision_time": time_limit, "timed_out": True})
                tr["alive"] = False
                continue
            good = [a for a, v in zip(opts, ok) if v] or opts
            score = np.array([tr["beta"] * overhang(world.successor(state, a).geometry) + tr["up"] * a.layer
                              for a in good])
            p = np.exp(score - score.max())
            action = good[rng.choice(len(good), p=p / p.sum())]
            moved = Action(round(action.x + rng.normal(0, noise), 6), action.layer)
            if world.is_legal(state, moved):
                action = moved
            seconds = float(rng.lognormal(math.log(tr["median"]), 0.5))
            if tr["condition"] == "time_limited":
                seconds = min(seconds, time_limit * 0.99)
            chosen.append((tr, base, action, seconds))
        towers = [world.successor(tr["state"], a).geometry for tr, _, a, _ in chosen]
        verdicts = stable_batch(world, towers) if towers else []
        for (tr, base, action, seconds), tower, stable in zip(chosen, towers, verdicts):
            tr["state"] = world.successor(tr["state"], action)
            last = not stable or tr["state"].done
            stood = stable and all(r["stable"] for r in tr["records"])
            tr["records"].append({**base, "x": action.x, "layer": action.layer, "stable": bool(stable),
                                  "overhang": overhang(tower), "reward": (overhang(tower) if stood else 0.0) if last
                                  else None, "decision_time": round(seconds, 3), "timed_out": False})
            tr["alive"] = not last
    records = [r for tr in sorted(trials, key=lambda tr: (tr["participant"], tr["trial"])) for r in tr["records"]]
    return records


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.analysis",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--world", action="append", default=[], metavar="OVERRIDE",
                    help="world override for the log and the analysis, e.g. world.physics=static (repeatable)")
    ap.add_argument("--scale", type=float, default=1.0, help="participants as a share of the paper's 81 (default 1)")
    ap.add_argument("--predictors", default="veridical,ipe,cnn")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", metavar="DIR", help="write the log and the analysis into DIR (default: a temporary one)")
    args = ap.parse_args(argv)
    from overhang_framework.preflight import overrides_problem

    problem = overrides_problem(args.world)
    if problem is not None:
        print(f"error: --world: {problem}", file=sys.stderr)
        return 2

    from overhang_framework.behaviour.analysis import Settings, build_world, run
    from overhang_framework.behaviour.log import write_log
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    tasks = tasks_from_config(compose_config(list(args.world)).tasks)
    conditions = {c: (max(1, round(n * args.scale)), *rest) for c, (n, *rest) in CONDITIONS.items()}
    with tempfile.TemporaryDirectory() as tmp:
        where = Path(args.keep or tmp)
        where.mkdir(parents=True, exist_ok=True)
        t0 = time.perf_counter()
        world = build_world(args.world)
        judge = build_world([*args.world, "world.physics=static"])
        records = synthetic_log(world, tasks, args.seed, conditions, judge=judge)
        close = getattr(getattr(world, "backend", None), "close", None)
        if close:
            close()
        write_log(records, where / "synthetic.jsonl")
        made = time.perf_counter() - t0
        n_part = sum(c[0] for c in conditions.values())
        print(f"synthetic log: {len(records)} placements, {n_part} participants x {len(tasks)} tasks, "
              f"made in {made:.1f} s", flush=True)
        settings = Settings(world_overrides=list(args.world), seed=args.seed,
                            predictors=[p for p in args.predictors.split(",") if p])
        t0 = time.perf_counter()
        sections = run([where / "synthetic.jsonl"], where / "analysis", settings,
                       log=lambda s: print(s, file=sys.stderr, flush=True))
        total = time.perf_counter() - t0
    world_name = " ".join(args.world) or "default world (tiered)"
    print(f"analysis of {len(records)} placements ({world_name}):")
    for name, sec in sections.items():
        print(f"  {name:<11} {sec.seconds:7.1f} s")
    print(f"  {'total':<11} {total:7.1f} s (reading the log and writing the report included)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

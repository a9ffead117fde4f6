"""The static engine under the default physics: ``python -m overhang_framework.bench.engine``.

The tiered world decides most towers with static checks and runs PyBullet only near a tipping point.
This benchmark times, side by side in one run, the static engine as it is now (the cheap stages compiled,
the LP stage by non-negative least squares with checked certificates, HiGHS for what they leave;
``world.static.compiled=true`` and ``world.static.lp_nnls=true``) and as it was before (the cheap stages
in NumPy, HiGHS for every LP scene; both ``false``), on:

* the **optimum search** of ``--tasks`` paper20 tasks (branch and bound over every placement, veridical
  predictor), each from a cold world;
* the **default main job** (veridical predictor, myopic planner) on the same tasks, one episode each,
  from a cold world.

The two settings alternate task by task; both must give the same optimum and the same episode. Each
cell prints seconds, PyBullet reference runs and the ratio. The last line is one JSON object.

    python -m overhang_framework.bench.engine --tasks 3
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence

SETTINGS = {"now": "true", "before": "false"}


def _world(overrides: Sequence[str], lp_nnls: str):
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config

    cfg = compose_config([*overrides, "predictor=veridical", "planner=myopic", f"+world.static.lp_nnls={lp_nnls}",
                                f"+world.static.compiled={lp_nnls}"])
    return cfg, build_models(cfg)


def _references(world) -> int:
    backend = getattr(world, "backend", None)
    inner = getattr(backend, "backend", backend)
    counts = getattr(inner, "counts", {}) or {}
    return int(counts.get("reference", 0))


def optimum(overrides: Sequence[str], index: int, lp_nnls: str) -> dict:
    from overhang_framework.optimum import task_optimum
    from overhang_framework.tasks import tasks_from_config

    cfg, models = _world(overrides, lp_nnls)
    task = tasks_from_config(cfg.tasks)[index]
    t0 = time.perf_counter()
    row = task_optimum(task, models["world"], path=None)
    return {"seconds": time.perf_counter() - t0, "value": round(float(row["optimum"]), 9),
            "reference": _references(models["world"])}


def episode(overrides: Sequence[str], index: int, lp_nnls: str) -> dict:
    from overhang_framework.episode import play_run_episode
    from overhang_framework.tasks import tasks_from_config

    cfg, models = _world(overrides, lp_nnls)
    task = tasks_from_config(cfg.tasks)[index]
    t0 = time.perf_counter()
    record = play_run_episode(models, task, index, 0, int(cfg.seed), None, None)
    actions = [(round(s["x"], 6), s["layer"], s["stable"]) for s in record["steps"]]
    return {"seconds": time.perf_counter() - t0, "value": [record["reward"], actions],
            "reference": _references(models["world"])}


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.engine", description=__doc__.split("\n\n")[0])
    ap.add_argument("overrides", nargs="*", help="config overrides (tasks=..., world....)")
    ap.add_argument("--tasks", type=int, default=3, help="tasks timed, the task set's first ones (default 3)")
    ap.add_argument("--skip-optimum", action="store_true", help="time the main job only")
    ap.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    from overhang_framework.preflight import overrides_problem

    problem = overrides_problem(args.overrides)
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    available = len(tasks_from_config(compose_config(list(args.overrides)).tasks))
    if not 1 <= args.tasks <= available:
        print(f"error: --tasks must be a whole number from 1 to {available} (the task set's tasks), got {args.tasks}",
              file=sys.stderr)
        return 2
    figures: dict = {}
    cells = [("episode", episode)] + ([] if args.skip_optimum else [("optimum", optimum)])
    for name, fn in cells:
        rows = {k: [] for k in SETTINGS}
        same = 0
        for i in range(args.tasks):
            order = list(SETTINGS) if i % 2 == 0 else list(SETTINGS)[::-1]
            got = {k: fn(args.overrides, i, SETTINGS[k]) for k in order}
            for k in SETTINGS:
                rows[k].append(got[k])
            same += int(got["now"]["value"] == got["before"]["value"])
            print(f"  {name} task {i}: now {got['now']['seconds']:.1f} s, before {got['before']['seconds']:.1f} s "
                  f"({got['now']['reference']} reference runs)", flush=True)
        now = sum(r["seconds"] for r in rows["now"])
        before = sum(r["seconds"] for r in rows["before"])
        figures[name] = {"tasks": args.tasks, "now_seconds": now, "before_seconds": before, "speedup": before / now,
                         "same_result": same, "reference_runs": sum(r["reference"] for r in rows["now"])}
        print(f"{name}: {args.tasks} tasks, now {now:.1f} s, before {before:.1f} s: {before / now:.2f}x faster; "
              f"the same result in {same} of {args.tasks}", flush=True)
    print(json.dumps(figures))
    if args.json:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.json, figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The optimum search before and after the benchmark's speed-up: ``python -m overhang_framework.bench.optimum``.

Both versions prove the optimum of the same tasks under the default physics, side by side in one run
(:mod:`~overhang_framework.bench.sidebyside`), and must give the same optimum and the same path:

* **before**: the search as ``python -m overhang_framework.optimum`` ran it, a cold world per task,
  ties searched (``OptimumSearch(lattice=False)``);
* **now**: as ``python -m overhang_framework.benchmark.optima`` runs it: scores known to lie on the
  0.1 lattice, so once a score is found only one a whole step higher is searched for, and each later
  block bounded by its width less one step; an inner tower that only the reference can decide is
  settled only after its subtree showed it could beat the best score (most cannot, so most such
  towers are never simulated); one world for all the tasks of a worker, so a tower two tasks build is
  decided once.

Neither uses a verdict file. Prints seconds and PyBullet reference runs per task, the ratio, and one
JSON line::

    python -m overhang_framework.bench.optimum --tasks w113132,w121232,w311111
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence


def _world():
    from overhang_framework.plugins import Registry

    return Registry().create("world", {"name": "overhang"})


def _references(world) -> int:
    backend = getattr(world, "backend", None)
    inner = getattr(backend, "backend", backend)
    return int((getattr(inner, "counts", {}) or {}).get("reference", 0))


def solve(world, tid: str, lattice: bool) -> dict:
    from overhang_framework.benchmark.splits import task
    from overhang_framework.optimum import OptimumSearch
    from overhang_framework.plugins import Registry

    predictor = Registry().create("predictor", {"name": "veridical"}, world=world)
    before = _references(world)
    search = OptimumSearch(world, predictor, lattice=lattice)
    best, path = search.best_path(world.initial_state(task(tid)))
    return {"optimum": round(float(best), 9), "path": [[a.x, a.layer] for a in path],
            "reference_runs": _references(world) - before, "nodes": search.expander.stats.nodes_expanded}


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.bench.sidebyside import ratio, side_by_side
    from overhang_framework.benchmark.splits import SplitError, sequence_of, split_ids

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.optimum", description=__doc__.split("\n\n")[0])
    ap.add_argument("--tasks", default=None, help="comma-separated task ids (default: the first 3 of the test split)")
    ap.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    try:
        ids = args.tasks.split(",") if args.tasks else split_ids("test")[:3]
        for t in ids:
            sequence_of(t)
    except SplitError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    warm = {"world": None}

    def before(tid):
        return solve(_world(), tid, lattice=False)

    def now(tid):
        if warm["world"] is None:
            warm["world"] = _world()
        return solve(warm["world"], tid, lattice=True)

    extra = {"before": [], "now": []}

    def keep(name, fn):
        def run(tid):
            out = fn(tid)
            extra[name].append({"reference_runs": out.pop("reference_runs"), "nodes": out.pop("nodes")})
            return out
        return run

    started = time.perf_counter()
    figures = side_by_side(ids, {"before": keep("before", before), "now": keep("now", now)})
    speedup = ratio(figures, "before", "now")
    result = {"tasks": ids, "same": figures["same"], "speedup": speedup,
              "seconds": {n: v["seconds"] for n, v in figures["versions"].items()},
              "total": {n: v["total"] for n, v in figures["versions"].items()},
              "reference_runs": {n: [e["reference_runs"] for e in extra[n]] for n in extra},
              "nodes": {n: [e["nodes"] for e in extra[n]] for n in extra},
              "optima": [r["optimum"] for r in figures["versions"]["now"]["results"]],
              "wall": time.perf_counter() - started}
    for name in ("before", "now"):
        print(f"{name}: {result['total'][name]:.1f} s, {sum(result['reference_runs'][name])} reference runs, "
              f"{sum(result['nodes'][name])} nodes")
    print(f"the optimum search is {speedup:.2f}x faster now on {len(ids)} tasks; the same optimum and path on "
          f"{figures['same']} of {len(ids)}")
    print(json.dumps(result))
    if args.json:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.json, result)
    return 0 if figures["same"] == len(ids) else 1


if __name__ == "__main__":
    raise SystemExit(main())

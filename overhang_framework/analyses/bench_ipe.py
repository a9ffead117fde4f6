"""Benchmark of the IPE predictor: speed, and agreement with the veridical predictor as sigma -> 0.

Speed: the time of one ``predict`` call scoring every legal action (world
resolution 0.1) of a typical mid-episode state -- a standing tower of 4
blocks, the next block to place -- with K = 50 and sigma = 0.03, on the
``static`` backend and on the ``pybullet`` backend through the process pool.
The states are the first ``--states`` 4-block towers grown by
:func:`~overhang_framework.analyses.ipe_mechanism.episode_questions` (seeded,
every prefix standing). Static times are the median of ``--repeats`` calls
after one warm-up call; PyBullet runs each of ``--pybullet-states`` states once.

Agreement: on the benchmark towers (``towers.random_towers(200, seed)`` and
``towers.near_critical_towers(50, static, seed)``), each tower's last block is
the action scored from the tower below it. The IPE with sigma = 0 must give
exactly the veridical verdicts of the same backend; with a vanishing sigma
(``--tiny-sigma``, K = 50) the majority verdict should too, except for towers
within a few tiny-sigmas of a flip.

    python -m overhang_framework.analyses.bench_ipe
    python -m overhang_framework.analyses.bench_ipe --skip-pybullet

Prints a table and, last, one JSON line with every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from typing import Optional, Sequence

import numpy as np

from overhang_framework.analyses.ipe_mechanism import episode_questions, make_backend
from overhang_framework.geometry import Action, Geometry
from overhang_framework.interfaces import State


def as_question(tower: Geometry) -> tuple[State, Action]:
    """The tower below ``tower``'s last block, and the last block as the action."""
    last = tower.blocks[-1]
    return State(Geometry(tower.blocks[:-1]), (last.width,)), Action(last.x, last.layer)


def mid_episode_states(n: int, seed: int) -> list[State]:
    static = make_backend("static")
    questions = episode_questions(static.stable_batch, per_height=max(n, 10), seed=seed,
                                  min_blocks=5, max_blocks=5)
    return [q.state for q in questions[:n]]


def time_call(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def verdicts_one_by_one(predictor, towers: Sequence[Geometry], rng_seed: int) -> np.ndarray:
    """``predict`` on every tower's last block, batched into one backend call via :meth:`scenes`."""
    scenes = []
    for i, t in enumerate(towers):
        state, action = as_question(t)
        scenes.append(predictor.scenes(state, [action], np.random.default_rng([rng_seed, i])))
    return np.array([v.mean() for v in predictor.run(scenes)])


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.analyses.bench_ipe",
                                 description="IPE speed and sigma -> 0 agreement benchmark.")
    ap.add_argument("--K", type=int, default=50)
    ap.add_argument("--sigma", type=float, default=0.03)
    ap.add_argument("--states", type=int, default=5, help="mid-episode states timed on static (default 5)")
    ap.add_argument("--repeats", type=int, default=5, help="timed static calls per state (default 5)")
    ap.add_argument("--pybullet-states", type=int, default=1, help="states timed on pybullet (default 1)")
    ap.add_argument("--workers", type=int, default=2, help="PyBullet pool processes (default 2)")
    ap.add_argument("--tiny-sigma", type=float, default=1e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-pybullet", action="store_true", help="static backend only")
    return ap.parse_args(argv)


def main(argv: Optional[Sequence[str]] = None) -> dict:
    from tqdm import tqdm

    from overhang_builtins.simulation import IPEPredictor, VeridicalPredictor
    from overhang_framework.plugins import Registry
    from overhang_framework.towers import near_critical_towers, random_towers

    args = parse_args(argv)
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "cache": False})
    static = make_backend("static")
    pool = None if args.skip_pybullet else make_backend("pybullet", args.workers)
    result: dict = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "processor": platform.processor() or platform.machine(), "gpu": None},
        "K": args.K, "sigma": args.sigma, "seed": args.seed, "resolution": world.resolution,
    }

    states = mid_episode_states(args.states, args.seed)
    speed = []
    ipe_static = IPEPredictor(world, K=args.K, sigma=args.sigma, backend=static)
    for i, state in enumerate(tqdm(states, desc="static timing", file=sys.stderr)):
        actions = world.legal_actions(state)
        rng = np.random.default_rng([args.seed, i])
        ipe_static.predict(state, actions, rng)
        times = time_call(lambda: ipe_static.predict(state, actions, rng), args.repeats)
        speed.append({"state": i, "backend": "static", "actions": len(actions),
                      "simulations": len(actions) * args.K, "seconds": float(np.median(times)),
                      "seconds_min": float(np.min(times))})
    if pool is not None:
        ipe_pb = IPEPredictor(world, K=args.K, sigma=args.sigma, backend=pool)
        ipe_pb.predict(states[0], world.legal_actions(states[0])[:2], np.random.default_rng(0))
        for i, state in enumerate(tqdm(states[:args.pybullet_states], desc="pybullet timing", file=sys.stderr)):
            actions = world.legal_actions(state)
            (t,) = time_call(lambda: ipe_pb.predict(state, actions, np.random.default_rng([args.seed, i])), 1)
            speed.append({"state": i, "backend": f"pybullet ({args.workers} processes)", "actions": len(actions),
                          "simulations": len(actions) * args.K, "seconds": t, "seconds_min": t})
    result["speed"] = speed

    towers = random_towers(200, seed=args.seed)
    critical = [c.geometry for c in near_critical_towers(50, static.stable_batch, seed=args.seed)]
    sets = {"random": towers, "near_critical": critical}
    backends = {"static": static} if pool is None else {"static": static, "pybullet": pool}
    agreement = []
    for bname, backend in backends.items():
        veridical = VeridicalPredictor(world, backend=backend)
        zero = IPEPredictor(world, K=args.K, sigma=0.0, backend=backend)
        tiny = IPEPredictor(world, K=args.K, sigma=args.tiny_sigma, backend=backend)
        for sname, ts in tqdm(sets.items(), desc=f"sigma -> 0 ({bname})", file=sys.stderr):
            v = verdicts_one_by_one(veridical, ts, args.seed)
            z = verdicts_one_by_one(zero, ts, args.seed)
            row = {"backend": bname, "towers": sname, "n": len(ts), "stable_rate": float(v.mean()),
                   "sigma0_equal": int((z == v).sum()), "sigma0_binary": bool(np.isin(z, (0, 1)).all())}
            if bname == "static":
                p = verdicts_one_by_one(tiny, ts, args.seed)
                row["tiny_sigma"] = args.tiny_sigma
                row["tiny_majority_equal"] = int(((p > 0.5) == (v > 0.5)).sum())
            agreement.append(row)
    result["agreement"] = agreement
    if pool is not None:
        pool.close()

    print(f"\nIPE benchmark: K={args.K}, sigma={args.sigma}, world resolution {world.resolution}, "
          f"{result['machine']['cpus']} CPUs, no GPU")
    print(f"{'backend':<24} {'state':>5} {'actions':>7} {'sims':>6} {'median s':>9} {'min s':>7}")
    for r in speed:
        print(f"{r['backend']:<24} {r['state']:>5} {r['actions']:>7} {r['simulations']:>6} "
              f"{r['seconds']:>9.3f} {r['seconds_min']:>7.3f}")
    print(f"\n{'backend':<9} {'towers':<14} {'n':>4} {'stable':>6} {'sigma=0 equal':>14} "
          f"{'tiny-sigma majority equal':>26}")
    for r in agreement:
        tiny_col = f"{r['tiny_majority_equal']}/{r['n']} (sigma {r['tiny_sigma']:g})" if "tiny_sigma" in r else "-"
        print(f"{r['backend']:<9} {r['towers']:<14} {r['n']:>4} {r['stable_rate']:>6.2f} "
              f"{r['sigma0_equal']:>7}/{r['n']:<6} {tiny_col:>26}")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()

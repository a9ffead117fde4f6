"""Benchmark of the IPE predictor: speed, and agreement with the veridical predictor as sigma -> 0.

Speed: the time of one ``predict`` call scoring every legal action (world
resolution 0.1) of a typical mid-episode state -- a standing tower of 4
blocks, the next block to place -- with K = 50 and sigma = 0.03, on the
``static`` backend and on the ``pybullet`` backend through the process pool.
The states are the first ``--states`` 4-block towers grown by
:func:`~overhang_framework.towers.episode_questions` (seeded, every prefix
standing). Static times are the median of ``--repeats`` calls after one
warm-up call; PyBullet runs each of ``--pybullet-states`` states once.

Agreement, on the physics benchmark's towers (``python -m
overhang_framework.bench``): ``towers.random_towers(--towers, seed)`` and
``--critical`` near-critical towers (``towers.near_critical_towers`` with seed
``seed + 2``, flips of the backend under test). Each tower's last block is the
action, scored from the tower below it. The check: with a vanishing sigma
(``--tiny-sigma``, K = ``--K``) the IPE's majority verdict equals the
veridical verdict of the same backend, except for towers within a few
tiny-sigmas of a flip. On PyBullet it runs on the first ``--pybullet-towers``
random towers and as many near-critical ones (flips found by PyBullet), on a
pool of ``--workers`` processes.

A sanity row checks that the IPE with sigma = 0 gives the veridical verdicts;
it cannot fail unless the code paths diverge, since both then make the same
backend call on the same geometries.

    python -m overhang_framework.analyses.bench_ipe
    python -m overhang_framework.analyses.bench_ipe --skip-pybullet
    python -m overhang_framework.analyses.bench_ipe --quick

Prints a table and, last, one JSON line with every figure.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence

import numpy as np

from overhang_framework.bench.physics import machine
from overhang_framework.geometry import Action, Geometry
from overhang_framework.interfaces import State
from overhang_framework.physics.factory import make_backend
from overhang_framework.physics.towers import episode_questions, near_critical_towers, random_towers


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


def tower_probabilities(predictor, towers: Sequence[Geometry], rng_seed: int) -> np.ndarray:
    """``p`` of every tower's last block scored from the tower below it, in one backend call."""
    scenes = []
    for i, t in enumerate(towers):
        state, action = as_question(t)
        scenes.append(predictor.scenes(state, [action], np.random.default_rng([rng_seed, i])))
    return np.array([v.mean() for v in predictor.run(scenes)])


def agreement_rows(world, backend, name: str, sets: dict, K: int, tiny_sigma: float, seed: int) -> list[dict]:
    """Per tower set: veridical stable rate, tiny-sigma majority == veridical, and the sigma = 0 sanity check."""
    from overhang_builtins.simulation import IPEPredictor, VeridicalPredictor

    veridical = VeridicalPredictor(world, backend=backend)
    zero = IPEPredictor(world, K=K, sigma=0.0, backend=backend)
    tiny = IPEPredictor(world, K=K, sigma=tiny_sigma, backend=backend)
    rows = []
    for sname, (towers, offsets) in sets.items():
        v = tower_probabilities(veridical, towers, seed) > 0.5
        p = tower_probabilities(tiny, towers, seed)
        z = tower_probabilities(zero, towers, seed)
        wrong = (p > 0.5) != v
        row = {"backend": name, "towers": sname, "n": len(towers), "stable_rate": float(v.mean()),
               "tiny_sigma": tiny_sigma, "K": K, "tiny_majority_equal": int((~wrong).sum()),
               "tiny_uncertain": int(((p > 0) & (p < 1)).sum()),
               "sanity_sigma0_equal": int(((z > 0.5) == v).sum()),
               "sanity_sigma0_binary": bool(np.isin(z, (0, 1)).all())}
        if offsets is not None:
            row["tiny_disagreement_offsets"] = [float(o) for o in np.asarray(offsets)[wrong]]
        rows.append(row)
    return rows


def tower_sets(n_random: int, n_critical: int, reference, seed: int, desc: str) -> dict:
    """The benchmark's random towers and near-critical towers (flips of ``reference``), with their offsets."""
    from overhang_framework.progress import progress_bar

    with progress_bar(desc=f"bisection checks ({desc})", file=sys.stderr) as bar:
        critical = near_critical_towers(n_critical, reference, seed=seed + 2, progress=bar.update) if n_critical > 0 else []
    return {"random": (random_towers(n_random, seed=seed), None),
            "near_critical": ([c.geometry for c in critical], [c.offset for c in critical])}


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.analyses.bench_ipe",
                                 description="IPE speed and sigma -> 0 agreement benchmark.")
    ap.add_argument("--K", type=int, default=50)
    ap.add_argument("--sigma", type=float, default=0.03)
    ap.add_argument("--states", type=int, default=5, help="mid-episode states timed on static (default 5)")
    ap.add_argument("--repeats", type=int, default=5, help="timed static calls per state (default 5)")
    ap.add_argument("--pybullet-states", type=int, default=1, help="states timed on pybullet (default 1)")
    ap.add_argument("--towers", type=int, default=1000, help="random towers for the agreement (default 1000)")
    ap.add_argument("--critical", type=int, default=200, help="near-critical towers (default 200)")
    ap.add_argument("--pybullet-towers", type=int, default=10,
                    help="random and near-critical towers each for the PyBullet agreement (default 10)")
    ap.add_argument("--workers", type=int, default=2, help="PyBullet pool processes (default 2)")
    ap.add_argument("--tiny-sigma", type=float, default=1e-4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--skip-pybullet", action="store_true", help="static backend only")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 2 states, 2 repeats, 100 random and 20 near-critical towers, K = 20, "
                         "no PyBullet timing, 2 + 2 PyBullet towers")
    args = ap.parse_args(argv)
    if args.quick:
        args.states, args.repeats, args.towers, args.critical = 2, 2, 100, 20
        args.K, args.pybullet_states, args.pybullet_towers = 20, 0, 2
    return args


def main(argv: Optional[Sequence[str]] = None) -> dict:
    from overhang_framework.progress import progress_bar

    from overhang_builtins.simulation import IPEPredictor
    from overhang_framework.plugins import Registry

    args = parse_args(argv)
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "cache": False})
    static = make_backend("static")
    pool = None if args.skip_pybullet else make_backend("pybullet", workers=args.workers)
    result: dict = {"machine": machine(), "K": args.K, "sigma": args.sigma, "seed": args.seed,
                    "resolution": world.resolution, "argv": list(argv) if argv is not None else sys.argv[1:]}

    states = mid_episode_states(args.states, args.seed)
    speed = []
    ipe_static = IPEPredictor(world, K=args.K, sigma=args.sigma, backend=static)
    for i, state in enumerate(progress_bar(states, desc="static timing", file=sys.stderr)):
        actions = world.legal_actions(state)
        rng = np.random.default_rng([args.seed, i])
        ipe_static.predict(state, actions, rng)
        times = time_call(lambda: ipe_static.predict(state, actions, rng), args.repeats)
        speed.append({"state": i, "backend": "static", "actions": len(actions),
                      "simulations": len(actions) * args.K, "seconds": float(np.median(times)),
                      "seconds_min": float(np.min(times))})
    if pool is not None and args.pybullet_states > 0:
        ipe_pb = IPEPredictor(world, K=args.K, sigma=args.sigma, backend=pool)
        ipe_pb.predict(states[0], world.legal_actions(states[0])[:2], np.random.default_rng(0))
        for i, state in enumerate(progress_bar(states[:args.pybullet_states], desc="pybullet timing", file=sys.stderr)):
            actions = world.legal_actions(state)
            (t,) = time_call(lambda: ipe_pb.predict(state, actions, np.random.default_rng([args.seed, i])), 1)
            speed.append({"state": i, "backend": f"pybullet ({args.workers} processes)", "actions": len(actions),
                          "simulations": len(actions) * args.K, "seconds": t, "seconds_min": t})
    result["speed"] = speed

    print("agreement: static backend", file=sys.stderr)
    agreement = agreement_rows(world, static, "static",
                               tower_sets(args.towers, args.critical, static.stable_batch, args.seed, "static"),
                               args.K, args.tiny_sigma, args.seed)
    if pool is not None and args.pybullet_towers > 0:
        print(f"agreement: pybullet, {args.pybullet_towers} + {args.pybullet_towers} towers "
              f"(near-critical flips by bisection on the pool)", file=sys.stderr)
        sets = tower_sets(args.pybullet_towers, args.pybullet_towers, pool.stable_batch, args.seed, "pybullet")
        agreement += agreement_rows(world, pool, "pybullet", sets, args.K, args.tiny_sigma, args.seed)
    result["agreement"] = agreement
    if pool is not None:
        pool.close()

    print(f"\nIPE benchmark: K={args.K}, sigma={args.sigma}, world resolution {world.resolution}, {machine()}, no GPU")
    print(f"{'backend':<24} {'state':>5} {'actions':>7} {'sims':>6} {'median s':>9} {'min s':>7}")
    for r in speed:
        print(f"{r['backend']:<24} {r['state']:>5} {r['actions']:>7} {r['simulations']:>6} "
              f"{r['seconds']:>9.3f} {r['seconds_min']:>7.3f}")
    print(f"\n{'backend':<9} {'towers':<14} {'n':>5} {'stable':>6} {'tiny-sigma majority = veridical':>32} "
          f"{'sanity: sigma=0 = veridical':>28}")
    for r in agreement:
        tiny = f"{r['tiny_majority_equal']}/{r['n']} (sigma {r['tiny_sigma']:g}, K {r['K']})"
        print(f"{r['backend']:<9} {r['towers']:<14} {r['n']:>5} {r['stable_rate']:>6.2f} {tiny:>32} "
              f"{r['sanity_sigma0_equal']:>21}/{r['n']:<6}")
    print(json.dumps(result))
    return result


if __name__ == "__main__":
    main()

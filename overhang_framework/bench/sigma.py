"""What one IPE table for every σ would have to do: ``python -m overhang_framework.bench.sigma [--states 8]``.

A fit scores the IPE on a grid of σ, one score table per value; their draws are common (the same standard
normals scaled by each σ). This measures, on the candidates of mid-episode states of the paper's tasks,
under the draws a search would use, the two ways one table could serve every σ:

* **one backend call for the whole grid**: every σ's perturbed scenes judged together by the static
  backend, against one call per σ, side by side, alternating which goes first; the verdicts must be
  identical;
* **a critical σ per draw**: along one draw ``eps``, the scene at ``sigma * eps`` is judged on a fine grid of
  σ, and the benchmark counts how often its verdict changes. A draw whose verdict changes once has one
  critical σ; one that changes twice or more needs several, and one that stands, falls and stands again
  has a set of standing σ that is not an interval, which no single threshold describes.

It prints both, with the share of draws of each kind. Measured on whatever else the machine is doing.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

#: The fit's default σ grid (conf/fit.yaml).
GRID = (0.01, 0.02, 0.03, 0.05, 0.08)


def _scenes(ipe, geometries, draws, sigma: float):
    from overhang_builtins.simulation import Noise

    ipe.noise = Noise(sigma, sigma, sigma)
    return ipe._scenes(geometries, draws)


def _changes(verdicts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per draw (rows: draws, columns: σ ascending): how often the verdict changes, and whether it stands,
    falls and stands again (its standing σ are not an interval)."""
    v = verdicts.astype(np.int8)
    flips = (np.diff(v, axis=1) != 0).sum(axis=1)
    first = np.argmax(v, axis=1)
    last = v.shape[1] - 1 - np.argmax(v[:, ::-1], axis=1)
    span = np.arange(v.shape[1])[None, :]
    inside = (span >= first[:, None]) & (span <= last[:, None])
    gap = (v.any(axis=1)) & ((v == 0) & inside).any(axis=1)
    return flips, gap


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.sigma", description=__doc__.split("\n\n")[0])
    ap.add_argument("--states", type=int, default=8, help="states per number of blocks placed (default 8)")
    ap.add_argument("--placed", default="0,1,2,3", help="blocks placed before each state (default 0,1,2,3)")
    ap.add_argument("--K", type=int, default=50, help="draws per candidate (default 50, the fit's)")
    ap.add_argument("--step", type=float, default=0.0025, help="step of the fine σ grid (default 0.0025)")
    ap.add_argument("--top", type=float, default=0.12, help="largest σ of the fine grid (default 0.12)")
    ap.add_argument("--repeats", type=int, default=3, help="timed repeats of the batching comparison (default 3)")
    ap.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    if args.states < 1 or args.K < 1 or args.repeats < 1 or not 0 < args.step < args.top:
        print("error: --states, --K and --repeats must be at least 1, and 0 < --step < --top", file=sys.stderr)
        return 2
    try:
        placed = [int(p) for p in args.placed.split(",") if p.strip()]
    except ValueError:
        print(f"error: --placed must be whole numbers separated by commas, got {args.placed!r}", file=sys.stderr)
        return 2

    from overhang_framework.bench.planners import mid_episode_states
    from overhang_framework.plugins import Registry
    from overhang_framework.search import canonical_state, node_rng, state_key

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    ipe = registry.create("predictor", {"name": "ipe", "K": args.K}, world=world)
    states = [canonical_state(s) for p in placed
              for s in mid_episode_states(["world.physics=static"], args.states, placed=p) if s.remaining]
    asked = []  # (geometries, draws) of each state's candidates, under the draws a search would use
    for n, state in enumerate(states):
        geometries = ipe.successors(state, world.legal_actions(state))
        if geometries:
            asked.append((geometries, ipe.draws(node_rng(n, state_key(state)), geometries)))
    candidates = sum(len(g) for g, _ in asked)
    print(f"{len(asked)} states ({', '.join(map(str, placed))} blocks placed), {candidates} candidates, "
          f"K = {args.K}, static physics", flush=True)

    # one backend call for the whole grid, against one per σ
    seconds = {"one call per sigma": 0.0, "one call for the grid": 0.0}
    identical = True
    for r in range(args.repeats):
        for n, (geometries, draws) in enumerate(asked):
            scenes = [_scenes(ipe, geometries, draws, s) for s in GRID]
            ways, verdicts = list(seconds), {}
            for way in (ways if (n + r) % 2 == 0 else ways[::-1]):
                t0 = time.perf_counter()
                verdicts[way] = [ipe.run([sc])[0] for sc in scenes] if way == ways[0] else ipe.run(scenes)
                seconds[way] += time.perf_counter() - t0
            identical &= all(np.array_equal(a, b) for a, b in zip(*verdicts.values()))
    gain = seconds["one call per sigma"] / max(seconds["one call for the grid"], 1e-12)
    print(f"judging the {len(GRID)} σ of the fit's grid ({', '.join(map(str, GRID))}), {args.repeats} repeats:")
    for way, s in seconds.items():
        print(f"  {way:<24}{s:>8.2f} s")
    print(f"  one call is {gain:.2f}x as fast; verdicts {'identical' if identical else 'DIFFER'}")

    # the verdict along each draw, on a fine grid of σ
    fine = np.arange(args.step, args.top + args.step / 2, args.step)
    flips, gaps = [], []
    for geometries, draws in asked:
        verdicts = np.stack([ipe.run([_scenes(ipe, geometries, draws, float(s))])[0] for s in fine], axis=-1)
        f, g = _changes(verdicts.reshape(-1, len(fine)))
        flips.append(f)
        gaps.append(g)
    flips, gaps = np.concatenate(flips), np.concatenate(gaps)
    share = {"0": float(np.mean(flips == 0)), "1": float(np.mean(flips == 1)), "2": float(np.mean(flips == 2)),
             "3+": float(np.mean(flips >= 3))}
    print(f"the verdict along each of {flips.size} draws, at {len(fine)} σ from {fine[0]:.4f} to {fine[-1]:.4f}:")
    print("  changes: " + ", ".join(f"{k}: {v:.2%}" for k, v in share.items()))
    print(f"  standing σ not an interval (stands, falls, stands again): {float(np.mean(gaps)):.2%}")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "states": len(asked), "candidates": candidates, "K": args.K, "grid": list(GRID),
            "seconds": seconds, "one_call_speedup": gain, "identical": bool(identical),
            "fine_grid": [float(fine[0]), float(fine[-1]), len(fine)], "draws": int(flips.size),
            "changes": share, "not_interval": float(np.mean(gaps))}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The hand's quadrature against a Monte Carlo of the same hand: ``python -m overhang_framework.bench.hand [--quick]``.

:class:`~overhang_builtins.hand.HandPredictor` averages an inner predictor's answer over the motor noise
``e ~ N(0, sd^2)`` with ``nodes`` Gauss-Hermite nodes; a shifted placement that the rules forbid counts as the
placement itself. Near the edge of stability the inner answer is a step (the veridical predictor's jumps from
1 to 0; the IPE's, under the draws of one call, a staircase of ``K`` small steps), which few nodes integrate
coarsely. This measures how coarsely, on decision states of the paper20 tasks whose first block (and, every
other task, a second one) is put near the edge of stability:

* **the reference**: for every legal action, the average of the inner answer at ``x + e`` over ``M`` draws of
  ``e``, with the hand's own rule (:meth:`HandPredictor.shifted`: x rounded to 6 decimals, a forbidden shift
  replaced by the action itself) and, for the IPE, the one generator state of the hand's call for every
  shifted action (common random numbers). Two Monte Carlos are run: plain (``M`` independent draws) and
  stratified (one draw in each of ``M`` equal-probability intervals of the normal: unbiased too, and on a step
  its error is of order ``1/M`` rather than ``1/sqrt(M)``). The errors are measured against the stratified
  one; the plain one checks it (their difference against their standard errors).
* **the rules**: ``HandPredictor(sd, nodes)`` itself (Gauss-Hermite), and equal-probability nodes (the
  midpoints ``Phi^-1((i + 1/2) / nodes)`` of ``nodes`` equal-mass intervals, equal weights; the same cost, built
  here on a HandPredictor whose nodes and weights are replaced, the class untouched).

For each inner predictor, ``sd`` and rule it prints the largest and the mean absolute error in probability over
the actions, the mean over the actions near a step (reference neither 0 nor 1), the share of actions off by
more than 0.05, and the cost (inner answers per action = nodes); then the nodes each rule needs for a largest
error below 0.05 and 0.01, the machine's load and the wall time. Measured on whatever else the machine is doing.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

#: The motor noise (metres) and the node counts compared.
SDS = (0.02, 0.05, 0.13)
NODES = (3, 5, 9, 15, 25, 51, 101)
#: How far inside the edge of stability (metres) the placed blocks go, cycled over the tasks.
EDGE_OFFSETS = (0.02, 0.1, 0.25)
#: Seeds: the IPE's draws of a state's calls (shared by every rule and the Monte Carlo), the motor draws.
IPE_SEED, DRAW_SEED = 2027, 31
#: A largest error below these is what "needed" is counted for; an action off by more than SHARE_OVER is counted.
TARGETS = (0.05, 0.01)
SHARE_OVER = 0.05
#: Scenes per backend call of the Monte Carlo (the draws are split into chunks of about this many).
CHUNK_SCENES = 200_000
RULES = ("gauss-hermite", "equal-probability")


def gauss_hermite(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The nodes (standard-normal units) and weights of the HandPredictor's rule."""
    z, w = np.polynomial.hermite_e.hermegauss(n)
    return z, w / w.sum()


def equal_probability(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The midpoints (in probability) of ``n`` equal-mass intervals of the standard normal, equal weights."""
    from scipy.special import ndtri

    return ndtri((np.arange(n) + 0.5) / n), np.full(n, 1.0 / n)


def rule_hand(world, inner, sd: float, rule: str, n: int):
    """A HandPredictor with ``rule``'s ``n`` nodes."""
    from overhang_builtins.hand import HandPredictor

    return HandPredictor(world, inner, sd=sd, nodes=n, rule=rule)


def sampled_answers(world, inner, state, actions, sd: float, z: np.ndarray, seed, K: int) -> np.ndarray:
    """The inner answers at every action shifted by every draw ``sd * z`` (rows: draws, columns: actions), by
    the HandPredictor's own :meth:`shifted` (6 decimals, a forbidden shift the action itself); each chunk of
    draws asked with a generator in the state ``seed`` gives it, as every hand's call of the state is."""
    from overhang_framework.geometry import X_DECIMALS

    probe = rule_hand(world, inner, sd, "gauss-hermite", 1)
    chunk = max(1, CHUNK_SCENES // max(1, len(actions) * K))
    rows = []
    for start in range(0, len(z), chunk):
        part = z[start:start + chunk]
        probe.offsets = np.round(sd * part, X_DECIMALS)
        p = inner.predict(state, probe.shifted(state, actions), np.random.default_rng(seed))
        rows.append(np.asarray(p, dtype=float).reshape(len(part), len(actions)))
    return np.concatenate(rows, axis=0)


def monte_carlo(y: np.ndarray, stratified: bool) -> tuple[np.ndarray, np.ndarray]:
    """The average of ``y`` (draws x actions) and its standard error: plain, or for one draw per stratum (in
    stratum order) the collapsed-strata estimate from adjacent pairs (conservative)."""
    m = y.shape[0]
    mean = y.mean(axis=0)
    if not stratified:
        return mean, y.std(axis=0, ddof=1) / np.sqrt(m)
    pairs = y[: m - m % 2].reshape(m // 2, 2, -1)
    return mean, np.sqrt(np.sum((pairs[:, 0] - pairs[:, 1]) ** 2, axis=0)) / m


def standard_draws(m: int, seed) -> tuple[np.ndarray, np.ndarray]:
    """``m`` plain standard-normal draws, and ``m`` stratified ones (one uniform in each equal-probability
    interval, in order)."""
    from scipy.special import ndtri

    rng = np.random.default_rng(seed)
    plain = rng.standard_normal(m)
    strat = ndtri((np.arange(m) + rng.random(m)) / m)
    return plain, strat


def build_states(world, veridical, count: int) -> list:
    """Decision states of the paper20 tasks near the edge of stability: task ``i``'s first block placed on
    layer 1 ``EDGE_OFFSETS[i % 3]`` inside the edge of the ground block (it stands); on every other task a
    second block then put on layer 2 at the largest x of the action grid where the tower still stands. Kept
    when the veridical answers over the legal actions are step-like (some stand, some fall); distinct states
    (geometry and next width) only, the first ``count``."""
    from overhang_framework.config import compose_config
    from overhang_framework.geometry import Action
    from overhang_framework.tasks import tasks_from_config

    states, seen = [], set()
    for i, task in enumerate(tasks_from_config(compose_config(["tasks=paper20"]).tasks)):
        state = world.initial_state(task)
        first = Action(round(task.sequence[0] / 2 - EDGE_OFFSETS[i % len(EDGE_OFFSETS)], 6), 1)
        if world.illegal_reason(state, first) is not None or veridical.predict(state, [first], None)[0] < 1:
            continue
        state = world.step(state, first)
        if i % 2 == 1 and len(state.remaining) > 1:
            upper = [a for a in world.legal_actions(state) if a.layer == 2]
            stands = veridical.predict(state, upper, None) if upper else np.zeros(0)
            if not stands.any():
                continue
            state = world.step(state, max((a for a, s in zip(upper, stands) if s == 1), key=lambda a: a.x))
        key = (state.geometry.key, state.next_width)
        p = veridical.predict(state, world.legal_actions(state), None)
        if key in seen or not (p.min() == 0 and p.max() == 1):
            continue
        seen.add(key)
        states.append((task.id, state))
        if len(states) >= count:
            break
    return states


def needed(rows: list[dict], inner: str, sd: Optional[float], rule: str, target: float) -> Optional[int]:
    """The fewest nodes (of those measured) of ``rule`` whose largest error is below ``target`` at ``sd`` (at every
    sd when ``None``), and at every larger node count measured too; ``None`` when none is."""
    sizes = sorted({r["nodes"] for r in rows if r["inner"] == inner and r["rule"] == rule})
    ok = [all(r["max_error"] < target for r in rows if r["inner"] == inner and r["rule"] == rule
              and r["nodes"] == n and (sd is None or r["sd"] == sd)) for n in sizes]
    for k, n in enumerate(sizes):
        if all(ok[k:]):
            return n
    return None


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.hand", description=__doc__.split("\n\n")[0])
    ap.add_argument("--states", type=int, default=12, help="decision states (default 12)")
    ap.add_argument("--draws", type=int, default=2000, help="Monte Carlo draws M per action, each way (default 2000)")
    ap.add_argument("--sd", default=",".join(map(str, SDS)),
                    help=f"motor noise sds, metres (default {','.join(map(str, SDS))})")
    ap.add_argument("--nodes", default=",".join(map(str, NODES)),
                    help=f"node counts (default {','.join(map(str, NODES))})")
    ap.add_argument("--inner", default="veridical,ipe", help="inner predictors: veridical, ipe (default both)")
    ap.add_argument("--K", type=int, default=50, help="the IPE's simulations per action (default 50)")
    ap.add_argument("--quick", action="store_true", help="2 states, 500 draws, nodes 3,5,9,25 (under a minute)")
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    if args.quick:
        args.states, args.draws = min(args.states, 2), min(args.draws, 500)
        if args.nodes == ap.get_default("nodes"):
            args.nodes = "3,5,9,25"
    try:
        sds = [float(s) for s in args.sd.split(",") if s.strip()]
        node_counts = [int(n) for n in args.nodes.split(",") if n.strip()]
    except ValueError:
        print("error: --sd takes numbers and --nodes whole numbers, separated by commas", file=sys.stderr)
        return 2
    inners = [i for i in args.inner.split(",") if i]
    if [i for i in inners if i not in ("veridical", "ipe")] or not inners:
        print(f"error: --inner takes veridical and/or ipe, got {args.inner!r}", file=sys.stderr)
        return 2
    if args.states < 1 or args.draws < 2 or args.K < 1 or not sds or min(sds) <= 0 or not node_counts \
            or min(node_counts) < 1:
        print("error: --states and --K must be >= 1, --draws >= 2, every sd > 0 and every node count >= 1",
              file=sys.stderr)
        return 2

    from overhang_framework.plugins import Registry

    started, load_before = time.perf_counter(), os.getloadavg()
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    veridical = registry.create("predictor", {"name": "veridical"}, world=world)
    predictors = {
        # the veridical predictor on the static backend's array path: the world's verdicts (checked on every
        # state's legal actions below), without the world's cache filling with a million shifted towers
        "veridical": registry.create("predictor", {"name": "veridical", "backend": "static"}, world=world),
        "ipe": registry.create("predictor", {"name": "ipe", "K": args.K}, world=world)}
    states = build_states(world, veridical, args.states)
    actions = {k: world.legal_actions(s) for k, (_, s) in enumerate(states)}
    for k, (_, state) in enumerate(states):
        if not np.array_equal(predictors["veridical"].predict(state, actions[k], None),
                              veridical.predict(state, actions[k], None)):
            raise AssertionError(f"the static backend's verdicts differ from the world's on state {k}")
    n_actions = sum(len(a) for a in actions.values())
    print(f"{len(states)} states of paper20 ({', '.join(t for t, _ in states)}), {n_actions} legal actions; "
          f"static physics; Monte Carlo M = {args.draws} draws per action (plain and stratified); "
          f"sd {', '.join(f'{s:g}' for s in sds)} m; load {load_before[0]:.2f}", flush=True)

    rows, checks = [], []
    for name in inners:
        inner = predictors[name]
        K = args.K if name == "ipe" else 1
        label = f"ipe K={args.K}" if name == "ipe" else name
        for sd in sds:
            t0 = time.perf_counter()
            ref, ref_se, plain, plain_se, quad = [], [], [], [], {(r, n): [] for r in RULES for n in node_counts}
            for k, (_, state) in enumerate(states):
                seed = [IPE_SEED, k]
                z_plain, z_strat = standard_draws(args.draws, [DRAW_SEED, k])
                for z, means, ses, strat in ((z_strat, ref, ref_se, True), (z_plain, plain, plain_se, False)):
                    m, se = monte_carlo(sampled_answers(world, inner, state, actions[k], sd, z, seed, K), strat)
                    means.append(m)
                    ses.append(se)
                for rule in RULES:
                    for n in node_counts:
                        hand = rule_hand(world, inner, sd, rule, n)
                        quad[rule, n].append(hand.predict(state, actions[k], np.random.default_rng(seed)))
            ref, ref_se = np.concatenate(ref), np.concatenate(ref_se)
            plain, plain_se = np.concatenate(plain), np.concatenate(plain_se)
            near = (ref > 0) & (ref < 1)
            gap = np.abs(plain - ref)
            # a standard error estimated as 0 (every draw gave one answer) is floored at one draw of M off by the
            # answers' smallest step (1/K for the IPE, 1 for the veridical predictor)
            zscore = gap / np.sqrt(plain_se ** 2 + ref_se ** 2 + (1.0 / (K * args.draws)) ** 2)
            checks.append({"inner": label, "sd": sd, "actions": int(ref.size), "near_step": int(near.sum()),
                           "reference_max_se": float(ref_se.max()), "plain_max_se": float(plain_se.max()),
                           "plain_vs_reference_max": float(gap.max()), "plain_vs_reference_max_z": float(zscore.max()),
                           "plain_vs_reference_over_4se": int(np.sum(zscore > 4)),
                           "seconds": time.perf_counter() - t0})
            for rule in RULES:
                for n in node_counts:
                    q = np.concatenate(quad[rule, n])
                    err = np.abs(q - ref)
                    rows.append({"inner": label, "sd": sd, "rule": rule, "nodes": n, "cost": n,
                                 "max_error": float(err.max()), "mean_error": float(err.mean()),
                                 "mean_error_near_step": float(err[near].mean()) if near.any() else 0.0,
                                 "share_over": float(np.mean(err > SHARE_OVER)),
                                 "max_error_vs_plain": float(np.abs(q - plain).max())})
            print(f"  {label}, sd {sd:g}: {checks[-1]['seconds']:.0f} s", file=sys.stderr, flush=True)

    wall, load_after = time.perf_counter() - started, os.getloadavg()
    print()
    print(f"{'inner':<12}{'sd':>6}  {'rule':<18}{'nodes':>6}{'max err':>9}{'mean err':>10}{'near step':>11}"
          f"{'> ' + format(SHARE_OVER, 'g'):>8}{'cost':>6}")
    for r in rows:
        print(f"{r['inner']:<12}{r['sd']:>6g}  {r['rule']:<18}{r['nodes']:>6}{r['max_error']:>9.4f}"
              f"{r['mean_error']:>10.4f}{r['mean_error_near_step']:>11.4f}{r['share_over']:>8.1%}{r['cost']:>6}")
    print("\nerrors against the stratified Monte Carlo; 'near step': mean over the actions whose reference is "
          "neither 0 nor 1; cost: inner answers per action")
    for c in checks:
        print(f"  reference {c['inner']}, sd {c['sd']:g}: {c['near_step']} of {c['actions']} actions near a step; "
              f"largest standard error {c['reference_max_se']:.4f} (collapsed strata; plain Monte Carlo "
              f"{c['plain_max_se']:.4f}); "
              f"plain - stratified at most {c['plain_vs_reference_max']:.4f} ({c['plain_vs_reference_max_z']:.1f} "
              f"standard errors, {c['plain_vs_reference_over_4se']} actions beyond 4)")
    need = {}
    for label in dict.fromkeys(r["inner"] for r in rows):
        for rule in RULES:
            for target in TARGETS:
                per_sd = {sd: needed(rows, label, sd, rule, target) for sd in sds}
                need[f"{label}|{rule}|{target:g}"] = {"every_sd": needed(rows, label, None, rule, target),
                                                      **{f"{sd:g}": v for sd, v in per_sd.items()}}
                shown = ", ".join(f"sd {sd:g}: {v if v is not None else f'> {max(node_counts)}'}"
                                  for sd, v in per_sd.items())
                print(f"  nodes for a largest error < {target:g}, {label}, {rule}: {shown}")
    print(f"load average (1, 5, 15 min): {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f} before, "
          f"{load_after[0]:.2f} {load_after[1]:.2f} {load_after[2]:.2f} after, on {os.cpu_count()} cores; "
          f"wall time {wall:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps({
            "states": [t for t, _ in states], "actions": n_actions, "draws": args.draws, "K": args.K,
            "sds": sds, "nodes": node_counts, "rows": rows, "references": checks, "needed": need,
            "load_before": list(load_before), "load_after": list(load_after), "cpus": os.cpu_count(),
            "wall_seconds": wall}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())

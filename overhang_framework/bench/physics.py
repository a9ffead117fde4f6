"""Physics benchmark: ``python -m overhang_framework.bench``.

Measures, in one run, on a seeded set of random legal towers and on a
near-critical set (:mod:`overhang_framework.towers`):

* the full PyBullet run (the reference: verdicts, final displacements, time),
* the early-stopping PyBullet check (agreement with the full run, time),
* the static backend, one geometry per call and batched (agreement, time,
  throughput), also on scenes perturbed by the IPE predictor's own code
  (``IPEPredictor.perturb``, sigma 0.03, one draw per tower),
* the PyBullet process pool against a one-worker pool (throughput),
* the verdict cache of a static world while a myopic planner with the
  veridical predictor plays ``--episodes`` paper20-like tasks (hit rate),
* how the reference verdicts move with the displacement threshold,

and, when asked:

* ``--margins``: static agreement for several margins (needs ``--critical``),
* ``--rest-speeds``: early stopping with several ``rest_speed`` values against
  the full runs (agreement, and how many stable towers ran the whole window),
* ``--friction-combine N``: the static backend with each friction-combine rule
  against full PyBullet runs on N IPE-perturbed random towers, a third of them
  with gravity tilted by up to 0.4 rad.

It prints a table and, as its last line, one JSON object with the figures.
``--out FILE`` also writes that object to FILE (atomically).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from dataclasses import replace
from typing import Optional, Sequence

import numpy as np
from overhang_framework.progress import progress_bar

from overhang_framework.geometry import Geometry
from overhang_framework.physics.pool import PyBulletPool
from overhang_framework.physics.pybullet_backend import (
    PyBulletParams,
    PyBulletSimulator,
)
from overhang_framework.physics.static_backend import StaticBackend, StaticParams
from overhang_framework.results import atomic_write_json
from overhang_framework.physics.towers import near_critical_towers, random_towers, with_last_x

THRESHOLDS = (0.01, 0.02, 0.05, 0.1, 0.2)
COMBINE_RULES = ("product", "min", "mean")


def confusion(reference: np.ndarray, verdicts: np.ndarray) -> dict:
    """Counts of (reference, verdict) pairs, keyed ``ref_stable_pred_fall`` and so on."""
    name = {True: "stable", False: "fall"}
    return {
        f"ref_{name[r]}_pred_{name[v]}": int(np.sum((reference == r) & (verdicts == v)))
        for r in (True, False)
        for v in (True, False)
    }


def timed_checks(fn, items: Sequence, desc: str, quiet: bool) -> tuple[list, np.ndarray]:
    """``fn(item)`` for every item with its wall time in seconds."""
    results, times = [], []
    for item in progress_bar(items, desc=desc, disable=quiet, leave=False, file=sys.stderr):
        t = time.perf_counter()
        results.append(fn(item))
        times.append(time.perf_counter() - t)
    return results, np.asarray(times)


def batched_rate(backend, geometries, gravity=None, friction=None, repeats: int = 3) -> float:
    """Checks per second of ``backend.stable_batch`` over all ``geometries`` (best of ``repeats``)."""
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        backend.stable_batch(geometries, gravity, friction)
        best = min(best, time.perf_counter() - t)
    return len(geometries) / best


def ipe_scenes(geometries: Sequence[Geometry], rng: np.random.Generator, sigma: float = 0.03,
               backend=None) -> tuple[list[Geometry], np.ndarray, list[np.ndarray]]:
    """One IPE-perturbed scene per geometry, made by the IPE predictor's own code.

    Each geometry goes through ``IPEPredictor.perturb`` with one
    ``Draws.sample`` draw (K = 1) and ``sigma`` on every channel: x offsets
    with overlaps separated, a tilted and scaled gravity vector, per-block
    friction. ``backend`` (default: a default :class:`StaticBackend`) only
    supplies the gravity and friction the noise is centred on. Returns
    ``(scenes, gravity (n, 2), friction [one array per scene])``.
    """
    from overhang_builtins.simulation import Draws, IPEPredictor

    ipe = IPEPredictor(None, K=1, sigma=sigma, backend=backend if backend is not None else StaticBackend())
    scenes, gravity, friction = [], [], []
    for g in geometries:
        s, grav, fric = ipe.perturb([g], Draws.sample(rng, 1, len(g)))
        scenes.extend(s)
        gravity.append(grav)
        friction.extend(fric)
    return scenes, np.concatenate(gravity), friction


def pool_rate(geometries, workers: int, params: PyBulletParams, early_stop: bool) -> tuple[float, np.ndarray]:
    """PyBullet checks per second on a pool of ``workers`` (start-up excluded) and its verdicts."""
    with PyBulletPool(workers, params=params, early_stop=early_stop) as pool:
        pool.worker_pids()
        t = time.perf_counter()
        verdicts = pool.stable_batch(geometries)
        return len(geometries) / (time.perf_counter() - t), verdicts


def margin_sweep(geoms, ref, crit, crit_ref, margins: Sequence[float], base: StaticParams,
                 offsets: int = 101, window: float = 0.05) -> dict:
    """Static agreement for each margin: on the random set, and expected on the near-critical set.

    The expected near-critical agreement of a tower is the fraction of
    ``offsets`` evenly spaced offsets within ``window`` of its reference flip
    at which the static verdict equals the reference's (stable on the side the
    reference found stable), so it does not depend on where the one sampled
    offset fell.
    """
    us = np.linspace(-window, window, offsets)
    out = {}
    for m in margins:
        backend = StaticBackend(replace(base, margin=float(m)))
        random_agree = float(np.mean(backend.stable_batch(geoms) == ref))
        scores = []
        for c, r in zip(crit, crit_ref):
            if c.offset == 0:
                continue
            side = np.sign(c.offset) if r else -np.sign(c.offset)
            v = backend.stable_batch([with_last_x(c.base, c.flip_x + u) for u in us])
            scores.append(np.mean(v == (us * side > 0)))
        out[str(m)] = {"agreement_static": random_agree,
                       "expected_agreement_static_critical": float(np.mean(scores)) if scores else None}
    return out


def rest_speed_sweep(geoms: Sequence[Geometry], reference: np.ndarray, rest_speeds: Sequence[float],
                     params: PyBulletParams, quiet: bool) -> dict:
    """Early stopping with each ``rest_speed`` against the full runs' ``reference`` verdicts.

    Per value: agreement, the towers it calls stable that the full run calls
    fallen and the reverse, how many of the reference's stable towers ran the
    whole window (no early stop), and the median time per check.
    """
    out = {}
    for rs in rest_speeds:
        prm = replace(params, rest_speed=float(rs))
        total = int(round(prm.duration / prm.time_step))
        sim = PyBulletSimulator(prm)
        outcomes, times = timed_checks(lambda g: sim.check(g, early_stop=True), geoms, f"rest_speed {rs:g}", quiet)
        sim.close()
        v = np.array([o.stable for o in outcomes])
        full_window = np.array([o.steps >= total for o in outcomes])
        out[str(rs)] = {
            "agreement": float(np.mean(v == reference)),
            "stable_but_full_run_fell": int(np.sum(v & ~reference)),
            "fell_but_full_run_stood": int(np.sum(~v & reference)),
            "reference_stable": int(reference.sum()),
            "stable_ran_full_window": int(np.sum(full_window & reference)),
            "median_ms": 1e3 * float(np.median(times)),
        }
    return out


def friction_combine_check(n: int, seed: int, sp: StaticParams, pp: PyBulletParams, workers: int,
                           sigma: float = 0.03, max_tilt: float = 0.4, quiet: bool = False) -> dict:
    """Each friction-combine rule of the static backend against full PyBullet runs on noisy, tilted towers.

    ``n`` random towers (``seed``) are perturbed by :func:`ipe_scenes`; every
    third one also has its gravity turned by ``U(-max_tilt, max_tilt)`` rad.
    """
    rng = np.random.default_rng([seed, 3])
    scenes, gravity, friction = ipe_scenes(random_towers(n, seed=seed), rng, sigma, StaticBackend(sp))
    tilt = np.where(np.arange(n) % 3 == 0, rng.uniform(-max_tilt, max_tilt, n), 0.0)
    c, s = np.cos(tilt), np.sin(tilt)
    gravity = np.c_[c * gravity[:, 0] - s * gravity[:, 1], s * gravity[:, 0] + c * gravity[:, 1]]
    with PyBulletPool(workers, params=pp, early_stop=False) as pool:
        if not quiet:
            print(f"friction combine: {n} full PyBullet runs on {workers} workers", file=sys.stderr)
        ref = pool.stable_batch(scenes, gravity, friction)
    out = {"towers": n, "sigma": sigma, "max_tilt": max_tilt, "tilted": int(np.sum(tilt != 0)),
           "reference_stable": int(ref.sum())}
    for rule in COMBINE_RULES:
        v = StaticBackend(replace(sp, friction_combine=rule)).stable_batch(scenes, gravity, friction)
        out[rule] = {"agreement": float(np.mean(v == ref)), **confusion(ref, v)}
    return out


def episode_cache_workload(episodes: int, seed: int = 2025, length: int = 6) -> dict:
    """The static world's verdict cache after a myopic planner with the veridical predictor plays ``episodes`` tasks.

    The tasks are ``generate_sequences(episodes, length, seed)`` (with the
    defaults, the first 20 are the paper20 set), one episode each, as
    ``python -m overhang_framework world.physics=static`` would run them.
    """
    from overhang_framework.episode import episode_rng, run_episode
    from overhang_framework.plugins import Registry
    from overhang_framework.tasks import generate_sequences, parse_tasks

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    predictor = registry.create("predictor", {"name": "veridical"}, world=world)
    planner = registry.create("planner", {"name": "myopic"}, world=world)
    value = registry.create("value", {"name": "overhang"}, world=world)
    placements = 0
    for i, task in enumerate(parse_tasks(generate_sequences(episodes, length, seed), prefix="bench")):
        placements += len(run_episode(task, world, predictor, planner, value, episode_rng(0, i, 0))["steps"])
    return {"episodes": episodes, "sequence_seed": seed, "placements": placements, **world.backend.stats()}


def machine() -> str:
    """The machine a figure was measured on: architecture, cores, Python."""
    return f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_implementation()} {platform.python_version()}"


def run(towers: int = 1000, seed: int = 0, critical: int = 200, workers: int = 2, pool_towers: int = 200,
        quiet: bool = False, static_params: Optional[StaticParams] = None,
        pybullet_params: Optional[PyBulletParams] = None, margins: Sequence[float] = (),
        rest_speeds: Sequence[float] = (), friction_towers: int = 0, episodes: int = 20) -> dict:
    """Run every measurement and return the figures (the JSON object the CLI prints)."""
    sp = static_params or StaticParams()
    pp = pybullet_params or PyBulletParams()
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr))
    geoms = random_towers(towers, seed=seed)
    sizes = np.array([len(g) for g in geoms])

    say(f"{towers} random towers (seed {seed}), {int(sizes.min())}-{int(sizes.max())} blocks")
    sim = PyBulletSimulator(pp)
    full, t_full = timed_checks(lambda g: sim.check(g, early_stop=False), geoms, "pybullet full", quiet)
    ref = np.array([o.stable for o in full])
    disp = np.array([o.displacement for o in full])
    early, t_early = timed_checks(lambda g: sim.check(g, early_stop=True), geoms, "pybullet early stop", quiet)
    es = np.array([o.stable for o in early])
    sim.close()

    static = StaticBackend(sp)
    static.stable_batch(geoms[:10])
    st_single, t_static = timed_checks(static.stable, geoms, "static single", quiet)
    st_single = np.array(st_single, dtype=bool)
    st_batch = static.stable_batch(geoms)
    rate = batched_rate(static, geoms)
    noisy, grav, fric = ipe_scenes(geoms, np.random.default_rng(seed + 1), backend=static)
    rate_noisy = batched_rate(static, noisy, grav, fric)
    lp_before = static.lp_solved
    static.stable_batch(noisy, grav, fric)
    lp_share_noisy = (static.lp_solved - lp_before) / len(noisy)
    lp_before = static.lp_solved
    static.stable_batch(geoms)
    lp_share = (static.lp_solved - lp_before) / len(geoms)

    sub = geoms[: min(pool_towers, len(geoms))]
    say(f"pool: {len(sub)} full PyBullet runs on 1 and on {workers} workers")
    load_before_pool = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    rate1, v1 = pool_rate(sub, 1, pp, early_stop=False)
    rate_n, vn = pool_rate(sub, workers, pp, early_stop=False)

    say(f"cache: {episodes} episodes of the myopic planner with the veridical predictor, static world")
    cache = episode_cache_workload(episodes)

    thresholds = {}
    for th in THRESHOLDS:
        v = disp <= th
        thresholds[str(th)] = {
            "stable_fraction": float(v.mean()),
            "changed_vs_reference": int(np.sum(v != ref)),
            "agreement_static": float(np.mean(v == st_batch)),
        }

    crit_figures = {}
    if critical > 0:
        say(f"near-critical set: {critical} towers, flips found by bisection with full PyBullet runs on {workers} workers")
        with PyBulletPool(workers, params=pp, early_stop=False) as pool:
            bar = progress_bar(desc="bisection checks", disable=quiet, leave=False, file=sys.stderr)
            crit = near_critical_towers(critical, pool.stable_batch, seed=seed + 2, progress=bar.update)
            bar.close()
            cgeoms = [c.geometry for c in crit]
            cref = pool.stable_batch(cgeoms)
        with PyBulletPool(workers, params=pp, early_stop=True) as pool:
            ces = pool.stable_batch(cgeoms)
        cst = static.stable_batch(cgeoms)
        crit_figures = {
            "critical_towers": len(crit),
            "critical_stable_fraction": float(np.mean(cref)),
            "agreement_static_critical": float(np.mean(cst == cref)),
            "agreement_early_stop_critical": float(np.mean(ces == cref)),
            "confusion_static_critical": confusion(cref, cst),
        }
        if margins:
            say(f"margin sweep: {', '.join(map(str, margins))}")
            crit_figures["margin_sweep"] = margin_sweep(geoms, ref, crit, cref, margins, sp)

    extra = {}
    if rest_speeds:
        say(f"rest_speed sweep: {', '.join(map(str, rest_speeds))}")
        extra["rest_speed_sweep"] = rest_speed_sweep(geoms, ref, rest_speeds, pp, quiet)
    if friction_towers > 0:
        extra["friction_combine"] = friction_combine_check(friction_towers, seed, sp, pp, workers, quiet=quiet)

    med_full, med_early, med_static = (float(np.median(t)) for t in (t_full, t_early, t_static))
    figures = {
        "towers": towers,
        "seed": seed,
        "agreement_early_stop": float(np.mean(es == ref)),
        "agreement_static": float(np.mean(st_batch == ref)),
        "agreement_static_critical": crit_figures.pop("agreement_static_critical", None),
        "speedup_early_stop": med_full / med_early,
        "speedup_static": med_full / med_static,
        "static_checks_per_s": rate,
        "pool_speedup": rate_n / rate1,
        "stable_fraction": float(ref.mean()),
        "median_ms": {"pybullet_full": 1e3 * med_full, "pybullet_early_stop": 1e3 * med_early,
                      "static_single": 1e3 * med_static},
        "static_checks_per_s_ipe_noise": rate_noisy,
        "static_lp_share": lp_share,
        "static_lp_share_ipe_noise": lp_share_noisy,
        "static_single_equals_batched": bool(np.all(st_single == st_batch)),
        "pool_checks_per_s": {"1": rate1, str(workers): rate_n},
        "load_average_before_pool": load_before_pool,
        "pool_equals_serial": bool(np.all(v1 == ref[: len(sub)]) and np.all(vn == ref[: len(sub)])),
        "confusion_static": confusion(ref, st_batch),
        "confusion_early_stop": confusion(ref, es),
        "cache": cache,
        "threshold_sensitivity": thresholds,
        **crit_figures,
        **extra,
        "workers": workers,
        "static_params": {k: getattr(sp, k) for k in sp.__dataclass_fields__},
        "pybullet_params": {k: getattr(pp, k) for k in pp.__dataclass_fields__},
        "machine": machine(),
    }
    figures["disagreements_static"] = [
        {"key": [list(b) for b in geoms[i].key], "reference_stable": bool(ref[i]),
         "displacement": float(disp[i])}
        for i in np.flatnonzero(st_batch != ref)[:20]
    ]
    return figures


def table(f: dict) -> str:
    """A readable summary of :func:`run`'s figures."""
    ms = f["median_ms"]
    rows = [
        ("towers (random set)", f"{f['towers']}  ({100 * f['stable_fraction']:.1f}% stable by the full run)"),
        ("pybullet full run, median", f"{ms['pybullet_full']:.1f} ms"),
        ("pybullet early stop, median", f"{ms['pybullet_early_stop']:.2f} ms   speed-up {f['speedup_early_stop']:.1f}x"),
        ("static single, median", f"{1e3 * ms['static_single']:.1f} us   speed-up {f['speedup_static']:.0f}x"),
        ("static batched", f"{f['static_checks_per_s']:.0f} checks/s  (IPE noise: {f['static_checks_per_s_ipe_noise']:.0f}/s)"),
        ("static LP share", f"{100 * f['static_lp_share']:.1f}%  (IPE noise: {100 * f['static_lp_share_ipe_noise']:.1f}%)"),
        ("agreement early stop", f"{f['agreement_early_stop']:.4f}"),
        ("agreement static", f"{f['agreement_static']:.4f}"),
    ]
    if f.get("agreement_static_critical") is not None:
        rows += [
            ("near-critical towers", f"{f['critical_towers']}  ({100 * f['critical_stable_fraction']:.1f}% stable)"),
            ("agreement static, critical", f"{f['agreement_static_critical']:.4f}"),
            ("agreement early stop, critical", f"{f['agreement_early_stop_critical']:.4f}"),
        ]
    pc = f["pool_checks_per_s"]
    rows += [
        ("pool (full runs)", ", ".join(f"{k} worker(s): {v:.2f}/s" for k, v in pc.items())
         + f"   speed-up {f['pool_speedup']:.2f}x"),
        (f"cache hit rate ({f['cache']['episodes']} myopic episodes)",
         f"{f['cache']['hit_rate']:.3f}  ({f['cache']['hits']} hits, {f['cache']['misses']} misses)"),
    ]
    width = max(len(r[0]) for r in rows)
    lines = [f"{a:<{width}}  {b}" for a, b in rows]
    c = f["confusion_static"]
    lines += ["", "static vs full run        pred stable  pred fall",
              f"  ref stable             {c['ref_stable_pred_stable']:>11}  {c['ref_stable_pred_fall']:>9}",
              f"  ref fall               {c['ref_fall_pred_stable']:>11}  {c['ref_fall_pred_fall']:>9}"]
    lines += ["", "threshold  stable   changed  static agreement"]
    for th, t in f["threshold_sensitivity"].items():
        lines.append(f"{th:>9}  {t['stable_fraction']:.3f}  {t['changed_vs_reference']:>7}  {t['agreement_static']:.4f}")
    if f.get("margin_sweep"):
        lines += ["", "margin   agreement (random)  expected agreement (near-critical)"]
        for m, t in f["margin_sweep"].items():
            lines.append(f"{m:>6}   {t['agreement_static']:.4f}              {t['expected_agreement_static_critical']:.4f}")
    if f.get("rest_speed_sweep"):
        lines += ["", "rest_speed  agreement  stable, full run fell  fell, full run stood  stable that ran 5 s  median ms"]
        for rs, t in f["rest_speed_sweep"].items():
            lines.append(f"{rs:>10}  {t['agreement']:.4f}     {t['stable_but_full_run_fell']:>21}  "
                         f"{t['fell_but_full_run_stood']:>20}  {t['stable_ran_full_window']:>11} of {t['reference_stable']:<5}"
                         f"  {t['median_ms']:>9.2f}")
    if f.get("friction_combine"):
        fc = f["friction_combine"]
        lines += ["", f"friction combine: {fc['towers']} IPE-perturbed towers (sigma {fc['sigma']}), "
                      f"{fc['tilted']} tilted by up to {fc['max_tilt']} rad, {fc['reference_stable']} stable by full runs",
                  "rule     agreement  stable, PyBullet fell  fell, PyBullet stood"]
        for rule in COMBINE_RULES:
            t = fc[rule]
            lines.append(f"{rule:<8} {t['agreement']:.4f}     {t['ref_fall_pred_stable']:>21}  {t['ref_stable_pred_fall']:>20}")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--towers", type=int, default=1000, help="random towers (default 1000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--critical", type=int, default=200, help="near-critical towers (default 200, 0 to skip)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 2, help="pool workers (default: all cores)")
    ap.add_argument("--pool-towers", type=int, default=200, help="towers for the pool measurement (default 200)")
    ap.add_argument("--quick", action="store_true",
                    help="tiny smoke run: 30 towers, 6 near-critical, 12 for the pool, 3 episodes")
    ap.add_argument("--margins", type=lambda t: [float(v) for v in t.split(",")], default=[],
                    help="comma-separated static margins to compare (needs --critical > 0)")
    ap.add_argument("--rest-speeds", type=lambda t: [float(v) for v in t.split(",")], default=[],
                    help="comma-separated early-stop rest speeds to compare with the full runs")
    ap.add_argument("--friction-combine", type=int, default=0, metavar="N",
                    help="check each static friction-combine rule against full PyBullet runs on N noisy towers")
    ap.add_argument("--episodes", type=int, default=20,
                    help="myopic episodes for the cache measurement (default 20, the paper20 tasks)")
    ap.add_argument("--out", help="also write the JSON figures to this file")
    ap.add_argument("--quiet", action="store_true", help="no progress bars or table")
    args = ap.parse_args(argv)
    if args.quick:
        args.towers, args.critical, args.pool_towers = min(args.towers, 30), min(args.critical, 6), 12
        args.episodes = min(args.episodes, 3)
    figures = run(args.towers, args.seed, args.critical, args.workers, args.pool_towers, quiet=args.quiet,
                  margins=args.margins, rest_speeds=args.rest_speeds, friction_towers=args.friction_combine,
                  episodes=args.episodes)
    if args.out:
        atomic_write_json(args.out, figures)
    if not args.quiet:
        print(table(figures))
    print(json.dumps({k: v for k, v in figures.items() if k != "disagreements_static"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

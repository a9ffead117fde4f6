"""Agreement with the full-window reference: ``python -m overhang_framework.bench.agreement``.

Measures, against the reference verdict (full-window PyBullet of the exact
geometry, :mod:`overhang_framework.physics.pybullet_backend`):

* **near-critical families** (:data:`~overhang_framework.physics.towers.FAMILIES`):
  for every family but ``edge``, seeded towers whose last block is moved to
  ``--offsets`` uniform offsets within ``--window`` of the x where the
  reference flips (found by bisection with the reference, to 3 mm); ``edge``
  towers have a load passing exactly through a support's edge;
* **planner workloads** (:mod:`~overhang_framework.bench.workload`): every
  candidate of every decision of the default main job (paper20, myopic,
  veridical) and of the same job with ``predictor=ipe``, and the placed towers;

and reports, by family and by distance to the flip:

* the tiered physics (the world's default): how often each stage decides and
  whether its verdicts equal the reference's;
* the static model with the old defaults and with the current ones;
* throughput of the tiered physics and of early-stop PyBullet on the
  planner's workload (one decision's candidates per batch, one process, no cache);
* with ``--band N``: the chaotic band of the reference, on N near-critical
  towers scanned in 1 mm steps across their flip, and how often moving the
  last block by one unit in the last place changes a verdict within 1 cm of
  the flip;
* with ``--creep-only``: only how towers balanced exactly on an edge creep
  (speed between 0.1 and 0.5 s, when they pass the threshold), against the
  early-stop rest speed;
* with ``--robust K``: how often the robust verdict (stable under the exact
  geometry and K fixed 1 mm jitters) differs from the reference on the placed
  towers and on the workload candidates near their flip (those the tiered
  physics sends to the reference).

It prints a table and, as its last line, one JSON object with the figures;
``--out FILE`` also writes that object to FILE (atomically). Reference
verdicts can be kept between runs with ``--reference-cache FILE``.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sys
import time
from dataclasses import asdict, replace
from typing import Optional, Sequence

import numpy as np
from overhang_framework.progress import progress_bar

from overhang_framework.physics.towers import FAMILIES, family_towers, find_flips, last_block_interval, with_last_x
from overhang_framework.bench.workload import planner_workload
from overhang_framework.geometry import Geometry
from overhang_framework.physics.pool import PyBulletPool
from overhang_framework.physics.pybullet_backend import PyBulletParams, PyBulletSimulator
from overhang_framework.physics.static_backend import StaticBackend, StaticParams
from overhang_framework.physics.tiered import TieredBackend, TieredParams

DISTANCE_BINS = (0.0, 0.005, 0.01, 0.02, np.inf)
OLD_STATIC = StaticParams(margin=0.002, height_margin=0.0, friction_scale=1.0)
"""The static model's defaults before the height and friction corrections."""


class Reference:
    """Full-window PyBullet verdicts on a pool, each distinct geometry run once (optionally kept in a file)."""

    def __init__(self, workers: int, params: PyBulletParams = PyBulletParams(early_stop=False),
                 path: Optional[str] = None, quiet: bool = False):
        self.params = replace(params, early_stop=False)
        self.pool = PyBulletPool(workers, params=self.params, early_stop=False)
        self.path = path
        self.quiet = quiet
        self.runs = 0
        self.known: dict = {}
        if path and os.path.exists(path):
            with open(path, "rb") as fh:
                stored = pickle.load(fh)
            if stored.get("params") == repr(self.params):
                self.known = stored["verdicts"]

    def __call__(self, geometries: Sequence[Geometry]) -> np.ndarray:
        geometries = list(geometries)
        todo = {}
        for g in geometries:
            if g.key not in self.known:
                todo.setdefault(g.key, g)
        items = list(todo.values())
        step = 256
        with progress_bar(total=len(items), desc="reference runs", disable=self.quiet or len(items) < step,
                  leave=False, file=sys.stderr) as bar:
            for k in range(0, len(items), step):
                part = items[k:k + step]
                for g, o in zip(part, self.pool.check_batch(part)):
                    self.known[g.key] = (bool(o.stable), int(o.steps))
                bar.update(len(part))
        self.runs += len(items)
        return np.array([self.known[g.key][0] for g in geometries], dtype=bool)

    def steps(self, geometries: Sequence[Geometry]) -> np.ndarray:
        return np.array([self.known[g.key][1] for g in geometries])

    def save(self) -> None:
        if self.path:
            tmp = f"{self.path}.partial"
            with open(tmp, "wb") as fh:
                pickle.dump({"params": repr(self.params), "verdicts": self.known}, fh)
            os.replace(tmp, self.path)

    def close(self) -> None:
        self.pool.close()


def near_critical(reference: Reference, per_family: int, seed: int, window: float, offsets: int):
    """``{family: [(geometry, offset), ...]}``: towers near the reference's flip (offset 0 for ``edge``)."""
    rng = np.random.default_rng([seed, 7])
    out = {}
    for family in FAMILIES:
        bases = family_towers(family, per_family, seed=seed)
        if family == "edge":
            out[family] = [(g, 0.0) for g in bases]
            continue
        rows = []
        for g, fx in zip(bases, find_flips(bases, reference, tolerance=0.003)):
            if fx is None:
                continue
            lo, hi = last_block_interval(g)
            for _ in range(offsets):
                x = float(np.clip(fx + rng.uniform(-window, window), lo, hi))
                rows.append((with_last_x(g, x), x - fx))
        out[family] = rows
    return out


def _agreement(verdicts: np.ndarray, ref: np.ndarray) -> dict:
    return {"n": int(ref.size), "agreement": float(np.mean(verdicts == ref)) if ref.size else None,
            "stable_but_reference_falls": int(np.sum(verdicts & ~ref)),
            "falls_but_reference_stands": int(np.sum(~verdicts & ref))}


def _stages(stage: np.ndarray) -> dict:
    n = max(stage.size, 1)
    return {"static_stable": float(np.sum(stage == 1) / n), "static_fall": float(np.sum(stage == 0) / n),
            "reference": float(np.sum(stage < 0) / n)}


def evaluate(sets: dict, reference: Reference, tiered: TieredParams, statics: dict) -> dict:
    """Per named set ``{name: (geometries, offsets or None)}``: tiered stages and agreement, static agreement."""
    out = {}
    for name, (geoms, offs) in sets.items():
        if not geoms:
            continue
        ref = reference(geoms)
        stage = TieredBackend(tiered).classify(geoms)
        verdict = np.where(stage < 0, ref, stage == 1)
        row = {"reference_stable": float(ref.mean()), "stages": _stages(stage),
               "tiered": _agreement(verdict, ref)}
        for label, params in statics.items():
            row[label] = _agreement(StaticBackend(params).stable_batch(geoms), ref)
        if offs is not None:
            dist = np.abs(np.asarray(offs))
            row["by_distance"] = {}
            for lo, hi in zip(DISTANCE_BINS[:-1], DISTANCE_BINS[1:]):
                sel = (dist >= lo) & (dist < hi)
                if sel.any():
                    key = f"{100 * lo:g}-{100 * hi:g} cm" if np.isfinite(hi) else f">={100 * lo:g} cm"
                    row["by_distance"][key] = {
                        "n": int(sel.sum()),
                        "tiered": float(np.mean(verdict[sel] == ref[sel])),
                        **{label: float(np.mean(StaticBackend(p).stable_batch([geoms[i] for i in np.flatnonzero(sel)])
                                                == ref[sel])) for label, p in statics.items()},
                    }
        out[name] = row
    return out


def throughput(decisions: Sequence[Sequence[Geometry]], tiered: TieredParams, quiet: bool) -> dict:
    """Queries per second on ``decisions`` (one batch each, one process, no cache): tiered and early stop."""
    backend = TieredBackend(tiered)
    n = sum(len(d) for d in decisions)
    t = time.perf_counter()
    for d in progress_bar(decisions, desc="tiered", disable=quiet, leave=False, file=sys.stderr):
        backend.stable_batch(d)
    tiered_s = time.perf_counter() - t
    stats = backend.stats()
    sim = PyBulletSimulator(PyBulletParams(early_stop=True))
    t = time.perf_counter()
    early_steps = 0
    for d in progress_bar(decisions, desc="early stop", disable=quiet, leave=False, file=sys.stderr):
        for g in d:
            early_steps += sim.check(g).steps
    early_s = time.perf_counter() - t
    sim.close()
    backend.close()
    return {"queries": n, "tiered_per_s": n / tiered_s, "early_stop_per_s": n / early_s,
            "speedup_vs_early_stop": early_s / tiered_s, "tiered_stage_counts": stats,
            "early_stop_mean_steps": early_steps / n}


EDGE_TOWERS = (((1.8, 0.0, 0), (1.8, 0.9, 1)), ((0.6, 0.0, 0), (1.2, -0.3, 1)), ((1.8, 0.0, 0), (0.6, -0.9, 1)))
"""Towers whose upper block's load passes exactly through the lower block's edge."""


def edge_creep(params: PyBulletParams = PyBulletParams()) -> list[dict]:
    """For each of :data:`EDGE_TOWERS`: its largest block speed over time and when it passes the threshold.

    Speed is measured as the early stop measures it (linear speed plus angular
    speed times the block height), after every step of the full window.
    """
    from overhang_framework.geometry import BLOCK_HEIGHT

    out = []
    for rows in EDGE_TOWERS:
        g = Geometry.from_tuples(rows)
        sim = PyBulletSimulator(params)
        p, cid = sim._p, sim._client
        bodies = sim._build(g, None, None)
        start = np.array([[b.x, 0.0, b.z] for b in g.blocks])
        total = int(round(params.duration / params.time_step))
        speed, disp = np.zeros(total), np.zeros(total)
        for k in range(total):
            p.stepSimulation(physicsClientId=cid)
            vel = [p.getBaseVelocity(b, physicsClientId=cid) for b in bodies]
            speed[k] = max(np.linalg.norm(v) + np.linalg.norm(w) * BLOCK_HEIGHT for v, w in vel)
            pos = np.array([p.getBasePositionAndOrientation(b, physicsClientId=cid)[0] for b in bodies])
            disp[k] = np.max(np.linalg.norm(pos - start, axis=1))
        sim.close()
        t = np.arange(1, total + 1) * params.time_step
        early = (t >= 0.1) & (t <= 0.5)
        passed = np.flatnonzero(disp > params.threshold)
        out.append({"tower": [list(r) for r in rows], "speed_0.1_0.5s": [float(speed[early].min()), float(speed[early].max())],
                    "speed_1s": float(speed[np.searchsorted(t, 1.0)]), "speed_2s": float(speed[np.searchsorted(t, 2.0)]),
                    "passes_threshold_s": float(t[passed[0]]) if passed.size else None,
                    "rest_speed": params.rest_speed})
    return out


def chaotic_band(crit: dict, reference: Reference, n: int, seed: int) -> dict:
    """The reference across the flip of ``n`` near-critical towers, and its sensitivity to one ulp of x."""
    rng = np.random.default_rng([seed, 11])
    pool = [(g, off) for fam, rows in crit.items() if fam != "edge" for g, off in rows]
    picks = [pool[i] for i in rng.choice(len(pool), size=min(n, len(pool)), replace=False)]
    steps = np.round(np.arange(-0.01, 0.01001, 0.001), 6)
    scans, widths, changes = [], [], []
    for g, off in picks:
        flip = g.blocks[-1].x - off
        lo, hi = last_block_interval(g)
        xs = np.clip(flip + steps, lo, hi)
        v = reference([with_last_x(g, x) for x in xs])
        flips = np.flatnonzero(v[1:] != v[:-1])
        changes.append(int(flips.size))
        widths.append(float(xs[flips[-1] + 1] - xs[flips[0]]) if flips.size else 0.0)
        scans.append({"tower": [[b.width, b.x, b.layer] for b in g.blocks[:-1]], "flip": float(flip),
                      "verdicts": "".join("S" if s else "F" for s in v)})
    near = [g for g, off in pool if abs(off) < 0.01]
    ulp = [with_last_x(g, float(np.nextafter(g.blocks[-1].x, np.inf))) for g in near]
    a, b = reference(near), reference(ulp)
    return {"scanned": len(picks), "step_m": 0.001, "scan_half_width_m": 0.01,
            "scans_with_several_changes": int(np.sum(np.array(changes) > 1)),
            "mean_changes": float(np.mean(changes)) if changes else None,
            "band_width_m": {"median": float(np.median(widths)) if widths else None,
                             "max": float(np.max(widths)) if widths else None},
            "ulp_towers": len(near), "ulp_flipped": int(np.sum(a != b)),
            "ulp_flipped_share": float(np.mean(a != b)) if near else None, "scans": scans}


def robust_check(placed: Sequence[Geometry], band: Sequence[Geometry], jitters: int, workers: int,
                 reference: Reference) -> dict:
    """Robust verdicts (``jitters`` fixed 1 mm jitters) against the reference."""
    params = replace(reference.params, jitters=jitters)
    out = {"jitters": jitters, "jitter_m": params.jitter}
    with PyBulletPool(workers, params=params, early_stop=False) as pool:
        for name, geoms in (("placed", placed), ("workload_band", band)):
            geoms = list({g.key: g for g in geoms}.values())
            if not geoms:
                continue
            robust = pool.stable_batch(geoms)
            ref = reference(geoms)
            out[name] = {"n": len(geoms), "differ": int(np.sum(robust != ref)),
                         "reference_stable_robust_falls": int(np.sum(ref & ~robust))}
    return out


def run(per_family: int = 100, offsets: int = 3, window: float = 0.02, seed: int = 1, workers: int = 2,
        band: int = 0, robust: int = 0, reference_cache: Optional[str] = None, speed_decisions: int = 100,
        episodes: int = 20, quiet: bool = False) -> dict:
    say = (lambda *a: None) if quiet else (lambda *a: print(*a, file=sys.stderr))
    reference = Reference(workers, path=reference_cache, quiet=quiet)
    tiered = TieredParams()
    statics = {"static_old": OLD_STATIC, "static": StaticParams()}
    try:
        say(f"near-critical families: {per_family} towers each, flips by bisection with the reference")
        crit = near_critical(reference, per_family, seed, window, offsets)
        say(f"planner workloads: the first {episodes} paper20 tasks, myopic, veridical and ipe")
        from overhang_framework.tasks import generate_sequences

        tasks = generate_sequences(20, 6, 2025)[:episodes]
        work = {"veridical": planner_workload("veridical", "static", tasks=tasks),
                "ipe": planner_workload("ipe", "static", tasks=tasks)}
        sets = {f: ([g for g, _ in rows], [o for _, o in rows] if f != "edge" else None) for f, rows in crit.items()}
        sets["all near-critical"] = ([g for f in FAMILIES if f != "edge" for g, _ in crit[f]],
                                     [o for f in FAMILIES if f != "edge" for _, o in crit[f]])
        for name, w in work.items():
            sets[f"{name} candidates"] = (w.candidates, None)
            sets[f"{name} placed"] = (w.placed, None)
        say("reference verdicts and agreement")
        figures = {"families": evaluate(sets, reference, tiered, statics)}
        cand = work["veridical"].candidates
        steps = reference.steps(cand)
        stage = TieredBackend(tiered).classify(cand)
        figures["workload_reference_steps_per_query"] = float(steps[stage < 0].sum() / len(cand))
        placed = work["veridical"].placed + work["ipe"].placed
        backend = TieredBackend(tiered)
        figures["placed_tiered_equals_reference"] = bool(np.array_equal(backend.stable_batch(placed), reference(placed)))
        backend.close()
        say(f"throughput on the first {speed_decisions} decisions of the veridical workload")
        figures["speed"] = throughput(work["veridical"].decisions[:speed_decisions], tiered, quiet)
        if band:
            say(f"chaotic band: {band} scans")
            figures["chaotic_band"] = chaotic_band(crit, reference, band, seed)
        if robust:
            say(f"robust verdicts with {robust} jitters")
            near = [g for w in work.values() for g, s in zip(w.candidates, TieredBackend(tiered).classify(w.candidates))
                    if s < 0]
            figures["robust"] = robust_check(placed, near, robust, workers, reference)
        figures.update({"per_family": per_family, "offsets": offsets, "window": window, "seed": seed,
                        "workers": workers, "reference_runs": reference.runs,
                        "tiered_params": asdict(tiered), "static_params": asdict(StaticParams()),
                        "static_old_params": asdict(OLD_STATIC)})
        from overhang_framework.bench.physics import machine

        figures["machine"] = machine()
    finally:
        reference.save()
        reference.close()
    return figures


def table(f: dict) -> str:
    lines = ["set                          n     ref stable  stages (stable/fall/reference)  tiered   static old  static"]
    for name, r in f["families"].items():
        s = r["stages"]
        lines.append(f"{name:<26} {r['tiered']['n']:>5}  {r['reference_stable']:>9.2f}   "
                     f"{s['static_stable']:.3f} / {s['static_fall']:.3f} / {s['reference']:.3f}      "
                     f"{r['tiered']['agreement']:.4f}   {r['static_old']['agreement']:.4f}      {r['static']['agreement']:.4f}")
    lines += ["", "by distance to the flip (all near-critical)   n     tiered   static old  static"]
    for k, d in f["families"].get("all near-critical", {}).get("by_distance", {}).items():
        lines.append(f"  {k:<42} {d['n']:>4}  {d['tiered']:.4f}   {d['static_old']:.4f}      {d['static']:.4f}")
    sp = f["speed"]
    lines += ["", f"planner workload ({sp['queries']} queries, one process, no cache): tiered {sp['tiered_per_s']:.0f}/s, "
                  f"early stop {sp['early_stop_per_s']:.1f}/s, speed-up {sp['speedup_vs_early_stop']:.1f}x",
              f"  reference steps per query {f['workload_reference_steps_per_query']:.1f} (early stop: "
              f"{sp['early_stop_mean_steps']:.1f})"]
    if f.get("chaotic_band"):
        c = f["chaotic_band"]
        lines += [f"chaotic band: {c['scans_with_several_changes']} of {c['scanned']} scans change verdict more than once; "
                  f"band width median {100 * c['band_width_m']['median']:.2f} cm, max {100 * c['band_width_m']['max']:.2f} cm; "
                  f"one ulp of x flips {c['ulp_flipped']} of {c['ulp_towers']} verdicts within 1 cm"]
    if f.get("robust"):
        r = f["robust"]
        lines += [f"robust ({r['jitters']} jitters of {1000 * r['jitter_m']:g} mm): "
                  + ", ".join(f"{k} {v['differ']} of {v['n']} differ" for k, v in r.items() if isinstance(v, dict))]
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.agreement",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-family", type=int, default=100, help="towers drawn per family (default 100)")
    ap.add_argument("--offsets", type=int, default=3, help="offsets per flip (default 3)")
    ap.add_argument("--window", type=float, default=0.02, help="offsets within this of the flip, m (default 0.02)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 2)
    ap.add_argument("--band", type=int, default=0, metavar="N", help="scan the reference across N flips")
    ap.add_argument("--robust", type=int, default=0, metavar="K", help="robust verdicts with K jitters")
    ap.add_argument("--speed-decisions", type=int, default=100, help="decisions timed (default 100: all)")
    ap.add_argument("--reference-cache", metavar="FILE", help="keep reference verdicts in FILE between runs")
    ap.add_argument("--creep-only", action="store_true", help="only measure how edge-balanced towers creep")
    ap.add_argument("--episodes", type=int, default=20, help="paper20 tasks played for the workloads (default 20)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 4 towers per family, 2 episodes, 5 decisions")
    ap.add_argument("--out", help="also write the JSON figures to this file")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    if args.creep_only:
        creep = edge_creep()
        if not args.quiet:
            for c in creep:
                lo, hi = c["speed_0.1_0.5s"]
                print(f"{c['tower']}: speed {lo:.2e}-{hi:.2e} m/s between 0.1 and 0.5 s (rest_speed {c['rest_speed']:g}), "
                      f"{c['speed_1s']:.1e} at 1 s, {c['speed_2s']:.1e} at 2 s, passes the threshold at {c['passes_threshold_s']:.2f} s")
        print(json.dumps({"edge_creep": creep}))
        return 0
    if args.quick:
        args.per_family, args.offsets, args.speed_decisions = min(args.per_family, 4), 1, min(args.speed_decisions, 5)
        args.episodes = min(args.episodes, 2)
    figures = run(args.per_family, args.offsets, args.window, args.seed, args.workers, args.band, args.robust,
                  args.reference_cache, args.speed_decisions, args.episodes, args.quiet)
    if args.out:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(args.out, figures)
    if not args.quiet:
        print(table(figures))
    print(json.dumps({k: v for k, v in figures.items() if k != "chaotic_band"}
                     | {"chaotic_band": {k: v for k, v in figures.get("chaotic_band", {}).items() if k != "scans"}}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

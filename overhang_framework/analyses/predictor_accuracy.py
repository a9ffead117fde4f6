"""Accuracy of predictors against the reference physics by number of blocks: where should the hybrid switch?

Questions are episode-like (:func:`overhang_framework.physics.towers.episode_questions`):
a tower whose every prefix stands by the reference, plus one more block of a
random width at a uniformly random legal action on the world's 0.1 grid, as a
planner scores it. For ``n`` = 2 to 7 blocks after the action, ``--towers``
questions each. Every predictor named in ``--predictors`` (registered names,
built from their config files' defaults; the IPE on its default static
backend) gives ``p`` per question, and per predictor and number of blocks the
CSV reports ``accuracy`` (``p > 0.5`` matches the reference; ``p = 0.5``
counts one half), ``p_correct`` (mean probability given to the reference
verdict) and ``log_likelihood`` (mean ``log p`` of the reference verdict,
``p`` clipped to [0.01, 0.99]), each with its standard error.

The first number of blocks from which the second predictor's accuracy is at
least the first's (and stays so) is printed as the suggested switch point.

    python -m overhang_framework.analyses.predictor_accuracy --out docs/figures
    python -m overhang_framework.analyses.predictor_accuracy --out /tmp/acc --quick
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.analyses.ipe_mechanism import chunked, to_csv
from overhang_framework.analyses.plots import plot_by_blocks
from overhang_framework.physics.towers import episode_questions
from overhang_framework.physics.factory import make_backend
from overhang_framework.results import atomic_write_json, atomic_write_text, mean_sem


def summarize(rows: list[dict], predictors: Sequence[str]) -> list[dict]:
    out = []
    for name in predictors:
        for n in sorted({r["n_blocks"] for r in rows}):
            sel = [r for r in rows if r["n_blocks"] == n]
            p = np.array([r[f"p_{name}"] for r in sel])
            ref = np.array([r["reference_stable"] for r in sel], dtype=bool)
            correct = np.where(p == 0.5, 0.5, ((p > 0.5) == ref).astype(float))
            pc = np.where(ref, p, 1 - p)
            row = {"predictor": name, "n_blocks": n, "towers": len(sel), "stable_rate": float(ref.mean())}
            for key, values in (("accuracy", correct), ("p_correct", pc),
                                ("log_likelihood", np.log(np.clip(pc, 0.01, 0.99)))):
                row[key], row[f"{key}_sem"] = mean_sem(values)
            out.append(row)
    return out


def switch_point(summary: list[dict], early: str, late: str) -> Optional[int]:
    """Smallest block count from which ``late`` is at least as accurate as ``early`` at every larger count."""
    acc = {(r["predictor"], r["n_blocks"]): r["accuracy"] for r in summary}
    counts = sorted({r["n_blocks"] for r in summary})
    for i, n in enumerate(counts):
        if all(acc[(late, m)] >= acc[(early, m)] for m in counts[i:]):
            return n
    return None


def plot(summary: list[dict], path: Path, title: str) -> None:
    """Accuracy and log-likelihood against the number of blocks, one line per predictor."""
    plot_by_blocks(summary, path, title, series="predictor",
                   panels=[("accuracy", "accuracy vs reference verdict"),
                           ("log_likelihood", "mean log p(reference verdict)")])


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.analyses.predictor_accuracy",
                                 description="Accuracy of predictors against the reference by number of blocks.")
    ap.add_argument("--out", required=True, type=Path, help="output directory")
    ap.add_argument("--towers", type=int, default=200, help="questions per number of blocks (default 200)")
    ap.add_argument("--predictors", default="ipe,cnn",
                    help="comma-separated registered predictor names; the first two decide the switch point")
    ap.add_argument("--reference", choices=("tiered", "pybullet", "static"), default="tiered",
                    help="physics giving the reference verdicts (default tiered: the full-window PyBullet's)")
    ap.add_argument("--workers", type=int, default=1, help="PyBullet processes for the reference (default 1)")
    ap.add_argument("--min-blocks", type=int, default=2)
    ap.add_argument("--max-blocks", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true", help="smoke run: 15 towers per count, static reference")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    args = ap.parse_args(argv)
    if args.quick:
        args.towers, args.reference = 15, "static"
    args.names = [s.strip() for s in args.predictors.split(",") if s.strip()]
    from overhang_framework.plugins import Registry

    known = Registry().names("predictor")
    bad = [n for n in args.names if n not in known]
    if bad or not args.names:
        ap.error(f"--predictors: unknown predictor(s) {', '.join(bad) or '(none given)'}; allowed: {', '.join(known)}")
    for name in ("towers", "workers"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be a whole number >= 1, got {getattr(args, name)}")
    if not 2 <= args.min_blocks <= args.max_blocks:
        ap.error(f"need 2 <= --min-blocks <= --max-blocks, got {args.min_blocks} and {args.max_blocks}")
    return args


def main(argv: Optional[Sequence[str]] = None) -> dict:
    from overhang_framework.progress import progress_bar

    from overhang_framework.config import compose_config
    from overhang_framework.plugins import Registry

    args = parse_args(argv)
    started = time.perf_counter()
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static", "cache": False})
    reference = make_backend(args.reference, workers=args.workers)
    levels = args.max_blocks - 1
    with progress_bar(total=2 * args.towers * levels, desc=f"reference ({args.reference})", unit="tower",
              disable=args.no_progress, file=sys.stderr) as bar:
        questions = episode_questions(chunked(reference.stable_batch, 100, bar), args.towers, seed=args.seed,
                                      min_blocks=args.min_blocks, max_blocks=args.max_blocks,
                                      resolution=world.resolution)
    close = getattr(reference, "close", None)
    if close:
        close()
    rows = [{"n_blocks": q.n_blocks, "index": q.index, "reference_stable": int(q.stable),
             "tower": json.dumps([list(b) for b in q.geometry.key])} for q in questions]
    seconds = {}
    for name in args.names:
        params = dict(compose_config([f"predictor={name}"]).predictor)
        predictor = registry.create("predictor", params, world=world)
        t0 = time.perf_counter()
        for row, q in progress_bar(list(zip(rows, questions)), desc=name, unit="question", disable=args.no_progress,
                           file=sys.stderr):
            rng = np.random.default_rng([args.seed, 1, q.n_blocks, q.index])
            row[f"p_{name}"] = float(predictor.predict(q.state, [q.action], rng)[0])
        seconds[name] = time.perf_counter() - t0
    summary = summarize(rows, args.names)
    switch = switch_point(summary, args.names[0], args.names[1]) if len(args.names) >= 2 else None
    out = args.out
    written = [out / "predictor_accuracy.csv", out / "predictor_accuracy_towers.csv", out / "predictor_accuracy.png",
               out / "predictor_accuracy.json"]
    atomic_write_text(written[0], to_csv(summary))
    atomic_write_text(written[1], to_csv(rows))
    plot(summary, written[2], f"{', '.join(args.names)} vs {args.reference} reference; "
                              f"{args.towers} episode-like questions per point, seed {args.seed}")
    meta = {"argv": list(argv) if argv is not None else sys.argv[1:], "towers": args.towers,
            "predictors": args.names, "reference": args.reference, "seed": args.seed,
            "switch_point": switch, "predictor_seconds": seconds, "seconds": time.perf_counter() - started}
    atomic_write_json(written[3], {"meta": meta, "summary": summary})
    print(f"{'predictor':>10} {'blocks':>6} {'n':>4} {'stable':>6} {'accuracy':>14} {'log p':>14}")
    for r in summary:
        print(f"{r['predictor']:>10} {r['n_blocks']:>6d} {r['towers']:>4d} {r['stable_rate']:>6.2f} "
              f"{r['accuracy']:>7.3f}±{r['accuracy_sem']:<6.3f} {r['log_likelihood']:>7.3f}±{r['log_likelihood_sem']:<6.3f}")
    if len(args.names) >= 2:
        print(f"{args.names[1]} is at least as accurate as {args.names[0]} from {switch} blocks on"
              if switch is not None else f"{args.names[1]} never stays at least as accurate as {args.names[0]}")
    print(f"wrote {', '.join(map(str, written))} in {meta['seconds']:.0f} s")
    return {"meta": meta, "summary": summary}


if __name__ == "__main__":
    main()

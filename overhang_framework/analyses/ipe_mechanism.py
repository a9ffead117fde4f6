"""How the IPE's predictive entropy and accuracy change with the number of blocks.

The paper (Results, "Physical Prediction Mechanism Switching") argues that the
IPE's position noise propagates up the stack, so its stability estimates grow
more diffuse and less informative as the tower grows. This command measures
that on our own physics.

Questions are episode-like: a tower whose every prefix stands (by the
reference physics) plus one more block of a random width at a uniformly random
legal action (x on the world's 0.1 grid), as a planner would score it. For
``n`` = 2 to 7 blocks after the action, ``--towers`` questions are drawn: the
towers of ``n - 1`` blocks are grown level by level, each level extending
randomly chosen standing towers of the level below. Each question gets the
reference verdict and, for every sigma, the IPE's probability ``p`` (``K``
simulations; one seeded generator per question, so every sigma sees the same
standard-normal draws). Per number of blocks and sigma the CSV reports:

* ``entropy``: mean binary entropy of ``p``, bits (0 = certain, 1 = p = 0.5);
* ``accuracy``: fraction of questions where ``p > 0.5`` matches the reference
  verdict (``p = 0.5`` counts one half);
* ``p_correct``: mean probability the IPE gives to the reference verdict;
* ``uncertain``: fraction of questions with ``0.1 < p < 0.9``;

each with its standard error, and ``stable_rate``, the reference's base rate.

    python -m overhang_framework.analyses.ipe_mechanism --out results/ipe_mechanism
    python -m overhang_framework.analyses.ipe_mechanism --out /tmp/ipe_quick --quick
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.analyses.plots import plot_by_blocks
from overhang_framework.physics.factory import make_backend
from overhang_framework.results import atomic_write_json, atomic_write_text, mean_sem
from overhang_framework.physics.towers import Verdicts, episode_questions


def binary_entropy(p: np.ndarray) -> np.ndarray:
    """Entropy of Bernoulli(p) in bits, 0 at p = 0 and p = 1."""
    p = np.asarray(p, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        h = -(p * np.log2(p) + (1 - p) * np.log2(1 - p))
    return np.where((p <= 0) | (p >= 1), 0.0, h)


def summarize(rows: list[dict]) -> list[dict]:
    """One summary row per (sigma, n_blocks) from the per-question rows."""
    out = []
    keys = sorted({(r["sigma"], r["n_blocks"]) for r in rows})
    for sigma, n in keys:
        sel = [r for r in rows if r["sigma"] == sigma and r["n_blocks"] == n]
        p = np.array([r["p"] for r in sel])
        ref = np.array([r["reference_stable"] for r in sel], dtype=bool)
        correct = np.where(p == 0.5, 0.5, ((p > 0.5) == ref).astype(float))
        row = {"sigma": sigma, "n_blocks": n, "towers": len(sel), "stable_rate": float(ref.mean())}
        for name, values in (("entropy", binary_entropy(p)), ("accuracy", correct),
                             ("p_correct", np.where(ref, p, 1 - p)),
                             ("uncertain", ((p > 0.1) & (p < 0.9)).astype(float))):
            row[name], row[f"{name}_sem"] = mean_sem(values)
        out.append(row)
    return out


def to_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for r in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()})
    return buf.getvalue()


def plot(summary: list[dict], path: Path, title: str) -> None:
    """Entropy and accuracy against the number of blocks, one line per sigma, saved atomically."""
    plot_by_blocks(sorted(summary, key=lambda r: r["sigma"]), path, title, series="sigma",
                   panels=[("entropy", "mean predictive entropy (bits)"),
                           ("accuracy", "accuracy vs reference verdict")],
                   label=lambda sigma: f"sigma = {sigma:g}", colormap="viridis")


def chunked(fn: Verdicts, size: int, bar) -> Verdicts:
    """``fn`` called on chunks of at most ``size`` geometries, advancing ``bar`` after each."""

    def run(geometries):
        geometries = list(geometries)
        out = []
        for i in range(0, len(geometries), size):
            part = geometries[i:i + size]
            out.append(np.asarray(fn(part), dtype=bool))
            bar.update(len(part))
        return np.concatenate(out) if out else np.zeros(0, dtype=bool)

    return run


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(
        prog="python -m overhang_framework.analyses.ipe_mechanism",
        description="IPE predictive entropy and accuracy by number of blocks, for several sigmas.",
    )
    ap.add_argument("--out", required=True, type=Path, help="output directory")
    ap.add_argument("--towers", type=int, default=200, help="questions per number of blocks (default 200)")
    ap.add_argument("--sigmas", default="0,0.01,0.03,0.1",
                    help="comma-separated sigmas (default 0,0.01,0.03,0.1)")
    ap.add_argument("--channel", choices=("all", "position", "gravity", "friction"), default="all",
                    help="perturb every channel with sigma (all, the paper's) or only this one")
    ap.add_argument("--K", type=int, default=50, help="simulations per question (default 50)")
    ap.add_argument("--backend", choices=("static", "pybullet"), default="static",
                    help="physics the IPE simulates with (default static)")
    ap.add_argument("--reference", choices=("static", "pybullet"), default="pybullet",
                    help="physics giving the reference verdicts (default pybullet)")
    ap.add_argument("--workers", type=int, default=2, help="PyBullet processes (default 2)")
    ap.add_argument("--min-blocks", type=int, default=2)
    ap.add_argument("--max-blocks", type=int, default=7)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: 20 towers, sigmas 0,0.03,0.1, K=20, static reference")
    ap.add_argument("--no-progress", action="store_true", help="hide the progress bars")
    args = ap.parse_args(argv)
    if args.quick:
        args.towers, args.sigmas, args.K, args.reference = 20, "0,0.03,0.1", 20, "static"
    try:
        args.sigma_list = [float(s) for s in args.sigmas.split(",") if s.strip()]
    except ValueError:
        ap.error(f"--sigmas must be comma-separated numbers, got {args.sigmas!r}")
    for name in ("towers", "K", "workers"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} must be a whole number >= 1, got {getattr(args, name)}")
    if any(s < 0 for s in args.sigma_list) or not args.sigma_list:
        ap.error(f"--sigmas must be numbers >= 0, got {args.sigmas!r}")
    if not 2 <= args.min_blocks <= args.max_blocks:
        ap.error(f"need 2 <= --min-blocks <= --max-blocks, got {args.min_blocks} and {args.max_blocks}")
    from overhang_framework.errors import OverhangError
    from overhang_framework.preflight import check_writable

    try:
        check_writable(args.out, "--out DIR")
    except OverhangError as err:
        ap.error(str(err))
    return args


def predictor_params(sigma: float, channel: str, K: int, backend: str) -> dict:
    params = {"name": "ipe", "K": K, "backend": backend, "sigma": sigma if channel == "all" else 0.0}
    if channel != "all":
        params[f"sigma_{channel}"] = sigma
    return params


def main(argv: Optional[Sequence[str]] = None) -> dict:
    from overhang_framework.progress import progress_bar

    from overhang_framework.plugins import Registry

    args = parse_args(argv)
    started = time.perf_counter()
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "cache": False})
    reference = make_backend(args.reference, workers=args.workers)
    levels = args.max_blocks - 1
    with progress_bar(total=2 * args.towers * levels, desc=f"reference ({args.reference})", unit="tower",
              disable=args.no_progress, file=sys.stderr) as bar:
        questions = episode_questions(chunked(reference.stable_batch, 100, bar), args.towers,
                                      seed=args.seed, min_blocks=args.min_blocks,
                                      max_blocks=args.max_blocks, resolution=world.resolution)
    ipe_backend = reference if args.backend == args.reference else make_backend(args.backend, workers=args.workers)
    rows: list[dict] = []
    chunk = 50
    with progress_bar(total=len(args.sigma_list) * len(questions), desc="IPE", unit="question",
              disable=args.no_progress, file=sys.stderr) as bar:
        for sigma in args.sigma_list:
            params = predictor_params(sigma, args.channel, args.K, args.backend)
            params["backend"] = ipe_backend
            ipe = registry.create("predictor", params, world=world)
            for start in range(0, len(questions), chunk):
                part = questions[start:start + chunk]
                scenes = [ipe.scenes(q.state, [q.action],
                                     np.random.default_rng([args.seed, 1, q.n_blocks, q.index]))
                          for q in part]
                for q, verdicts in zip(part, ipe.run(scenes)):
                    rows.append({"sigma": sigma, "n_blocks": q.n_blocks, "index": q.index,
                                 "reference_stable": int(q.stable), "p": float(verdicts.mean()),
                                 "tower": json.dumps([list(b) for b in q.geometry.key])})
                bar.update(len(part))
    for physics in {id(reference): reference, id(ipe_backend): ipe_backend}.values():
        close = getattr(physics, "close", None)
        if close:
            close()
    summary = summarize(rows)
    out = args.out
    written = [out / "ipe_mechanism.csv", out / "ipe_mechanism_towers.csv", out / "ipe_mechanism.png",
               out / "ipe_mechanism.json"]
    atomic_write_text(written[0], to_csv(summary))
    atomic_write_text(written[1], to_csv(rows))
    title = (f"IPE ({args.backend}, K={args.K}, channel={args.channel}) vs {args.reference} reference; "
             f"{args.towers} towers per point, seed {args.seed}")
    plot(summary, written[2], title)
    meta = {"argv": list(argv) if argv is not None else sys.argv[1:], "towers": args.towers,
            "sigmas": args.sigma_list, "channel": args.channel, "K": args.K, "backend": args.backend,
            "reference": args.reference, "seed": args.seed, "seconds": time.perf_counter() - started}
    atomic_write_json(written[3], {"meta": meta, "summary": summary})
    print(format_table(summary))
    print(f"wrote {', '.join(map(str, written))} in {meta['seconds']:.0f} s")
    return {"meta": meta, "summary": summary}


def format_table(summary: list[dict]) -> str:
    lines = [f"{'sigma':>6} {'blocks':>6} {'n':>4} {'stable':>6} {'entropy':>14} {'accuracy':>14} "
             f"{'p_correct':>9} {'uncertain':>9}"]
    for r in summary:
        lines.append(f"{r['sigma']:>6g} {r['n_blocks']:>6d} {r['towers']:>4d} {r['stable_rate']:>6.2f} "
                     f"{r['entropy']:>7.3f}±{r['entropy_sem']:<6.3f} {r['accuracy']:>7.3f}±{r['accuracy_sem']:<6.3f} "
                     f"{r['p_correct']:>9.3f} {r['uncertain']:>9.3f}")
    return "\n".join(lines)


if __name__ == "__main__":
    main()

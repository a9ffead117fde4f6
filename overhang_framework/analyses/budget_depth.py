"""Budgets truncate search: depth reached and reward as the per-placement budget shrinks.

The paper's central claim is that time pressure truncates deliberative
lookahead. Here it is made mechanical: the lookahead planner deepens
iteratively (depth 1, 2, ... up to ``--depth``) and plays the best action of the
deepest depth it completed when the budget of predictor calls per placement
runs out. Every task of the task set is played once per budget, with the same
seed, and the command reports per budget:

* ``depth``: mean search depth completed per placement (its SEM over placements);
* ``reward``: mean terminal reward (SEM over episodes);
* ``calls``: mean predictor calls per placement;
* ``truncated``: share of placements whose budget ran out before the full depth.

It writes ``budget_depth.csv``, ``budget_depth.json`` and ``budget_depth.png``
into ``--out``. The budget is in predictor calls rather than seconds, so the
figure is the same on every machine and reproducible by seed.

    python -m overhang_framework.analyses.budget_depth --out results/budget_depth
    python -m overhang_framework.analyses.budget_depth --out /tmp/bd --quick world.physics=static
"""

from __future__ import annotations

import argparse
import csv
import io
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from overhang_framework.results import atomic_output, atomic_write_json, atomic_write_text, mean_sem

BUDGETS = (1, 2, 4, 8, 16, 32, 64, 128, None)
QUICK_BUDGETS = (1, 4, 16, None)


def run(overrides: Sequence[str], budgets: Sequence[Optional[int]], depth: int, seed: int,
        quiet: bool = False) -> list[dict]:
    """One row per budget, from every task of the composed config played once with that budget."""
    from overhang_framework.progress import progress_bar

    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.episode import episode_rng, run_episode
    from overhang_framework.tasks import tasks_from_config

    cfg = compose_config([*overrides, "planner=lookahead", f"planner.depth={depth}"])
    models = build_models(cfg)
    tasks = tasks_from_config(cfg.tasks)
    rows = []
    bar = progress_bar(total=len(budgets) * len(tasks), desc="episodes", unit="ep", disable=quiet, file=sys.stderr)
    for budget in budgets:
        rewards, depths, calls, truncated = [], [], [], []
        started = time.perf_counter()
        for i, task in enumerate(tasks):
            record = run_episode(task, models["world"], models["predictor"], models["planner"], models["value"],
                                 episode_rng(seed, i, 0), call_limit=budget)
            rewards.append(record["reward"])
            for step in record["steps"]:
                depths.append(step["spend"]["depth_completed"])
                calls.append(step["spend"]["predictor_calls"])
                remaining = len(task.sequence) - 1 - record["steps"].index(step)
                truncated.append(step["spend"]["depth_completed"] < min(depth, remaining))
            bar.update(1)
        d, d_sem = mean_sem(depths)
        r, r_sem = mean_sem(rewards)
        rows.append({"budget": "none" if budget is None else budget, "depth": d, "depth_sem": d_sem,
                     "reward": r, "reward_sem": r_sem, "calls": float(np.mean(calls)),
                     "truncated": float(np.mean(truncated)), "episodes": len(rewards),
                     "seconds": time.perf_counter() - started})
    bar.close()
    return rows


def figure(rows: list[dict], depth: int, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [str(r["budget"]) for r in rows]
    x = np.arange(len(rows))
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
    ax1.errorbar(x, [r["depth"] for r in rows], yerr=[r["depth_sem"] or 0 for r in rows], marker="o")
    ax1.set_ylabel("mean depth completed")
    ax1.set_ylim(0.8, depth + 0.2)
    ax2.errorbar(x, [r["reward"] for r in rows], yerr=[r["reward_sem"] or 0 for r in rows], marker="o",
                 color="tab:orange")
    ax2.set_ylabel("mean terminal reward")
    for ax in (ax1, ax2):
        ax.set_xticks(x, labels)
        ax.set_xlabel("predictor calls per placement")
        ax.grid(alpha=0.3)
    fig.suptitle(f"Lookahead (D = {depth}) under a shrinking budget")
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def to_csv(rows: list[dict]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in row.items()})
    return buf.getvalue()


def table(rows: list[dict]) -> str:
    lines = [f"{'budget':>8}{'depth':>14}{'reward':>16}{'calls':>8}{'truncated':>11}"]
    for r in rows:
        lines.append(f"{r['budget']!s:>8}{r['depth']:>8.2f} ± {r['depth_sem'] or 0:.2f}"
                     f"{r['reward']:>9.3f} ± {r['reward_sem'] or 0:.3f}{r['calls']:>8.1f}{r['truncated']:>11.2f}")
    return "\n".join(lines)


def main(argv: Optional[Sequence[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.analyses.budget_depth",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("overrides", nargs="*", help="config overrides, as for the main job")
    parser.add_argument("--out", required=True, help="directory for the CSV, JSON and figure")
    parser.add_argument("--depth", type=int, default=3, help="lookahead depth (default 3)")
    parser.add_argument("--budgets", default=None,
                        help="comma-separated predictor-call budgets, 'none' for no limit "
                             f"(default {','.join(str(b).lower() for b in BUDGETS)})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="four budgets on the first five tasks")
    args = parser.parse_args(argv)
    try:
        if args.depth < 1:
            raise ValueError(f"--depth must be a whole number >= 1, got {args.depth}")
        if args.budgets:
            budgets = [None if b.strip().lower() == "none" else int(b) for b in args.budgets.split(",")]
        else:
            budgets = list(QUICK_BUDGETS if args.quick else BUDGETS)
        if any(b is not None and b < 1 for b in budgets):
            raise ValueError(f"--budgets must be whole numbers >= 1 or 'none', got {args.budgets}")
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    overrides = list(args.overrides)
    if args.quick and not any(o.startswith("tasks.only") for o in overrides):
        overrides.append("tasks.only=[paper00,paper01,paper02,paper03,paper04]")
    from overhang_framework.errors import OverhangError
    from overhang_framework.preflight import check_command_line, check_writable

    try:
        check_command_line([*overrides, "--cfg", "job"])
        check_writable(args.out, "--out DIR")
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    out = Path(args.out)
    rows = run(overrides, budgets, args.depth, args.seed)
    atomic_write_text(out / "budget_depth.csv", to_csv(rows))
    atomic_write_json(out / "budget_depth.json", {"overrides": overrides, "depth": args.depth, "seed": args.seed,
                                                  "rows": rows})
    figure(rows, args.depth, out / "budget_depth.png")
    print(table(rows))
    print(f"written: {out / 'budget_depth.csv'}, {out / 'budget_depth.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

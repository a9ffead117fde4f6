"""The benchmark's leaderboard: one row per agent and split, with the command that recreates it.

``overhang_framework/data/leaderboard.csv`` holds, per row, the agent, the split, the score with its
95% interval, the share of towers that stood, the mean raw reward, the area under the
score-against-compute curve (with a ladder), the compute spent per decision, the command, and the
framework's version and commit and the date the row was scored::

    python -m overhang_framework.benchmark.leaderboard add runs/bench/d2-ipe     # a finished run's row
    python -m overhang_framework.benchmark.leaderboard show                      # the table, in Markdown
    python -m overhang_framework.benchmark.leaderboard figure --out docs/figures/benchmark.png
    python -m overhang_framework.benchmark.leaderboard rerun --out runs/leaderboard --add  # every row again, timed

A row is replaced when a run of the same agent and split is added again (a run with a budget ladder and
one without are different rows).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.benchmark.board import (  # noqa: F401  (the board's names, importable from here as before)
    COLUMNS,
    DATA_FILE,
    NO_CALLS,
    SPLITS,
    add,
    check_split,
    command_of,
    figure,
    load,
    markdown,
    row_of,
)


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.benchmark.leaderboard",
                                 description="Add finished benchmark runs to the leaderboard, show it, draw it, run it again.")
    sub = ap.add_subparsers(dest="what", required=True)
    a = sub.add_parser("add", help="add the rows of finished runs")
    a.add_argument("runs", nargs="+", help="run directories (each with summary.json)")
    a.add_argument("--agent", help="the name to show (default: the run's own)")
    s = sub.add_parser("show", help="print the table in Markdown")
    s.add_argument("--split", default=None)
    s.add_argument("--commands", action="store_true", help="also list the command that recreates each row")
    f = sub.add_parser("figure", help="draw score against compute for one split")
    f.add_argument("--out", required=True)
    f.add_argument("--split", default="test")
    r = sub.add_parser("rerun", help="run every row's command again, timed, in resumable sittings")
    r.add_argument("--out", required=True, help="a directory for the rows' runs and their timing.json")
    r.add_argument("--split", default=None, help="only this split's rows")
    r.add_argument("--agent", action="append", default=[], help="only this agent's rows (repeatable)")
    r.add_argument("--jobs", type=int, default=None, help="episodes played at once in each row (default: the cores)")
    r.add_argument("--verdicts", default=None, help="the reference's verdict cache (default OUT/verdicts.sqlite, "
                   "so the table is timed from a cold start)")
    r.add_argument("--add", action="store_true", help="put each finished row into the leaderboard")
    r.add_argument("--untimed", action="store_true", help="only the rows without a wall time (a table re-run in part "
                   "elsewhere, its directory gone, goes on with the rest)")
    r.add_argument("--dry-run", action="store_true", help="print the commands and what is done, run nothing")
    r.add_argument("--report", action="store_true", help="print the rows' wall times so far, run nothing")
    for p in (a, s, f, r):
        p.add_argument("--file", default=str(DATA_FILE), help=f"the leaderboard (default {DATA_FILE})")
    args = ap.parse_args(argv)
    try:
        check_split(getattr(args, "split", None))
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.what == "add":
        try:
            rows = [row_of(Path(r), args.agent) for r in args.runs]
        except (FileNotFoundError, KeyError, ValueError) as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        add(rows, args.file)
        for r in rows:
            print(f"{r['agent']} on {r['split']}: {r['score']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]")
    elif args.what == "show":
        board = load(args.file)
        print(markdown(board, args.split))
        if args.commands:
            print()
            for _, r in board.iterrows():
                if not args.split or r["split"] == args.split:
                    print(f"- {r['agent']} ({r['split']}): `{r['command']}`")
    elif args.what == "rerun":
        from overhang_framework.benchmark.rerun import rerun

        try:
            return rerun(Path(args.file), Path(args.out), args.split, args.agent, args.jobs, args.verdicts, args.add,
                         args.dry_run, args.report, args.untimed)
        except ValueError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"interrupted: every finished episode is kept under {args.out}; run the same command again to "
                  "continue", file=sys.stderr)
            return 130
    else:
        figure(load(args.file), Path(args.out), args.split)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

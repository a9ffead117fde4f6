"""``python -m overhang_framework.study``: the studies' command line."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional, Sequence


from overhang_framework.errors import OverhangError
from overhang_framework import studies
from overhang_framework.studies.findings import STUDIES
from overhang_framework.studies.run import run



def _quoted(word: str) -> str:
    import shlex

    return shlex.quote(str(word))


def parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.study", description=studies.__doc__.split("\n\n")[0])
    ap.add_argument("study", help=f"one of: {', '.join(STUDIES)}")
    ap.add_argument("--out", required=True, help="the study's directory")
    ap.add_argument("--scale", type=float, default=1.0, help="participants per condition, share of the paper's 43 + 38")
    ap.add_argument("--pool", type=float, default=2.0,
                    help="simulate this many times the study's participants, to redraw studies from (default 2)")
    ap.add_argument("--tasks", type=int, default=None, help="tasks per participant (default: all 20)")
    ap.add_argument("--depths", default="1,2", help="fitted depths (default 1,2)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--resamples", type=int, default=1000,
                    help="redrawn studies for power (default 1000: each power within 0.016; 0: none)")
    ap.add_argument("--replicas", type=int, default=39, help="predictive check replicas (default 39; 0: no check)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--world", action="append", default=[], metavar="OVERRIDE", help="world override, every step")
    ap.add_argument("--participants", action="append", default=[], metavar="OVERRIDE",
                    help="participants override (repeatable)")
    ap.add_argument("--fit", action="append", default=[], metavar="OVERRIDE", help="fit override (repeatable)")
    ap.add_argument("--sim", action="append", default=[], metavar="DIR",
                    help="take the participants of this finished simulation of the study's cohort (or of another "
                         "whose participants are the study's people) instead of simulating (repeatable, e.g. one "
                         "run a condition); power is then a bootstrap")
    ap.add_argument("--log", action="append", default=[], metavar="LOG",
                    help="analyse people: a behaviour log of the study's participants (an export: JSON Lines, CSV or a "
                         "Psych-DS folder; repeatable) instead of simulating any; power is then a bootstrap of them")
    ap.add_argument("--no-fit", action="store_true", help="leave out the fit and the findings that need it")
    ap.add_argument("--no-progress", action="store_true")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(argv)
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    try:
        depths = [int(d) for d in args.depths.split(",") if d.strip()]
    except ValueError:
        print(f"error: --depths must be whole numbers separated by commas, got {args.depths!r}", file=sys.stderr)
        return 2
    try:
        summary = run(args.study, Path(args.out), args.scale, args.pool, args.tasks, args.jobs, depths, args.resamples,
                      args.replicas, args.seed, args.world, args.participants, args.fit, not args.no_progress, say,
                      args.sim, not args.no_fit, args.log,
                      " ".join(["python -m overhang_framework.study", *map(_quoted, argv if argv is not None else sys.argv[1:])]))
    except OverhangError as err:
        print(f"error: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: each finished step and part is kept; run the same command to continue", file=sys.stderr)
        return 130
    print(summary["report"].split("\n## ")[0].strip())
    print(f"\nwrote {Path(summary['out']) / 'study.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Every behaviour analysis of logs: ``python -m overhang_framework.analyze LOG [LOG ...] --out DIR``.

Table 1, order dependency Γ (Fig. 3b), trajectory flows (Fig. 3a) and physical prediction by
construction stage (Fig. 4) of behaviour logs (people, simulated participants, converted model
runs), written to ``DIR/report.md`` with one CSV per table and one PNG per figure. The analyses
themselves are in :mod:`overhang_framework.behaviour.analysis`; docs/analyses.md describes them.
"""

from __future__ import annotations

import argparse
import sys
from typing import Optional, Sequence

from overhang_framework.behaviour.analysis import ANALYSES, GAMMA_TOWERS, Settings

EXAMPLES = """examples:
  python -m overhang_framework.analyze people.jsonl --out results/behaviour
  python -m overhang_framework.analyze people.jsonl models.jsonl --out results/all --world world.physics=static
  python -m overhang_framework.analyze people.jsonl --out results/final --gamma-towers final
  python -m overhang_framework.analyze log.jsonl --out out --compare unconstrained veridical-myopic \\
      --predictors veridical,ipe --only table1,prediction --n-resamples 2000
"""


def parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.analyze", description=__doc__.split("\n\n")[0],
                                 epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("logs", nargs="+", metavar="LOG", help="behaviour logs (.jsonl or .csv), read as one log")
    ap.add_argument("--out", required=True, metavar="DIR", help="directory for report.md, CSVs and PNGs")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"),
                    help="the two groups to test (default: time_limited unconstrained, or the only two groups)")
    ap.add_argument("--n-resamples", type=int, default=10_000, metavar="N",
                    help="permutation-test resamples (default 10000)")
    ap.add_argument("--bootstrap", type=int, default=1_000, metavar="N",
                    help="bootstrap resamples of the Fig. 4 CIs (default 1000)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the tests, the bootstrap and the IPE (default 0)")
    ap.add_argument("--epsilon", type=float, default=1e-3,
                    help="log-likelihoods are log(clip(p, eps, 1 - eps)) (default 1e-3)")
    ap.add_argument("--predictors", default="veridical,ipe,cnn",
                    help="registered predictor names for Fig. 4, comma-separated (default veridical,ipe,cnn)")
    ap.add_argument("--flow-task", metavar="ID", help="task of the flows (default: the paper's example "
                    "sequence if present, else the most-played task)")
    ap.add_argument("--gamma-towers", default=GAMMA_TOWERS[0], metavar="|".join(GAMMA_TOWERS),
                    help="which towers order dependency Γ counts: completed (every block placed, standing after each "
                         "placement; the paper's reading, default) or final (every trial's last tower)")
    ap.add_argument("--world", action="append", default=[], metavar="OVERRIDE",
                    help="config override of the world (and predictors), e.g. world.physics=static; repeatable")
    ap.add_argument("--only", default=",".join(ANALYSES),
                    help=f"analyses to run, comma-separated (default all: {','.join(ANALYSES)})")
    ap.add_argument("--quiet", action="store_true", help="no progress lines on standard error")
    return ap


def settings_of(args) -> Settings:
    from overhang_framework.errors import OverhangError

    only = [a.strip() for a in args.only.split(",") if a.strip()]
    bad = [a for a in only if a not in ANALYSES]
    if bad:
        raise OverhangError(f"--only: unknown analysis {', '.join(map(repr, bad))}; analyses: {', '.join(ANALYSES)}")
    predictors = [p.strip() for p in args.predictors.split(",") if p.strip()]
    if not predictors:
        raise OverhangError("--predictors: give at least one predictor name")
    if args.n_resamples < 1 or args.bootstrap < 1:
        raise OverhangError("--n-resamples and --bootstrap must be >= 1")
    if args.gamma_towers not in GAMMA_TOWERS:
        raise OverhangError(f"--gamma-towers: unknown reading {args.gamma_towers!r}; "
                            f"readings: {', '.join(GAMMA_TOWERS)}")
    if not 0 < args.epsilon < 0.5:
        raise OverhangError(f"--epsilon must be in (0, 0.5), got {args.epsilon}")
    return Settings(world_overrides=list(args.world), compare=tuple(args.compare) if args.compare else None,
                    n_resamples=args.n_resamples, bootstrap=args.bootstrap, seed=args.seed, epsilon=args.epsilon,
                    predictors=predictors, flow_task=args.flow_task, only=only, progress=not args.quiet,
                    gamma_towers=args.gamma_towers)


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.behaviour.analysis import run
    from overhang_framework.errors import OverhangError

    args = parser().parse_args(argv)
    say = (lambda s: None) if args.quiet else (lambda s: print(s, file=sys.stderr, flush=True))
    try:
        settings = settings_of(args)
        sections = run(args.logs, args.out, settings, log=say)
    except OverhangError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    files = sorted({f for s in sections.values() for f in s.files} | {"report.md", "summary.json"})
    print(f"wrote {args.out}/report.md and {len(files) - 1} files: {', '.join(f for f in files if f != 'report.md')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

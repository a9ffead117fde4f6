"""Score a finished (or stopped) benchmark run again from its episodes, in seconds, with no agent.

``python -m overhang_framework.benchmark.rescore RUN_DIR`` rewrites ``scores.csv``, ``summary.json`` and
``score.png`` of ``RUN_DIR`` from its ``episodes.jsonl``, dividing by the optima as the optima file holds
them now (after new optima were added, say). Nothing is played and no physics runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.benchmark.run import EPISODES, RUN, build_agent, format_summary, read_episodes, write_results

    ap = argparse.ArgumentParser(prog="python -m overhang_framework.benchmark.rescore", description=__doc__.split("\n\n")[0])
    ap.add_argument("run", help="a benchmark run directory (with run.json and episodes.jsonl)")
    ap.add_argument("--no-figure", action="store_true", help="leave score.png as it is")
    args = ap.parse_args(argv)
    out = Path(args.run)
    if not (out / RUN).exists() or not (out / EPISODES).exists():
        print(f"error: {out} is not a benchmark run directory (it needs {RUN} and {EPISODES})", file=sys.stderr)
        return 2
    cfg = json.loads((out / RUN).read_text())["identity"]
    world, _ = build_agent({**cfg, "agent": {"type": "random"}, "verdicts": None}, out)
    records = read_episodes(out / EPISODES)
    result = write_results(out, cfg, records, world, figure=not args.no_figure)
    print(format_summary(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())

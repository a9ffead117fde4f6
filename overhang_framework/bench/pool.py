"""What handing out a long run's items costs the parent process: ``python -m overhang_framework.bench.pool``.

:func:`overhang_framework.parallel.pool_map` runs many small items on worker
processes (the fit's score tables come in chunks of 8 decision states, tens of
thousands of them in a recovery at the paper's size). This benchmark runs the
same items, each a fixed stretch of arithmetic in a worker, in two ways side by
side in one run, alternating: every item handed to the pool at once
(``in_flight`` = all), and a few a worker at a time (the default). For each it
prints the wall time, the items a second, and the CPU seconds the parent spent
handing out and collecting (which the workers then lack on a machine whose
cores they fill).

It prints a summary and, as its last line, one JSON object with the figures;
``--out FILE`` writes that object too (atomically).
"""

from __future__ import annotations

import argparse
import json
import resource
import time
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.parallel import pool_map
from overhang_framework.results import atomic_write_json


def _setup(seconds: float) -> float:
    return seconds


def _work(seconds: float, item: int) -> int:
    end = time.process_time() + seconds
    total = item
    while time.process_time() < end:
        total = (total * 1103515245 + 12345) % 2147483648
    return total


def _parent_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def run_once(items: int, seconds: float, workers: int, in_flight: Optional[int]) -> dict:
    cpu, start = _parent_cpu(), time.perf_counter()
    done = sum(1 for _ in pool_map(_setup, (seconds,), _work, range(items), workers, lambda: None,
                                   in_flight=in_flight))
    wall = time.perf_counter() - start
    assert done == items
    return {"wall_s": wall, "items_per_s": items / wall, "parent_cpu_s": _parent_cpu() - cpu}


def main(argv: Optional[Sequence[str]] = None) -> dict:
    parser = argparse.ArgumentParser(prog="python -m overhang_framework.bench.pool", description=__doc__.splitlines()[0])
    parser.add_argument("--items", type=int, default=20000, help="items in each run (default 20000)")
    parser.add_argument("--seconds", type=float, default=0.002,
                        help="CPU seconds of work an item (default 0.002)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2, help="alternations of the two ways (default 2)")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    ways = {"all at once": args.items, "default": None}
    runs: dict[str, list[dict]] = {name: [] for name in ways}
    for _ in range(args.rounds):
        for name, in_flight in ways.items():
            runs[name].append(run_once(args.items, args.seconds, args.workers, in_flight))
    summary = {"items": args.items, "seconds_an_item": args.seconds, "workers": args.workers, "rounds": args.rounds}
    for name, figures in runs.items():
        best = min(figures, key=lambda f: f["wall_s"])
        summary[name] = {key: round(min(f[key] for f in figures) if key != "items_per_s" else best[key], 3)
                         for key in ("wall_s", "items_per_s", "parent_cpu_s")}
        print(f"{name:>12}: {summary[name]['wall_s']:.2f} s wall, {summary[name]['items_per_s']:.0f} items/s, "
              f"parent {summary[name]['parent_cpu_s']:.2f} CPU s (best of {args.rounds})")
    summary["speedup"] = round(summary["all at once"]["wall_s"] / summary["default"]["wall_s"], 3)
    summary["parent_cpu_ratio"] = round(summary["all at once"]["parent_cpu_s"]
                                        / max(summary["default"]["parent_cpu_s"], 1e-9), 3)
    print(f"default against all at once: {summary['speedup']:.2f}x the speed, "
          f"{summary['parent_cpu_ratio']:.1f}x less of the parent's CPU")
    if args.out:
        atomic_write_json(args.out, summary)
    print(json.dumps(summary))
    return summary


if __name__ == "__main__":
    main()

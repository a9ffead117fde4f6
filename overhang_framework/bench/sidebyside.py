"""Timing two or more versions of a computation side by side, in one run, on the same cases.

Machines here are noisy, so a speed-up is only believed when the versions ran in one process, on
the same cases, alternating which goes first from case to case (so neither always meets a warm or a
cold machine). :func:`side_by_side` does that and checks the versions agree.
"""

from __future__ import annotations

import time
from typing import Any, Callable, Mapping, Sequence


def side_by_side(cases: Sequence[Any], versions: Mapping[str, Callable[[Any], Any]],
                 label: Callable[[Any], str] = str, quiet: bool = False) -> dict:
    """Run every version on every case, the order of the versions reversed on every other case.

    Each version returns its result (compared across versions: the same result is counted). Returns,
    per version, its seconds per case and in total, the results, and ``same``: the cases on which
    every version gave the same result.
    """
    names = list(versions)
    seconds = {n: [] for n in names}
    results = {n: [] for n in names}
    same = 0
    for k, case in enumerate(cases):
        order = names if k % 2 == 0 else names[::-1]
        got = {}
        for name in order:
            started = time.perf_counter()
            got[name] = versions[name](case)
            seconds[name].append(time.perf_counter() - started)
        for name in names:
            results[name].append(got[name])
        agree = all(got[n] == got[names[0]] for n in names)
        same += int(agree)
        if not quiet:
            cells = ", ".join(f"{n} {seconds[n][-1]:.1f} s" for n in names)
            print(f"  {label(case)}: {cells}{'' if agree else ' (results differ)'}", flush=True)
    return {"cases": len(cases), "same": same,
            "versions": {n: {"seconds": seconds[n], "total": sum(seconds[n]), "results": results[n]} for n in names}}


def ratio(figures: dict, slow: str, fast: str) -> float:
    """How many times faster ``fast`` was than ``slow`` in total."""
    return figures["versions"][slow]["total"] / max(figures["versions"][fast]["total"], 1e-12)

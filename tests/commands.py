"""Independent commands of one test run two at a time: a refusal costs an interpreter's start, and the
test run's own process leaves the machine's second core idle."""

from __future__ import annotations

import subprocess
from concurrent.futures import ThreadPoolExecutor
from typing import Mapping, Optional, Sequence


def run_each(argvs: Sequence[Sequence[str]], timeout: float = 300, workers: int = 2,
             env: Optional[Mapping[str, str]] = None, cwd=None) -> list:
    """``subprocess.run`` of each argv (text, output captured, in ``env`` and ``cwd`` when given), in the order
    given."""
    def one(argv):
        return subprocess.run(list(argv), capture_output=True, text=True, timeout=timeout,
                              env=None if env is None else dict(env), cwd=cwd)

    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(one, argvs))

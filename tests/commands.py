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


def run_chains(chains: Sequence[Sequence[Sequence[str]]], timeout: float = 300, workers: int = 2,
               envs: Optional[Sequence[Mapping[str, str]]] = None, cwds: Optional[Sequence] = None) -> list:
    """Each chain's argvs in their order (a later one may read what an earlier one wrote), the chains two at a
    time, chain ``i`` in ``envs[i]`` and ``cwds[i]`` when given; the ``subprocess.run`` results, chain by chain."""
    def chain(i):
        env = None if envs is None else dict(envs[i])
        cwd = None if cwds is None else cwds[i]
        return [subprocess.run(list(argv), capture_output=True, text=True, timeout=timeout, env=env, cwd=cwd)
                for argv in chains[i]]

    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(chain, range(len(chains))))

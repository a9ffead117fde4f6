"""PyBullet checks in parallel over a pool of worker processes.

Each worker opens one DIRECT-mode :class:`PyBulletSimulator` when it starts and
reuses it for every check it runs. A batch is cut into chunks, one task per
chunk, so the inter-process traffic is a few messages per batch. If a worker
dies (segfault, killed), the pending batch fails with :class:`PoolCrashed`
instead of hanging, and the pool is restarted on the next call.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Optional, Sequence

import numpy as np

from overhang_framework.geometry import Geometry
from overhang_framework.parallel import exit_with_parent
from overhang_framework.physics.pybullet_backend import (
    Outcome,
    PyBulletParams,
    PyBulletSimulator,
)

_SIM: Optional[PyBulletSimulator] = None


class PoolCrashed(RuntimeError):
    """A pool worker died while checking a batch."""


def _init_worker(params: PyBulletParams) -> None:
    global _SIM
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    exit_with_parent()
    _SIM = PyBulletSimulator(params)


def _run_chunk(items, early_stop):
    return [_SIM.check(g, grav, fr, early_stop=early_stop) for g, grav, fr in items]


def _worker_pid(_=None) -> int:
    return os.getpid()


class PyBulletPool:
    """:class:`~overhang_framework.physics.PhysicsBackend` running PyBullet checks on ``workers`` processes.

    ``early_stop`` overrides ``params.early_stop`` for every check (``None``
    keeps it). Use as a context manager or call :meth:`close`.
    """

    name = "pybullet"

    def __init__(self, workers: Optional[int] = None, params: PyBulletParams = PyBulletParams(),
                 early_stop: Optional[bool] = None, chunks_per_worker: int = 4):
        self.workers = max(1, int(workers or os.cpu_count() or 1))
        self.params = params
        self.early_stop = early_stop
        self.chunks_per_worker = chunks_per_worker
        self._executor: Optional[ProcessPoolExecutor] = None

    def _pool(self) -> ProcessPoolExecutor:
        if self._executor is None:
            self._executor = ProcessPoolExecutor(
                max_workers=self.workers,
                mp_context=mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn"),
                initializer=_init_worker,
                initargs=(self.params,),
            )
        return self._executor

    def worker_pids(self) -> list[int]:
        """Process ids of the live workers (starts the pool if needed)."""
        pool = self._pool()
        list(pool.map(_worker_pid, range(self.workers * 2)))
        return sorted(p.pid for p in pool._processes.values())

    def check_batch(self, geometries: Sequence[Geometry], gravity=None, friction=None) -> list[Outcome]:
        """One :class:`Outcome` per geometry, in order. Raises :class:`PoolCrashed` if a worker dies."""
        geometries = list(geometries)
        n = len(geometries)
        if n == 0:
            return []
        items = [
            (g, None if gravity is None else tuple(map(float, gravity[i])),
             None if friction is None else tuple(map(float, friction[i])))
            for i, g in enumerate(geometries)
        ]
        size = max(1, -(-n // (self.workers * self.chunks_per_worker)))
        chunks = [items[k:k + size] for k in range(0, n, size)]
        pool = self._pool()
        try:
            futures = [pool.submit(_run_chunk, c, self.early_stop) for c in chunks]
            results = [f.result() for f in futures]
        except BrokenProcessPool as exc:
            self._discard()
            raise PoolCrashed(
                f"a PyBullet pool worker died while checking a batch of {n} geometries; the pool will restart on the next call"
            ) from exc
        return [o for r in results for o in r]

    def stable(self, geometry: Geometry, gravity=None, friction=None) -> bool:
        return bool(self.stable_batch(
            [geometry], None if gravity is None else [gravity], None if friction is None else [friction]
        )[0])

    def stable_batch(self, geometries: Sequence[Geometry], gravity=None, friction=None) -> np.ndarray:
        return np.array([o.stable for o in self.check_batch(geometries, gravity, friction)], dtype=bool)

    def _discard(self) -> None:
        if self._executor is not None:
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None

    def close(self) -> None:
        """Stop the workers."""
        if self._executor is not None:
            self._executor.shutdown(wait=True, cancel_futures=True)
            self._executor = None

    def __enter__(self) -> "PyBulletPool":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        try:
            self._discard()
        except Exception:
            pass

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_executor"] = None
        return state

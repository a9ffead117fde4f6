"""Work spread over worker processes (``jobs=N``), with the results of a serial run.

:func:`pool_map` runs any function over items on spawned workers, each of which
builds what it needs once (:func:`overhang_framework.episode.play_episodes` plays a run's episodes with it).

Every episode draws its generator from ``(seed, task index, repeat)`` and the
physics answers do not depend on what ran before (a cache only remembers
verdicts), so an episode's record is the same whichever process plays it and
in whatever order. Each worker builds the run's models once from the resolved
config and plays the episodes it is given; placements are reported back as
they happen, so the progress bar still moves per placement. Workers ignore
Ctrl-C: the parent process handles it, stops them, and keeps every episode
that finished. A worker whose parent is gone (killed outright, which runs no
cleanup) ends itself within a second (:func:`exit_with_parent`).
"""

from __future__ import annotations

import itertools
import multiprocessing as mp
import os
import queue as queue_module
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

_STATE: Any = None
_TICKS = None


def exit_with_parent(interval: float = 1.0) -> None:
    """In a worker process: end this process once its parent is gone. A parent killed outright (``kill``,
    a job's time limit) runs no cleanup, and its workers would otherwise go on computing for nobody."""
    parent = os.getppid()

    def watch() -> None:
        while True:
            time.sleep(interval)
            if os.getppid() != parent:
                os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _init(setup: Callable[..., Any], args: tuple, ticks) -> None:
    global _STATE, _TICKS
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle
    exit_with_parent()
    # One compute thread per worker: the workers already fill the cores, and oversubscribed
    # thread pools (torch's, BLAS's) slow every process down (a model's own `threads` still wins).
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(1)
    from overhang_framework.config import enable_plugin_configs

    enable_plugin_configs()
    _TICKS = ticks
    _STATE = setup(*args)


def given(*args: Any) -> tuple:
    """A :func:`pool_map` setup for work that needs nothing built per worker: its arguments are the state."""
    return args


def tick() -> None:
    """In a worker of :func:`pool_map`: report one unit of progress to the parent (a no-op elsewhere)."""
    if _TICKS is not None:
        _TICKS.put(1)


def _call(work: Callable[[Any, Any], Any], item: Any) -> tuple[Any, int]:
    return work(_STATE, item), os.getpid()


def pool_map(setup: Callable[..., Any], args: tuple, work: Callable[[Any, Any], Any], items: Iterable[Any],
             workers: int, on_tick: Callable[[], None],
             in_flight: Optional[int] = None) -> Iterator[tuple[Any, Any, int]]:
    """Yield ``(item, work(state, item), process id)`` for every item, as each finishes, computed
    on ``workers`` spawned processes.

    Each worker runs ``state = setup(*args)`` once, then ``work(state, item)`` for
    the items it is given; both must be importable module-level functions.
    ``on_tick`` is called in this process once per :func:`tick` made in any
    worker. On an error or Ctrl-C the workers are stopped; every result already
    yielded stays with the caller.

    At most ``in_flight`` items (default four a worker) are handed out at a time, in their order, the next
    as each finishes and the caller asks for more: waiting on every item of a long run at once costs this
    process a core of its own (``python -m overhang_framework.bench.pool`` measures it), and a caller that
    takes long over each result leaves the workers idle once their few items are done.
    """
    in_flight = max(1, in_flight if in_flight is not None else 4 * workers)
    context = mp.get_context("spawn")
    ticks = context.Queue()
    executor = ProcessPoolExecutor(max_workers=workers, mp_context=context, initializer=_init,
                                   initargs=(setup, tuple(args), ticks))
    pending: dict[Future, Any] = {}
    todo = iter(items)
    try:
        for item in itertools.islice(todo, in_flight):
            pending[executor.submit(_call, work, item)] = item
        while pending:
            finished, _ = wait(list(pending), timeout=0.1, return_when=FIRST_COMPLETED)
            _drain(ticks, on_tick)
            done = [(pending.pop(future), future) for future in finished]
            try:
                for item in itertools.islice(todo, len(done)):
                    pending[executor.submit(_call, work, item)] = item
            except BrokenProcessPool:
                pass  # the results already finished are yielded first; a pending one then raises
            for item, future in done:
                result, pid = future.result()
                yield item, result, pid
        _drain(ticks, on_tick)
    finally:
        processes = list((getattr(executor, "_processes", None) or {}).values())
        for future in pending:
            future.cancel()
        executor.shutdown(wait=not pending, cancel_futures=True)
        for process in processes:
            if process.is_alive():
                process.terminate()


def merge_stats(parts: Sequence[Any]) -> Any:
    """Several processes' stats as one: numbers summed, nested dicts merged key by key, anything else
    kept from the first; a ``hit_rate`` beside ``hits`` and ``misses`` is computed again."""
    parts = [p for p in parts if p is not None]
    if not parts:
        return {}
    first = parts[0]
    if isinstance(first, dict):
        keys = list(dict.fromkeys(k for p in parts if isinstance(p, dict) for k in p))
        out = {k: merge_stats([p.get(k) for p in parts if isinstance(p, dict)]) for k in keys}
        if "hit_rate" in out and isinstance(out.get("hits"), int) and isinstance(out.get("misses"), int):
            asked = out["hits"] + out["misses"]
            out["hit_rate"] = out["hits"] / asked if asked else 0.0
        return out
    if all(isinstance(p, (int, float)) and not isinstance(p, bool) for p in parts):
        return sum(parts)
    return first


def _drain(ticks, on_step: Callable[[], None]) -> None:
    while True:
        try:
            ticks.get_nowait()
        except queue_module.Empty:
            return
        on_step()

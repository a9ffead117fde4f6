"""Worker processes end with their parent: a parent killed outright leaves no worker computing for nobody."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

PARENT = textwrap.dedent("""
    import os, sys, time

    def setup():
        return None

    def work(state, seconds):
        time.sleep(seconds)
        return os.getpid()

    if __name__ == "__main__":
        if sys.argv[1] == "pool_map":
            from overhang_framework.parallel import pool_map

            for item, result, pid in pool_map(setup, (), work, [0.0] * 4 + [600.0] * 2, 2, lambda: None):
                print(pid, flush=True)
        else:
            from overhang_framework.physics.pool import PyBulletPool

            pool = PyBulletPool(2)
            print(*pool.worker_pids(), flush=True)
            time.sleep(600)
""")


def _children(pid: int) -> set[int]:
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").iterdir():
        out |= {int(c) for c in (task / "children").read_text().split()}
    return out


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")  # a zombie has ended; only its exit status waits to be read


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="reads /proc")
@pytest.mark.parametrize("pool", ["pool_map", "pybullet"])
def test_workers_end_when_their_parent_is_killed_outright(tmp_path, pool):
    if pool == "pybullet":
        pytest.importorskip("pybullet")
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    parent = subprocess.Popen([sys.executable, str(script), pool], stdout=subprocess.PIPE, text=True)
    try:
        first = parent.stdout.readline().split()  # a first result, or the pool's pids: the workers are set up
        if pool == "pybullet":
            workers = {int(w) for w in first}
        else:  # the spawned workers (not the resource tracker)
            workers = {w for w in _children(parent.pid) if "spawn_main" in Path(f"/proc/{w}/cmdline").read_text()}
        assert len(workers) == 2 and workers <= _children(parent.pid)
        parent.send_signal(signal.SIGKILL)
        parent.wait(30)
        deadline = time.monotonic() + 20
        while any(_running(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not any(_running(w) for w in workers), "a worker outlived its killed parent"
    finally:
        if parent.poll() is None:
            parent.kill()


@pytest.mark.parametrize("in_flight", [1, 3])
def test_pool_map_hands_out_a_few_items_at_a_time_and_returns_every_one(in_flight):
    from overhang_framework.bench.pool import _setup, _work
    from overhang_framework.parallel import pool_map

    pulled = []

    def items():
        for i in range(40):
            pulled.append(i)
            yield i

    seen, pulled_at_first = {}, None
    for item, result, _ in pool_map(_setup, (0.0,), _work, items(), 2, lambda: None, in_flight=in_flight):
        if pulled_at_first is None:
            pulled_at_first = len(pulled)
        seen[item] = result
    assert sorted(seen) == list(range(40))
    assert all(seen[i] == i for i in seen)  # no work: each item comes back as it went
    # every item taken from the iterator at once would leave 40 pulled at the first result
    assert pulled_at_first <= 2 * in_flight

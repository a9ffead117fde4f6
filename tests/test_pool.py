"""The PyBullet process pool: same verdicts as serial checks, and a crash is an error, not a hang."""

import os
import signal

import numpy as np
import pytest

pytest.importorskip("pybullet")

from overhang_framework.physics.pool import PoolCrashed, PyBulletPool
from overhang_framework.physics.pybullet_backend import PyBulletBackend
from overhang_framework.physics.towers import random_towers


def test_pool_verdicts_equal_serial():
    towers = random_towers(8, seed=3, max_blocks=4)
    serial = PyBulletBackend().stable_batch(towers)
    with PyBulletPool(2) as pool:
        assert np.array_equal(pool.stable_batch(towers), serial)
        assert pool.stable(towers[0]) == serial[0]
        grav = np.tile([0.0, -9.81], (len(towers), 1))
        assert np.array_equal(pool.stable_batch(towers, grav), serial)


def test_workers_are_reused_between_batches():
    towers = random_towers(4, seed=5, max_blocks=3)
    with PyBulletPool(2) as pool:
        before = pool.worker_pids()
        pool.stable_batch(towers)
        pool.stable_batch(towers)
        assert pool.worker_pids() == before


def test_a_killed_worker_raises_instead_of_hanging():
    towers = random_towers(6, seed=6, max_blocks=3)
    with PyBulletPool(2) as pool:
        expected = pool.stable_batch(towers)
        os.kill(pool.worker_pids()[0], signal.SIGKILL)
        with pytest.raises(PoolCrashed, match="worker died"):
            for _ in range(50):
                pool.stable_batch(towers)
        assert np.array_equal(pool.stable_batch(towers), expected)

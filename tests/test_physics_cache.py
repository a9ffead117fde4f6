"""The verdict cache: order-independent keys, hit counting, batching of misses."""

import numpy as np
import pytest

from overhang_framework.geometry import Geometry
from overhang_framework.physics.cache import CachedBackend, VerdictCache, verdict_key
from overhang_framework.physics.static_backend import StaticBackend


class Counting:
    """A backend that counts what it is asked and answers from a static backend."""

    name = "counting"

    def __init__(self, **params):
        self.inner = StaticBackend(**params)
        self.params = self.inner.params
        self.asked = 0

    def stable(self, geometry, gravity=None, friction=None):
        self.asked += 1
        return self.inner.stable(geometry, gravity, friction)

    def stable_batch(self, geometries, gravity=None, friction=None):
        self.asked += len(geometries)
        return self.inner.stable_batch(geometries, gravity, friction)


TOWER = Geometry.from_tuples([(1.8, 0.0, 0), (0.6, 0.6, 1), (1.2, -0.3, 1), (0.6, 0.2, 2)])
PERMUTED = Geometry(tuple(TOWER.blocks[i] for i in (2, 0, 3, 1)))


def test_keys_are_order_independent():
    assert verdict_key(TOWER) == verdict_key(PERMUTED)
    fr = [0.1, 0.2, 0.3, 0.4]
    assert verdict_key(TOWER, friction=fr) == verdict_key(PERMUTED, friction=[fr[i] for i in (2, 0, 3, 1)])
    assert verdict_key(TOWER, friction=fr) != verdict_key(PERMUTED, friction=fr)


def test_keys_round_as_the_canonical_geometry_key():
    assert verdict_key(TOWER)[1] == TOWER.key
    nudged = Geometry.from_tuples([(b.width, b.x + 1e-9, b.layer) for b in TOWER.blocks])
    fr = [0.1, 0.2, 0.3, 0.4]
    assert verdict_key(nudged, friction=fr) == verdict_key(TOWER, friction=[f + 1e-9 for f in fr])
    signed = Geometry.from_tuples([(0.6, -0.0, 0)])
    assert verdict_key(signed, gravity=(-0.0, -9.81)) == verdict_key(Geometry.from_tuples([(0.6, 0.0, 0)]),
                                                                     gravity=(0.0, -9.81))
    with pytest.raises(ValueError):
        verdict_key(TOWER, friction=fr[:3])


def test_keys_tell_apart_what_changes_the_verdict():
    moved = Geometry(TOWER.blocks[:-1] + (TOWER.blocks[-1].__class__(0.6, 0.25, 2),))
    assert verdict_key(TOWER) != verdict_key(moved)
    assert verdict_key(TOWER) != verdict_key(TOWER, gravity=(0.1, -9.81))
    assert verdict_key(TOWER, gravity=(0.1, -9.81)) != verdict_key(TOWER, gravity=(0.2, -9.81))
    assert verdict_key(TOWER, context="a") != verdict_key(TOWER, context="b")


def test_hits_are_counted_and_the_backend_is_not_asked_again():
    inner = Counting()
    cached = CachedBackend(inner)
    first = cached.stable(TOWER)
    assert cached.stable(PERMUTED) == first
    assert inner.asked == 1
    assert cached.stats()["hits"] == 1 and cached.stats()["misses"] == 1
    assert cached.cache.hit_rate == pytest.approx(0.5)


def test_batch_sends_each_distinct_miss_once():
    inner = Counting()
    cached = CachedBackend(inner)
    other = Geometry.from_tuples([(0.6, 0.0, 0), (1.2, 0.5, 1)])
    out = cached.stable_batch([TOWER, PERMUTED, other, TOWER])
    assert inner.asked == 2
    assert list(out) == [cached.stable(TOWER)] * 2 + [cached.stable(other), cached.stable(TOWER)]
    assert inner.asked == 2
    grav = np.array([[0.0, -9.81], [3.0, -9.81]])
    cached.stable_batch([TOWER, TOWER], grav, [[0.1] * 4, [0.1] * 4])
    assert inner.asked == 4


def test_verdicts_match_the_wrapped_backend():
    from overhang_framework.physics.towers import random_towers

    towers = random_towers(50, seed=1)
    static = StaticBackend()
    cached = CachedBackend(StaticBackend())
    assert np.array_equal(cached.stable_batch(towers), static.stable_batch(towers))
    assert np.array_equal(cached.stable_batch(towers), static.stable_batch(towers))
    assert cached.stats()["hits"] >= 50


def test_one_cache_shared_by_two_wrappers_keeps_parameters_apart():
    cache = VerdictCache()
    edge = Geometry.from_tuples([(0.6, 0.0, 0), (1.2, 0.295, 1)])
    loose = CachedBackend(StaticBackend(margin=0.0), cache)
    strict = CachedBackend(StaticBackend(margin=0.01), cache)
    assert loose.stable(edge) and not strict.stable(edge)
    again = CachedBackend(StaticBackend(margin=0.0), cache)
    assert again.stable(edge)
    assert cache.hits == 1


def test_lru_eviction_bounds_the_size():
    cache = VerdictCache(maxsize=2)
    for k in "abc":
        cache.put(k, True)
    assert len(cache) == 2 and cache.get("a") is None and cache.get("c") is True

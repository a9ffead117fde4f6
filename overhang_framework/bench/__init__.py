"""Benchmarks and their data: how fast and how right the physics is.

* :mod:`~overhang_framework.physics.towers` -- seeded random, near-critical and
  episode-like towers (benchmark data).
* :mod:`~overhang_framework.bench.physics` -- ``python -m overhang_framework.bench``:
  the PyBullet reference, early stopping, the static backend, pool and cache.
* :mod:`~overhang_framework.bench.workload` -- the towers planners ask about in
  real episodes.
* :mod:`~overhang_framework.bench.agreement` -- ``python -m
  overhang_framework.bench.agreement``: the tiered physics and the static
  models against the full-window reference, by family and distance to the flip.
"""

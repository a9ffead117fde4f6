"""The Overhang Tower benchmark: fixed splits with proven optima, one protocol and metric, any agent.

* :mod:`~overhang_framework.benchmark.splits`: stable task ids and the ``test``, ``train`` (5 folds),
  ``cross`` and ``paper20`` splits, kept in ``overhang_framework/data/benchmark_splits.json``;
* :mod:`~overhang_framework.benchmark.optima`: the proven optimum of every scored task, replayed under
  the reference (``python -m overhang_framework.benchmark.optima split=test``);
* :mod:`~overhang_framework.benchmark.score`: scores, bootstrap intervals and the area under the
  score-against-compute curve;
* :mod:`~overhang_framework.benchmark.agents`: what plays, a planner plugin with a predictor or an
  external program speaking JSON Lines (:mod:`~overhang_framework.benchmark.external`);
* ``python -m overhang_framework.benchmark``: scores one agent on one split (docs/benchmark.md).
"""

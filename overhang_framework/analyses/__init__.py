"""Analyses that reproduce the paper's claims on this framework's own physics.

Each module is a command, ``python -m overhang_framework.analyses.<name> --help``:

* :mod:`~overhang_framework.analyses.ipe_mechanism` -- how the IPE's predictive
  entropy and accuracy change with the number of blocks (paper, Results:
  "Physical Prediction Mechanism Switching").
* :mod:`~overhang_framework.analyses.bench_ipe` -- the IPE's speed benchmark and
  its sigma -> 0 agreement with the veridical predictor.
* :mod:`~overhang_framework.analyses.predictor_accuracy` -- each predictor's
  accuracy against the reference by number of blocks (the hybrid's switch point).
* :mod:`~overhang_framework.analyses.budget_depth` -- how deep a lookahead gets
  within a call budget.

:mod:`~overhang_framework.analyses.plots` draws the figure they share (measures
against the number of blocks).
"""

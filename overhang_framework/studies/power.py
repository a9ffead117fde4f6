"""Studies redrawn from the simulated participants, and the share of them in which a finding holds: the power of a
study of that size (where the effect is planted), or its false-positive rate (where none is). The paper's findings
(:func:`overhang_framework.studies.findings.power`) and the graded study's trends
(:func:`overhang_framework.studies.graded.power`) are both redrawn here."""

from __future__ import annotations

from typing import Callable, Mapping, Optional, Sequence

import numpy as np
import pandas as pd


def replaced(df: pd.DataFrame, sizes: Mapping[str, int]) -> bool:
    """Whether a study of ``sizes`` must draw ``df``'s participants with replacement: a condition has no more
    than the study takes (drawn without replacement, a study of all of them would be the same every time)."""
    return any(n >= int((df["condition"] == c).sum()) for c, n in sizes.items())


def resample(df: pd.DataFrame, sizes: Mapping[str, int], rng: np.random.Generator, replace: Optional[bool] = None,
             prefix: str = "r") -> pd.DataFrame:
    """A study of ``sizes`` participants per condition drawn from ``df``'s, in the order of ``sizes``, renamed apart
    (``prefix`` and a number): with replacement when ``replace`` says so, or by default when a condition has too few
    for a draw without (:func:`replaced`)."""
    parts = []
    replace = replaced(df, sizes) if replace is None else replace
    for condition, n in sizes.items():
        pool = df[df["condition"] == condition]
        if len(pool) and n:
            rows = rng.integers(len(pool), size=n) if replace else rng.choice(len(pool), size=n, replace=False)
            parts.append(pool.iloc[rows])
    out = pd.concat(parts, ignore_index=True)
    out["participant"] = [f"{prefix}{i}" for i in range(len(out))]
    return out


def rates(names: Sequence[str], resamples: int, draw: Callable[[], pd.DataFrame],
          test: Callable[[pd.DataFrame, int], Mapping[str, tuple[bool, bool]]],
          on_study: Callable[[], None] = lambda: None) -> dict[str, float]:
    """For each of ``names``, the share of ``resamples`` studies (each ``draw()``, then ``test(study, b)`` giving
    each name's ``(holds, tested)``) in which it holds; NaN for a name no study could test."""
    hits = {name: 0 for name in names}
    tested = {name: 0 for name in names}
    for b in range(resamples):
        found = test(draw(), b)
        for name in hits:
            holds, testable = found[name]
            hits[name] += int(holds)
            tested[name] += int(testable)
        on_study()
    return {name: h / resamples if tested[name] else float("nan") for name, h in hits.items()}

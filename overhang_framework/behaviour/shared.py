"""What every behaviour analysis section shares: the groups and their colours, the statistics
(:func:`mean_sem`, :func:`permutation_p`: SciPy's ``permutation_test``, independent samples, difference of
means, two-sided, seeded; :func:`bootstrap_ci`: participants resampled with replacement, seeded), how a
finding is worded, the tables and files, and the :class:`Settings` and :class:`Section` of a run.

The sections (:mod:`~overhang_framework.behaviour.table1`, :mod:`~overhang_framework.behaviour.gamma`,
:mod:`~overhang_framework.behaviour.flows`, :mod:`~overhang_framework.behaviour.prediction`) take these from
here, and :mod:`~overhang_framework.behaviour.analysis`, which runs them, does too; none of them is imported
back.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.results import atomic_output, atomic_write_text

ANALYSES = ("table1", "gamma", "flows", "prediction")
#: Which towers Γ counts (:attr:`Settings.gamma_towers`), the default first.
GAMMA_TOWERS = ("completed", "final")
DEFAULT_COMPARE = ("time_limited", "unconstrained")
GROUP_COLOURS = {"time_limited": "#d98c1f", "unconstrained": "#2f6db5"}
OTHER_COLOURS = ("#3a9a5b", "#8e5bb5", "#6b6b6b", "#b5875b", "#2aa3a3", "#c2559a")


def group_of(source: Any, participant: str, condition: str) -> str:
    """A record's group: its model label for ``source == "model"`` (participant id before '/'), else its condition."""
    if source == "model":
        return str(participant).split("/", 1)[0]
    return str(condition)


def with_groups(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with a ``group`` column (see :func:`group_of`)."""
    df = df.copy()
    df["group"] = [group_of(s, p, c) for s, p, c in zip(df["source"], df["participant"], df["condition"])]
    return df


def group_order(groups: Sequence[str], compare: Optional[Sequence[str]]) -> list[str]:
    """The compared groups first, then the others alphabetically."""
    first = [g for g in (compare or ()) if g in groups]
    return first + sorted(g for g in set(groups) if g not in first)


def default_compare(groups: Sequence[str]) -> Optional[tuple[str, str]]:
    """``time_limited`` vs ``unconstrained`` when both are present, else the two groups when there are two."""
    present = sorted(set(groups))
    if all(g in present for g in DEFAULT_COMPARE):
        return DEFAULT_COMPARE
    if len(present) == 2:
        return (present[0], present[1])
    return None


def colour(group: str, order: Sequence[str]) -> str:
    if group in GROUP_COLOURS:
        return GROUP_COLOURS[group]
    others = [g for g in order if g not in GROUP_COLOURS]
    return OTHER_COLOURS[others.index(group) % len(OTHER_COLOURS)] if group in others else OTHER_COLOURS[0]


def mean_sem(values) -> tuple[float, float]:
    """Mean and standard error of the finite ``values`` (NaN for none; SEM NaN for one)."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if v.size == 0:
        return math.nan, math.nan
    return float(v.mean()), float(v.std(ddof=1) / math.sqrt(v.size)) if v.size > 1 else math.nan


def _diff_of_means(x, y, axis):
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def permutation_p(a, b, n_resamples: int, seed: int) -> float:
    """Two-sided p of the difference of means of independent samples ``a`` and ``b``
    (``scipy.stats.permutation_test``, ``n_resamples`` resamples, seeded); NaN when a side has fewer
    than two values (SciPy's minimum)."""
    from scipy.stats import permutation_test

    a = np.asarray([x for x in a if np.isfinite(x)], dtype=float)
    b = np.asarray([x for x in b if np.isfinite(x)], dtype=float)
    if a.size < 2 or b.size < 2:
        return math.nan
    res = permutation_test((a, b), _diff_of_means, permutation_type="independent", vectorized=True,
                           n_resamples=n_resamples, alternative="two-sided", random_state=seed)
    return float(res.pvalue)


def bootstrap_ci(sums: np.ndarray, counts: np.ndarray, n_resamples: int, seed: int,
                 level: float = 0.95) -> tuple[float, float]:
    """CI of a pooled mean ``sum(sums) / sum(counts)`` by resampling participants (the rows) with replacement.

    ``sums[i]`` and ``counts[i]`` are participant ``i``'s total and number of values. Percentile
    interval of ``n_resamples`` resamples; NaN when there is no value.
    """
    sums, counts = np.asarray(sums, float), np.asarray(counts, float)
    keep = counts > 0
    sums, counts = sums[keep], counts[keep]
    if counts.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    weights = rng.multinomial(counts.size, np.full(counts.size, 1 / counts.size), size=n_resamples)
    means = (weights @ sums) / (weights @ counts)
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


def fmt_p(p: float) -> str:
    """A p-value as the paper writes it: ``.107``, ``<.001``; ``–`` when there is none."""
    if p is None or not np.isfinite(p):
        return "–"
    if p < 0.001:
        return "<.001"
    return f"{p:.3f}".lstrip("0")


def p_is(p: float) -> str:
    """``p = .107`` or ``p < .001``."""
    text = fmt_p(p)
    return f"p {text[0]} {text[1:]}" if text.startswith("<") else f"p = {text}"


#: p below this is called credible in the reports' findings.
ALPHA = 0.05


def paper_p_credible(text: str) -> bool:
    """Whether a p as the paper prints it (``.022``, ``<.001``) is below :data:`ALPHA`."""
    return text.startswith("<") or float(text) < ALPHA


def is_paper_comparison(compare: Optional[Sequence[str]]) -> bool:
    """Whether the compared groups are the paper's two conditions, ``time_limited`` and ``unconstrained``."""
    return bool(compare) and set(compare) == set(DEFAULT_COMPARE)


def paper_pair(compare: Optional[Sequence[str]], time_limited: float, unconstrained: float
               ) -> Optional[tuple[float, float]]:
    """The paper's values of a metric in the order of ``compare``, or None when the compared groups are not
    the paper's two conditions."""
    if not is_paper_comparison(compare):
        return None
    return (time_limited, unconstrained) if compare[0] == "time_limited" else (unconstrained, time_limited)


def _direction(a: float, b: float) -> str:
    return "higher" if b > a else "lower" if b < a else "the same"


@dataclass(frozen=True)
class Finding:
    """A comparison in a sentence, and whether it matches the paper (None: no paper value or no test)."""

    text: str
    matches: Optional[bool]


def finding(what: str, compare: Sequence[str], ours: tuple[float, float], p: float,
            paper: Optional[tuple[float, float, str]], show: Callable[[float], str],
            no_paper: str = "; the paper reports no such comparison",
            show_paper: Optional[Callable[[float], str]] = None) -> Finding:
    """A sentence on a comparison: ``what`` is higher or lower for ``compare[1]`` than for ``compare[0]``
    (``ours`` = their values, in that order), whether ``p`` is credible (below :data:`ALPHA`), and whether
    that matches ``paper`` (its values in the same order and its p as printed; None: no paper value, and
    ``no_paper`` ends the sentence). ``show`` writes a value, ``show_paper`` (default ``show``) the paper's.

    Matching means the same verdict: both credible in the same direction, or neither credible.
    """
    a, b = compare
    if not (np.isfinite(ours[0]) and np.isfinite(ours[1])):
        return Finding(f"{what}: no value for {a if not np.isfinite(ours[0]) else b}, so no comparison", None)
    tested = p is not None and np.isfinite(p)
    credible = tested and p < ALPHA
    text = (f"{what} is {_direction(*ours)} for {b} than for {a} ({show(ours[1])} vs {show(ours[0])}; "
            + (f"{p_is(p)}, {'credible' if credible else 'not credible'})" if tested else
               "no test: a group has fewer than two participants with a value)"))
    if paper is None:
        return Finding(text + no_paper, None)
    pa, pb, ptext = paper
    shown = show_paper or show
    theirs = (f"{_direction(pa, pb)}, {shown(pb)} vs {shown(pa)}, "
              f"p {'< ' + ptext[1:] if ptext.startswith('<') else '= ' + ptext}")
    paper_credible = paper_p_credible(ptext)
    same = np.sign(ours[1] - ours[0]) == np.sign(pb - pa)
    if not tested:
        return Finding(f"{text}: {'same' if same else 'opposite'} direction to the paper's, untested here ({theirs})",
                       None)
    if credible and paper_credible:
        verdict, matches = ("matches the paper" if same else "opposite to the paper"), bool(same)
    elif credible:
        verdict, matches = "differs from the paper, which found no credible difference", False
    elif paper_credible:
        verdict, matches = "does not reproduce the paper's credible difference", False
    else:
        verdict, matches = "matches the paper, which found no credible difference either", True
    return Finding(f"{text}: {verdict} ({theirs})", matches)


def fmt_ms(mean: float, sem: float, digits: int) -> str:
    if not np.isfinite(mean):
        return "–"
    return f"{mean:.{digits}f} ± {sem:.{digits}f}" if np.isfinite(sem) else f"{mean:.{digits}f}"


def markdown_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(map(str, header)) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(map(str, r)) + " |" for r in rows]
    return "\n".join(lines)


def write_csv(df: pd.DataFrame, path: Path) -> None:
    atomic_write_text(path, df.to_csv(index=False, float_format="%.12g"))


def save_figure(fig, path: Path) -> None:
    import matplotlib.pyplot as plt

    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=130, bbox_inches="tight", format="png")
    plt.close(fig)


@dataclass
class Settings:
    """What every analysis needs besides the log."""

    world_overrides: Sequence[str] = ()
    compare: Optional[tuple[str, str]] = None
    n_resamples: int = 10_000
    bootstrap: int = 1_000
    seed: int = 0
    epsilon: float = 1e-3
    predictors: Sequence[str] = ("veridical", "ipe", "cnn")
    flow_task: Optional[str] = None
    only: Sequence[str] = ANALYSES
    progress: bool = False
    #: Which towers Γ counts: ``completed`` (every block placed, the tower standing after each placement) or
    #: ``final`` (every trial's last tower, however the trial ended); see :mod:`overhang_framework.behaviour.gamma`.
    gamma_towers: str = "completed"


@dataclass
class Section:
    """One analysis's part of the report: markdown, and the files it wrote."""

    title: str
    text: str
    files: list[str] = field(default_factory=list)
    seconds: float = 0.0

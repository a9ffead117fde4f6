"""Every behaviour analysis of a log at once: Table 1, order dependency Γ (Fig. 3b), trajectory flows
(Fig. 3a) and physical prediction by construction stage (Fig. 4), written as ``report.md``, one CSV per
table and one PNG per figure (all written atomically).

Groups: a record's group is its ``condition``, except that records whose ``source`` is ``model`` are
grouped by their model label, the participant id before its first ``/`` (``veridical-myopic/0`` is in
group ``veridical-myopic``). People, simulated participants and models therefore sit side by side in
every table and figure. Two groups are compared with permutation tests: ``time_limited`` against
``unconstrained`` when both are present (or the only two groups, whatever their names), or the pair
given.

The log is read in its canonical order (participant, trial, step: :func:`~overhang_framework.behaviour.log.read_log`)
and every analysis takes a trial's last record as its last step, so the report is the same for any order
of the log's lines. Table 1 and Γ open with their finding: the direction, whether it is credible
(:data:`ALPHA`) and whether it matches the paper (:func:`finding`).

The statistics every analysis shares are here: :func:`mean_sem`, :func:`permutation_p` (SciPy's
``permutation_test``, independent samples, difference of means, two-sided, seeded) and
:func:`bootstrap_ci` (participants resampled with replacement, seeded).
"""

from __future__ import annotations

import json

import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.results import atomic_output, atomic_write_text, staged_files

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


def build_world(overrides: Sequence[str]):
    """The world of the run config composed with ``overrides``, through the plugin registry."""
    from overhang_framework.check import build_world as build

    return build(list(overrides))


def completeness(df: pd.DataFrame, gamma_towers: str = "completed") -> list[str]:
    """What the log lacks, one line each: missing trials, trials that ended early, timeouts, trajectories.
    ``gamma_towers`` (:attr:`Settings.gamma_towers`) says whether Γ counts the towers that fell."""
    from overhang_framework.behaviour.log import last_records

    notes = []
    tasks = df["task_id"].nunique()
    trials = df.groupby("participant")["trial"].nunique()
    short = trials[trials < tasks]
    if len(short):
        notes.append(f"{len(short)} of {len(trials)} participants did fewer trials than the {tasks} tasks in the log "
                     f"(fewest: {int(short.min())}); per-participant sums (total reward) cover the trials they did, "
                     "reward per trial compares them fairly.")
    last = last_records(df)
    placed = (last["step"] == last["sequence"].map(len) - 1) & ~last["timed_out"]
    fell = (last["stable"] == False).fillna(False).astype(bool) & placed  # noqa: E712
    early = int((~placed).sum())
    counted = "Γ counts every trial's final tower" if gamma_towers == "final" else "Γ counts completed towers only"
    if early:
        timeouts = int(last["timed_out"].sum())
        notes.append(f"{early} of {len(last)} trials ended before their last block "
                     f"({timeouts} on a timeout, {early - timeouts} on a collapse); {counted}.")
    if fell.sum():
        n = int(fell.sum())
        notes.append(f"{n} trial{'s' if n != 1 else ''} placed every block but the last placement toppled the tower: "
                     + ("Γ counts the fallen tower (`--gamma-towers final`)." if gamma_towers == "final" else
                        "not a completed tower, so not in Γ (`--gamma-towers final` counts it)."))
    timeouts = int(df["timed_out"].sum())
    if timeouts:
        notes.append(f"{timeouts} record{' is a timeout' if timeouts == 1 else 's are timeouts'} (no placement): "
                     "timeouts count in decision time and end their trial with reward 0; flows and Fig. 4 skip them.")
    if df["trajectory"].isna().all():
        notes.append("the log has no mouse trajectories (`trajectory`); no analysis here needs them "
                     "(the flows are drawn from placements).")
    elif df["trajectory"].isna().any():
        notes.append(f"{int(df['trajectory'].isna().sum())} of {len(df)} records have no mouse trajectory; "
                     "no analysis here needs them.")
    return notes


def _number(value):
    return None if pd.isna(value) else float(value)


def summary(out: Path, sections: dict[str, Section], seconds: float, settings: Settings,
            tasks: int) -> dict:
    """The report's headline figures as one JSON object (``summary.json``), for scripts and the docs' checks.

    ``table1[metric][group]`` holds ``mean``, ``sem`` and ``n``, ``table1[metric]["p"]`` the test's p;
    ``gamma[group]`` the mean and SEM across participants and tasks and ``gamma["p"]``, for the towers Γ
    counts (``gamma["reading"]``: ``completed`` or ``final``), and ``gamma["readings"][reading]`` the same
    for each reading; ``tasks`` the number of tasks in the log;
    ``lateral[group][measure]`` the mean, SEM and n across participants of each lateral measure of the flows
    (``abs_x``, ``abs_x_late``, ``step_x``: :func:`overhang_framework.behaviour.flows.lateral`);
    ``fig4[group][predictor]`` the mean log-likelihood of the executed placements; ``seconds`` each
    analysis's time and ``total``.
    """
    data: dict[str, Any] = {"seconds": {n: round(s.seconds, 3) for n, s in sections.items()}}
    data["seconds"]["total"] = round(seconds, 3)
    data["tasks"] = tasks
    if (out / "table1.csv").exists() and "table1" in sections:
        table: dict[str, dict] = {}
        for row in pd.read_csv(out / "table1.csv").itertuples():
            entry = table.setdefault(row.metric, {"p": _number(row.p)})
            entry[row.group] = {"mean": _number(row.mean), "sem": _number(row.sem), "n": int(row.n)}
        data["table1"] = table
    if (out / "gamma.csv").exists() and "gamma" in sections:
        readings: dict[str, dict[str, Any]] = {}
        for row in pd.read_csv(out / "gamma.csv").itertuples():
            gamma = readings.setdefault(row.reading, {})
            gamma["p"] = _number(row.p)
            gamma[row.group] = {"participants_mean": _number(row.gamma_participants_mean),
                                "participants_sem": _number(row.gamma_participants_sem),
                                "tasks_mean": _number(row.gamma_tasks_mean), "tasks_sem": _number(row.gamma_tasks_sem),
                                "towers": int(row.towers)}
        data["gamma"] = {**readings[settings.gamma_towers], "reading": settings.gamma_towers, "readings": readings}
    if (out / "fig3a_lateral.csv").exists() and "flows" in sections:
        people = pd.read_csv(out / "fig3a_lateral.csv")
        data["lateral"] = {g: {c: dict(zip(("mean", "sem"), map(_number, mean_sem(at[c]))), n=int(at[c].notna().sum()))
                               for c in ("abs_x", "abs_x_late", "step_x")}
                           for g, at in people.groupby("group", sort=True)}
    if (out / "fig4_placements.csv").exists() and "prediction" in sections:
        per = pd.read_csv(out / "fig4_placements.csv")
        cols = [c for c in per.columns if c.startswith("ll_")]
        data["fig4"] = {g: {c[3:]: float(v) for c, v in row.items()}
                        for g, row in per.groupby("group")[cols].mean().iterrows()}
    return data


def run(paths: Sequence[str | Path], out: str | Path, settings: Settings,
        log: Callable[[str], None] = lambda s: None) -> dict[str, Section]:
    """Read the logs in ``paths``, run the analyses of ``settings.only`` and write everything into ``out``.

    Returns the sections by analysis name; ``report.md`` holds them all.
    """
    from overhang_framework.behaviour.log import in_step_order, read_log, require_records

    started = time.perf_counter()
    if settings.gamma_towers not in GAMMA_TOWERS:
        from overhang_framework.errors import OverhangError

        raise OverhangError(f"--gamma-towers: unknown reading {settings.gamma_towers!r}; "
                            f"readings: {', '.join(GAMMA_TOWERS)}")
    from overhang_framework.preflight import check_writable

    df = with_groups(in_step_order(require_records(read_log(list(paths)), paths)))
    check_writable(out, "--out DIR")
    groups = list(df["group"].unique())
    compare = settings.compare or default_compare(groups)
    if settings.compare:
        missing = [g for g in settings.compare if g not in groups]
        if missing:
            from overhang_framework.errors import OverhangError

            raise OverhangError(f"--compare: no group {' or '.join(map(repr, missing))} in the log; "
                                f"groups: {', '.join(sorted(groups))}")
    order = group_order(groups, compare)
    sections: dict[str, Section] = {}
    world = None
    if any(a in settings.only for a in ("gamma", "flows", "prediction")):
        try:
            from overhang_framework.behaviour.prediction import targets_predictor

            world = build_world([o for o in settings.world_overrides if not targets_predictor(o)])
        except Exception as exc:  # a bad override or parameter: one line, as the main job reports it
            from overhang_framework.errors import OverhangError

            raise OverhangError(f"--world: {' '.join(str(exc).split()) or type(exc).__name__}") from None
    with staged_files(out) as staging:  # every file or none
        try:
            for name in ANALYSES:
                if name not in settings.only:
                    continue
                t0 = time.perf_counter()
                log(f"{name}...")
                if name == "table1":
                    from overhang_framework.behaviour import table1

                    sec = table1.section(df, staging, order, compare, settings)
                elif name == "gamma":
                    from overhang_framework.behaviour import gamma

                    sec = gamma.section(df, staging, order, compare, settings, world)
                elif name == "flows":
                    from overhang_framework.behaviour import flows

                    sec = flows.section(df, staging, order, settings, world, compare)
                else:
                    from overhang_framework.behaviour import prediction

                    sec = prediction.section(df, staging, order, compare, settings, world)
                sec.seconds = time.perf_counter() - t0
                sections[name] = sec
                log(f"{name}: {sec.seconds:.1f} s")
        finally:
            close = getattr(getattr(world, "backend", None), "close", None)
            if close is not None:
                close()
        write_report(df, staging, order, compare, settings, sections, paths, time.perf_counter() - started)
    return sections


def write_report(df, out: Path, order, compare, settings: Settings, sections: dict[str, Section],
                 paths, seconds: float) -> None:
    from overhang_framework.behaviour.log import describe

    people = df.drop_duplicates("participant")
    lines = ["# Behaviour analysis", "",
             f"Logs: {', '.join(str(p) for p in paths)}; {describe(df)}.", "",
             "Groups (a record's `condition`; records with source `model` by their model label, the participant "
             "id before '/'):", "",
             markdown_table(["group", "participants", "trials", "placements"],
                            [[g, int((people["group"] == g).sum()),
                              len(df[df["group"] == g].drop_duplicates(["participant", "trial"])),
                              int(((df["group"] == g) & ~df["timed_out"]).sum())] for g in order]), ""]
    lines.append(f"Compared groups: {compare[0]} vs {compare[1]}." if compare else
                 "No two groups to compare (give `--compare A B`): no p-values.")
    world = " ".join(settings.world_overrides) or "the default world (tiered physics)"
    lines += ["", f"World: {world}. Seed {settings.seed}.", "", "## What the log lacks", ""]
    notes = completeness(df, settings.gamma_towers)
    lines += [f"- {n}" for n in notes] if notes else ["Nothing: every participant did every task to its end."]
    skipped = [a for a in ANALYSES if a not in sections]
    if skipped:
        lines += ["", f"Not run (`--only`): {', '.join(skipped)}."]
    for name, sec in sections.items():
        lines += ["", f"## {sec.title}", "", sec.text.strip()]
        if sec.files:
            lines += ["", "Files: " + ", ".join(f"`{f}`" for f in sec.files) + "."]
            lines += [line for f in sec.files if f.endswith(".png") for line in ("", f"![{f}]({f})")]
    lines += ["", "## Time", "",
              markdown_table(["analysis", "seconds"], [[n, f"{s.seconds:.1f}"] for n, s in sections.items()]
                             + [["total (reading and writing included)", f"{seconds:.1f}"]]), ""]
    atomic_write_text(out / "report.md", "\n".join(lines))
    data = summary(out, sections, seconds, settings, int(df["task_id"].nunique()))
    atomic_write_text(out / "summary.json", json.dumps(data, indent=1, sort_keys=True) + "\n")

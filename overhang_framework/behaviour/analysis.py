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

The statistics every analysis shares are in :mod:`~overhang_framework.behaviour.shared`: :func:`mean_sem`,
:func:`permutation_p` (SciPy's ``permutation_test``, independent samples, difference of means, two-sided,
seeded) and :func:`bootstrap_ci` (participants resampled with replacement, seeded).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import pandas as pd

from overhang_framework.behaviour.shared import (  # noqa: F401  (the sections' shared pieces, importable from here as before)
    ALPHA,
    ANALYSES,
    DEFAULT_COMPARE,
    Finding,
    GAMMA_TOWERS,
    GROUP_COLOURS,
    OTHER_COLOURS,
    Section,
    Settings,
    _diff_of_means,
    _direction,
    bootstrap_ci,
    colour,
    default_compare,
    finding,
    fmt_ms,
    fmt_p,
    group_of,
    group_order,
    is_paper_comparison,
    markdown_table,
    mean_sem,
    p_is,
    paper_p_credible,
    paper_pair,
    permutation_p,
    save_figure,
    with_groups,
    write_csv,
)
from overhang_framework.results import atomic_write_text, staged_files


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

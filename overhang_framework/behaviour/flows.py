"""Trajectory flows for one task (the paper's Fig. 3a): where each group placed each block, step by step.

For the chosen task, every executed placement is a node ``(x rounded to the world's grid, layer)`` of
its step; the transitions of each trial from step to step (from the ground block at step 0) are the
edges. Each trial is mirrored, if needed, so that its tower extends to the right (the block reaching
furthest from the centre has x >= 0), as the task is symmetric. An edge's opacity is its transition
probability (trials taking it / trials leaving its start node); its width the share of the group's
trials taking it; its colour the group's when the tower stood after the placement it leads to and
crimson when it fell. The optimal path of the task under the world's physics is drawn in black when
``overhang_framework/data/optima.json`` holds it.

Task: ``--flow-task`` or, by default, the paper's example sequence (0.6, 1.8, 1.2, 1.8, 0.6, 1.8) when
the log holds it (the first such task id in sorted order), else the task played in the most trials.

The paper reads the flows in words: "time-constrained participants exhibited a stronger tendency toward
vertical stacking; early differences remain modest ..., with divergence clearer later", and unconstrained
ones "explored more laterally extended configurations". :func:`lateral` makes that a test over every task:
each participant's mean distance |x| of their placements from the centre of the ground block, over all
placements and over the later ones (from step :data:`LATE_STEP` on), and the mean sideways step |Δx| from
the block placed before (the ground block for the first); the groups' later |x| are compared with the
analysis's permutation test (``fig3a_lateral.csv``).
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.behaviour.shared import (Section, colour, finding, fmt_ms, markdown_table, mean_sem, p_is,
                                                permutation_p, save_figure, write_csv)
from overhang_framework.behaviour.log import in_step_order, last_records

EXAMPLE_SEQUENCE = (0.6, 1.8, 1.2, 1.8, 0.6, 1.8)
CRIMSON = "#dc143c"
#: The first of the later placements in :func:`lateral` (steps count placements from 1; a task of six blocks has
#: five): the paper sees the groups diverge later in the trial.
LATE_STEP = 3


def choose_task(df: pd.DataFrame, wanted: Optional[str] = None) -> str:
    """The task of the flows: ``wanted``, else the paper's example sequence, else the most-played task."""
    if wanted is not None:
        if wanted not in set(df["task_id"]):
            from overhang_framework.errors import OverhangError

            raise OverhangError(f"--flow-task: no task {wanted!r} in the log; tasks: "
                                f"{', '.join(sorted(set(df['task_id'])))}")
        return wanted
    example = df[df["sequence"].map(lambda s: tuple(round(w, 6) for w in s) == EXAMPLE_SEQUENCE)]
    if len(example):
        return str(sorted(set(example["task_id"]))[0])
    trials = df.drop_duplicates(["participant", "trial"])["task_id"].value_counts()
    return str(sorted(trials.index, key=lambda t: (-trials[t], t))[0])


def optimal_path(sequence: Sequence[float], task_id: str, world) -> Optional[dict]:
    """The stored optimum of ``sequence``: under ``world``'s physics and resolution when stored, else under
    another physics (its ``physics`` field says which); None when none is stored."""
    from overhang_framework.interfaces import Task
    from overhang_framework.optimum import load_optima, optimum_key

    try:
        optima = load_optima()
    except ValueError:
        return None
    exact = optima.get(optimum_key(Task(task_id, tuple(sequence)), world))
    if exact is not None:
        return {**exact, "same_physics": True}
    wanted = [round(w, 6) for w in sequence]
    for row in optima.values():
        if [round(w, 6) for w in row.get("sequence", [])] == wanted and "actions" in row:
            return {**row, "same_physics": False}
    return None


def _mirror(xs: list[float], widths: list[float]) -> float:
    """+1 or -1: the sign that puts the block reaching furthest from the centre on the right."""
    if not xs:
        return 1.0
    i = max(range(len(xs)), key=lambda k: abs(xs[k]) + widths[k] / 2)
    return -1.0 if xs[i] < 0 else 1.0


def transitions(df: pd.DataFrame, task: str, resolution: float) -> pd.DataFrame:
    """One row per (group, step, from node, to node): ``count``, ``from_count``, ``probability``,
    ``fell`` (towers that fell after the placement), ``trials`` (of the group on the task); the same rows in
    the same order for any order of ``df``'s rows."""
    rows = []
    sub = in_step_order(df[df["task_id"] == task])
    for g, gd in sub.groupby("group", sort=False):
        trials = gd.groupby(["participant", "trial"], sort=False)
        n_trials = trials.ngroups
        edges: Counter = Counter()
        falls: Counter = Counter()
        starts: Counter = Counter()
        for _, t in trials:
            t = t[~t["timed_out"]].sort_values("step")
            sign = _mirror(list(t["x"]), list(t["width"]))
            prev = (0.0, 0)
            for step, x, layer, stable in zip(t["step"], t["x"], t["layer"], t["stable"]):
                node = (round(round(sign * x / resolution) * resolution, 6) + 0.0, int(layer))
                edges[(int(step), prev, node)] += 1
                starts[(int(step), prev)] += 1
                falls[(int(step), prev, node)] += int(stable is False or stable == False)  # noqa: E712
                prev = node
        for (step, a, b), c in edges.items():
            rows.append({"group": g, "step": step, "from_x": a[0], "from_layer": a[1], "to_x": b[0], "to_layer": b[1],
                         "count": c, "from_count": starts[(step, a)], "probability": c / starts[(step, a)],
                         "fell": falls[(step, a, b)], "trials": n_trials})
    return pd.DataFrame(rows, columns=["group", "step", "from_x", "from_layer", "to_x", "to_layer", "count",
                                       "from_count", "probability", "fell", "trials"])


def lateral(df: pd.DataFrame) -> pd.DataFrame:
    """One row per participant (sorted by group and participant, so the same for any order of ``df``'s rows):
    ``placements``, ``abs_x`` (mean |x| of the placements), ``abs_x_late`` (the same from step
    :data:`LATE_STEP` on; NaN without such a placement) and ``step_x`` (mean |Δx| from the block placed before,
    the ground block at x = 0 for the first). Timed-out records place nothing and are left out."""
    placed = df[~df["timed_out"].astype(bool)]
    rows = []
    for (g, pid), d in placed.groupby(["group", "participant"], sort=True):
        d = d.sort_values(["trial", "step"])
        x = d["x"].to_numpy(dtype=float)
        before = d.groupby("trial", sort=False)["x"].shift(1).fillna(0.0).to_numpy(dtype=float)
        late = d["step"].to_numpy() >= LATE_STEP
        rows.append({"group": g, "participant": pid, "placements": len(d), "abs_x": float(np.abs(x).mean()),
                     "abs_x_late": float(np.abs(x[late]).mean()) if late.any() else float("nan"),
                     "step_x": float(np.abs(x - before).mean())})
    return pd.DataFrame(rows, columns=["group", "participant", "placements", "abs_x", "abs_x_late", "step_x"])


def _lateral_text(people: pd.DataFrame, order, compare, settings) -> str:
    """The lateral extent's finding (with two groups compared) and its table."""
    rows = []
    for g in order:
        at = people[people["group"] == g]
        if len(at):
            rows.append([g, len(at), *(fmt_ms(*mean_sem(at[c]), 3) for c in ("abs_x", "abs_x_late", "step_x"))])
    if not rows:
        return "**Lateral extent, every task.** No placement in the log."
    text = "**Lateral extent, every task.**"
    if compare and all((people["group"] == g).any() for g in compare):
        def p_of(column: str) -> float:
            a, b = (people.loc[people["group"] == g, column].to_numpy(dtype=float) for g in compare)
            return permutation_p(a, b, settings.n_resamples, settings.seed)

        ours = tuple(mean_sem(people.loc[people["group"] == g, "abs_x_late"])[0] for g in compare)
        said = finding(f"the mean |x| of placements from step {LATE_STEP} on", compare, ours, p_of("abs_x_late"),
                       None, lambda v: f"{v:.3f} m",
                       no_paper="; the paper shows the flows of one task and says it in words (Fig. 3a: "
                                "time-constrained people stack more vertically, the divergence clearer later)")
        text += (f" **Finding** (credible: permutation p < .05): {said.text[0].upper() + said.text[1:]}. Over all "
                 f"steps: {p_is(p_of('abs_x'))}; {settings.n_resamples} resamples.")
    return (text + "\n\n" + markdown_table(["group", "participants", "mean \\|x\\| of placements",
                                            f"mean \\|x\\| from step {LATE_STEP} on", "mean sideways step \\|Δx\\|"],
                                           rows)
            + "\n\nMean ± SEM across participants of each participant's mean over their placements, in metres; x is "
              "a block's centre, the ground block's at 0; |Δx| is from the block placed just before (the ground block "
              "for the first). File: `fig3a_lateral.csv`.")


def _y(x: float, layer: int, step: int) -> float:
    """Where a node is drawn: its x, nudged by how far its layer is below a straight stack's."""
    return x + 0.04 * (layer - step)


def figure(edges: pd.DataFrame, order: Sequence[str], task: str, sequence: Sequence[float],
           optimum: Optional[dict], best: dict):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    groups = [g for g in order if (edges["group"] == g).any()]
    steps = len(sequence) - 1
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups) + 1, 5.2), sharey=True, squeeze=False)
    opt_nodes = None
    if optimum:
        xs = [a[0] for a in optimum["actions"]]
        sign = _mirror(xs, list(sequence[1:]))
        opt_nodes = [(0.0, 0)] + [(sign * x, int(l)) for x, l in optimum["actions"]]
    for ax, g in zip(axes[0], groups):
        e = edges[edges["group"] == g]
        c = colour(g, order)
        trials = int(e["trials"].iloc[0])
        for r in e.itertuples():
            y0, y1 = _y(r.from_x, r.from_layer, r.step - 1), _y(r.to_x, r.to_layer, r.step)
            fell = r.fell / r.count > 0.5
            ax.plot([r.step - 1, r.step], [y0, y1], color=CRIMSON if fell else c,
                    alpha=float(np.clip(r.probability, 0.08, 1.0)), lw=0.8 + 7 * r.count / trials,
                    solid_capstyle="round", zorder=2)
        nodes = e.groupby(["step", "to_x", "to_layer"])["count"].sum().reset_index()
        ax.scatter(nodes["step"], [_y(x, l, s) for s, x, l in zip(nodes["step"], nodes["to_x"], nodes["to_layer"])],
                   s=8 + 120 * nodes["count"] / trials, color=c, edgecolor="white", lw=0.5, zorder=3)
        for s, x, l, n in zip(nodes["step"], nodes["to_x"], nodes["to_layer"], nodes["count"]):
            if n / trials >= 0.15:
                ax.text(s + 0.08, _y(x, l, s), f"L{l}", fontsize=6.5, va="center", zorder=5)
        ax.scatter([0], [0], s=60, color="black", marker="s", zorder=3)
        mean_x = [0.0] + [float(np.average(nodes.loc[nodes["step"] == k, "to_x"],
                                           weights=nodes.loc[nodes["step"] == k, "count"]))
                          if (nodes["step"] == k).any() else np.nan for k in range(1, steps + 1)]
        ax.plot(range(steps + 1), mean_x, ls=":", lw=2.5, color="dimgrey", zorder=4)
        if opt_nodes:
            ax.plot(range(len(opt_nodes)), [_y(x, l, k) for k, (x, l) in enumerate(opt_nodes)], "k--", lw=1.4,
                    marker="*", ms=9, zorder=4)
        ax.set_title(f"{g.replace('_', ' ')}: {trials} trials, best reward {best.get(g, float('nan')):.2f}",
                     fontsize=9)
        ax.set_xticks(range(steps + 1), ["ground"] + [f"{k}\n(w {sequence[k]:g})" for k in range(1, steps + 1)],
                      fontsize=8)
        ax.set_xlabel("step (width placed)")
        ax.grid(alpha=0.25)
    axes[0][0].set_ylabel("x of the placed block (mirrored: tower extends right)\n"
                          "nudged by 0.04 per layer below a stack")
    handles = [Line2D([], [], color="grey", lw=3, label="stood after the placement"),
               Line2D([], [], color=CRIMSON, lw=3, label="tower fell after it")]
    if opt_nodes:
        under = "" if optimum.get("same_physics") else f", {optimum.get('physics')} physics"
        handles.append(Line2D([], [], color="black", ls="--", marker="*",
                              label=f"optimum (overhang {optimum['optimum']:.2f}{under})"))
    handles.append(Line2D([], [], color="grey", ls=":", lw=2.5, label="group's mean x per step"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=8, frameon=False)
    fig.suptitle(f"Placement flows, task {task} (widths {', '.join(f'{w:g}' for w in sequence)}); "
                 "opacity = transition probability, width = share of trials, L = layer", fontsize=9)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    return fig


def section(df: pd.DataFrame, out: Path, order, settings, world, compare=None) -> Section:
    people = lateral(df)
    write_csv(people, out / "fig3a_lateral.csv")
    task = choose_task(df, settings.flow_task)
    sequence = list(df.loc[df["task_id"] == task, "sequence"].iloc[0])
    resolution = float(getattr(world, "resolution", 0.1))
    edges = transitions(df, task, resolution)
    write_csv(edges, out / "fig3a_flows.csv")
    files = ["fig3a_flows.csv", "fig3a_lateral.csv"]
    optimum = optimal_path(sequence, task, world)
    last = last_records(df[df["task_id"] == task])
    best = last.groupby("group")["reward"].max().to_dict()
    rows = []
    for g in order:
        e = edges[edges["group"] == g]
        if not len(e):
            continue
        placed = e[e["step"] == 1]["count"].sum()
        final = e[e["step"] == len(sequence) - 1]
        mean_x = (e["to_x"].abs() * e["count"]).sum() / e["count"].sum()
        rows.append([g, int(e["trials"].iloc[0]), int(placed), int(final["count"].sum() - final["fell"].sum()),
                     f"{mean_x:.2f}", f"{best.get(g, float('nan')):.2f}"])
    text = (_lateral_text(people, order, compare, settings) + "\n\n**The flows of one task.** "
            f"Task `{task}` (widths {', '.join(f'{w:g}' for w in sequence)}); "
            + (f"optimum under this world: overhang {optimum['optimum']:.2f}." if optimum and optimum["same_physics"]
               else f"no stored optimum under this world's physics; drawn: the optimum under the {optimum['physics']} "
                    f"physics (overhang {optimum['optimum']:.2f}), which may not stand under this world's."
               if optimum else "no stored optimum for this task.") + "\n\n"
            + markdown_table(["group", "trials", "first placements", "finished standing", "mean \\|x\\| of placements",
                              "best reward"], rows)
            + f"\n\nRules: nodes are (x rounded to the grid of {resolution:g}, layer) per step; each trial is mirrored "
              "so that its tower extends to the right; opacity = transition probability, width = share of the "
              "group's trials, crimson = the tower fell after that placement; timed-out records place nothing.")
    if len(edges):
        save_figure(figure(edges, order, task, sequence, optimum, best), out / "fig3a_flows.png")
        files.insert(0, "fig3a_flows.png")
    else:
        text += "\n\nNo placement of this task in the log: no figure."
    return Section("Trajectory flows (Fig. 3a)", text, files)

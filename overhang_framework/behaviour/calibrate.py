"""A cohort calibrated to the paper's people, by simulation: a library of simulated participants drawn from
a wide proposal, reweighted to any candidate cohort, and fitted to Table 1 and Γ per condition.

    python -m overhang_framework.participants cohort=proposal conditions.time_limited.time_limit=null \\
        world.physics=static predictor=hybrid jobs=2 hydra.run.dir=runs/library          # resumable
    python -m overhang_framework.behaviour.calibrate library runs/library --out runs/library/trials.csv
    python -m overhang_framework.behaviour.calibrate fit runs/library/trials.csv --out runs/calibration

**The library.** Every participant of ``cohort=proposal`` draws its depth, σ, β, lapse and switch point
from wide distributions and does every task. It runs without the time limit (the time-limited condition
keeps its budget of predictor calls, which changes how its searches go), so no trial ends on a timeout:
timeouts are applied afterwards, exactly, from the calls of each decision. ``library`` turns the log
into one row per trial: the participant's parameters, the reward, whether the tower stood, Γ of the
completed tower, and the predictor calls of each decision.

**A candidate cohort** gives each condition a depth distribution over 1, 2 and 3, lognormal σ and β
around medians of their own, a beta lapse around a mean of its own, and a decision-time model
``(t0 + per_call * calls) * exp(noise * z)``. Its Table 1 and Γ are predicted without simulating
anything new: each library participant is weighted by the candidate's density of its parameters over the
proposal's (self-normalised importance sampling; the effective sample size says how far that can be
trusted), and the decision times, timeouts and their effect on rewards follow from the lognormal time
model in closed form.

**The fit** matches, per condition, the paper's reward per trial, stable proportion, average overhang,
decision time and Γ, each in units of the paper's SEM: a global search (SciPy's differential evolution,
seeded) for the best candidate, and an approximate Bayesian computation that keeps every candidate of a
seeded uniform draw whose five measures all lie within one SEM of the paper's (the paper's SEMs as
tolerances), as the region the data allow.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Optional, Sequence

import numpy as np
import pandas as pd
from scipy.special import expit, logit
from scipy.stats import norm

from overhang_framework.behaviour.participants import Distribution, TimeModel
from overhang_framework.errors import ConfigError, first_line
from overhang_framework.geometry import GRID_HALF_WIDTH

#: The measures the fit matches, per condition: the paper's (mean, SEM) (Table 1; Γ from Fig. 3b).
TARGETS = {
    "time_limited": {"reward_per_trial": (18.25 / 20, 0.57 / 20), "stable_pct": (70.2, 2.5),
                     "avg_overhang": (1.321, 0.023), "decision_time": (2.47, 0.07), "gamma": (0.15, 0.02)},
    "unconstrained": {"reward_per_trial": (19.57 / 20, 0.56 / 20), "stable_pct": (67.8, 2.1),
                      "avg_overhang": (1.460, 0.029), "decision_time": (7.27, 0.88), "gamma": (0.24, 0.03)},
}
METRICS = ("reward_per_trial", "stable_pct", "avg_overhang", "decision_time", "gamma")
#: The paper's time limit of the time-limited condition, seconds.
TIME_LIMITS = {"time_limited": 5.0, "unconstrained": None}
#: A candidate's free numbers per condition, with the box the search stays in.
FREE = (("depth2", -4.0, 4.0), ("depth3", -4.0, 4.0), ("log_sigma", math.log(0.01), math.log(0.2)),
        ("log_beta", math.log(0.5), math.log(30.0)), ("logit_lapse", logit(0.005), logit(0.25)),
        ("t0", 0.3, 6.0), ("per_call", 0.0, 0.2))
#: Fixed spreads of a candidate's distributions (the paper's cohort's): σ and β lognormal, lapse beta.
SIGMA_SPREAD, BETA_SPREAD, LAPSE_CONCENTRATION = 0.3, 0.5, 31.0
PARAMS = ("sigma", "depth", "beta", "lapse")
#: The axes that separate why towers fall from how far people aim (docs/participants.md): a library whose
#: participants draw one makes it a free number of every candidate, with the box the search stays in.
AXES = {"risk": ("logit_risk", logit(0.01), logit(0.94)), "percept": ("log_percept", math.log(0.002), math.log(0.2)),
        "hand": ("log_hand", math.log(0.002), math.log(0.2))}
#: Fixed spreads of the axes' distributions: risk beta (mean and this concentration), percept and hand lognormal.
RISK_CONCENTRATION, AXIS_SPREAD = 4.0, 0.8
#: The least effective sample (participants) a candidate's prediction may rest on.
MIN_ESS = 30.0


@dataclass(frozen=True)
class Candidate:
    """One condition's distributions: depth probabilities over 1, 2, 3, medians of σ and β, mean lapse, time model."""

    depth_p: tuple[float, float, float]
    sigma: float
    beta: float
    lapse: float
    t0: float
    per_call: float
    noise: float = 0.3
    #: The axes of :data:`AXES` the candidate draws: the mean risk, the medians of percept and hand.
    axes: tuple[tuple[str, float], ...] = ()
    #: The spreads of the axes' distributions: the risk's beta concentration, percept's and hand's lognormal sigma.
    risk_concentration: float = RISK_CONCENTRATION
    axis_spread: float = AXIS_SPREAD

    @classmethod
    def from_vector(cls, v: Sequence[float], noise: float = 0.3, axes: Sequence[str] = (),
                    risk_concentration: float = RISK_CONCENTRATION, axis_spread: float = AXIS_SPREAD) -> "Candidate":
        z = np.array([0.0, v[0], v[1]])
        p = np.exp(z - z.max())
        p /= p.sum()
        drawn = tuple((name, float(expit(x) if name == "risk" else math.exp(x))) for name, x in zip(axes, v[7:]))
        return cls(tuple(float(x) for x in p), float(math.exp(v[2])), float(math.exp(v[3])), float(expit(v[4])),
                   float(v[5]), float(v[6]), noise, drawn, risk_concentration, axis_spread)

    def distributions(self) -> dict[str, Distribution]:
        k = LAPSE_CONCENTRATION
        out = {"depth": Distribution("categorical", ((1, 2, 3), self.depth_p)),
               "sigma": Distribution("lognormal", (self.sigma, SIGMA_SPREAD)),
               "beta": Distribution("lognormal", (self.beta, BETA_SPREAD)),
               "lapse": Distribution("beta", (self.lapse * k, (1 - self.lapse) * k))}
        k = self.risk_concentration
        for name, value in self.axes:
            out[name] = Distribution("beta", (value * k, (1 - value) * k)) if name == "risk" \
                else Distribution("lognormal", (value, self.axis_spread))
        return out

    @property
    def time(self) -> TimeModel:
        return TimeModel(self.t0, self.per_call, self.noise)

    @property
    def mean_depth(self) -> float:
        return float(np.dot(self.depth_p, (1, 2, 3)))

    def config(self) -> dict:
        """The ``cohort.by_condition.<condition>`` node of this candidate."""
        k = LAPSE_CONCENTRATION
        return {"parameters": {
            "depth": {"dist": "categorical", "values": [1, 2, 3], "p": [round(p, 4) for p in self.depth_p[:2]]
                      + [round(1 - round(self.depth_p[0], 4) - round(self.depth_p[1], 4), 4)]},
            "sigma": {"dist": "lognormal", "median": round(self.sigma, 5), "sigma": SIGMA_SPREAD},
            "beta": {"dist": "lognormal", "median": round(self.beta, 4), "sigma": BETA_SPREAD},
            "lapse": {"dist": "beta", "a": round(self.lapse * k, 4), "b": round((1 - self.lapse) * k, 4)},
            **{name: ({"dist": "beta", "a": round(value * self.risk_concentration, 4),
                       "b": round((1 - value) * self.risk_concentration, 4)} if name == "risk"
                      else {"dist": "lognormal", "median": round(value, 5), "sigma": self.axis_spread})
               for name, value in self.axes}},
            "decision_time": {"t0": round(self.t0, 4), "per_call": round(self.per_call, 5), "noise": self.noise}}


# ----------------------------------------------------------------------------------------------- measured

PEOPLE_COLUMNS = ("participant", "condition", *METRICS)
"""The columns of a saved table of per-participant measures (``measure --save``)."""
#: Each measure's possible values, and what they are: a reward and an overhang reach at most the grid's half width.
RANGES = {"reward_per_trial": (0.0, GRID_HALF_WIDTH, "task units"), "stable_pct": (0.0, 100.0, "a percentage"),
          "avg_overhang": (0.0, GRID_HALF_WIDTH, "task units"), "decision_time": (0.0, math.inf, "seconds"),
          "gamma": (0.0, 1.0, "a share of the orders")}


def people_measures(df: pd.DataFrame, world) -> pd.DataFrame:
    """One row per participant of a simulated (or real) cohort's log: its condition and the five measures
    (reward per trial, stable proportion, average overhang of successful trials, decision time, Γ of completed
    towers), as the paper's Table 1 and Fig. 3b take them per person."""
    from overhang_framework.behaviour.analysis import with_groups
    from overhang_framework.behaviour.gamma import per_participant as gamma_people
    from overhang_framework.behaviour.gamma import tower_gammas
    from overhang_framework.behaviour.table1 import per_participant

    df = with_groups(df)
    people = per_participant(df).set_index("participant")
    gammas = gamma_people(tower_gammas(df, world)).set_index("participant")["gamma"]
    people["gamma"] = gammas.reindex(people.index)
    condition = df.drop_duplicates("participant").set_index("participant")["condition"]
    people["condition"] = condition.reindex(people.index)
    return people.reset_index()[list(PEOPLE_COLUMNS)].sort_values("participant", kind="stable").reset_index(drop=True)


def measured_people(people: pd.DataFrame) -> dict[str, dict[str, tuple[float, float]]]:
    """The ten measures from per-participant rows (:func:`people_measures`): per condition, the mean and SEM
    over participants of each measure."""
    out: dict[str, dict[str, tuple[float, float]]] = {}
    for name in sorted(set(people["condition"]),
                       key=lambda c: (c not in TARGETS, list(TARGETS).index(c) if c in TARGETS else 0, c)):
        group = people[people["condition"] == name]
        row = {}
        for metric in METRICS:
            v = group[metric].dropna().to_numpy(dtype=float)
            row[metric] = (float(v.mean()) if len(v) else math.nan,
                           float(v.std(ddof=1) / math.sqrt(len(v))) if len(v) > 1 else math.nan)
        out[name] = row
    return out


def measured(df: pd.DataFrame, world) -> dict[str, dict[str, tuple[float, float]]]:
    """The ten measures of a simulated (or real) cohort's log, measured directly: per condition, the mean and
    SEM over participants of reward per trial, stable proportion, average overhang of successful trials,
    decision time and Γ (of completed towers), as the paper's Table 1 and Fig. 3b report them."""
    return measured_people(people_measures(df, world))


def read_people(path: Path) -> pd.DataFrame:
    """A table of per-participant measures that ``measure --save`` wrote; :class:`ConfigError` naming what
    is wrong when it is not one."""
    try:
        people = pd.read_csv(path, dtype={"participant": str, "condition": str})
    except (OSError, ValueError) as err:
        raise ConfigError(f"{path}: not a readable CSV of per-participant measures ({first_line(err)})") from None
    missing = [c for c in PEOPLE_COLUMNS if c not in people.columns]
    if missing:
        raise ConfigError(f"{path}: not a table of per-participant measures; it lacks {', '.join(missing)} "
                          f"(expected columns: {', '.join(PEOPLE_COLUMNS)}, as measure --save writes them)")
    if people.empty:
        raise ConfigError(f"{path}: no participants (a header and no rows)")
    blank = people["participant"].isna() | people["condition"].isna()
    if blank.any():
        raise ConfigError(f"{path}: line {int(blank.to_numpy().argmax()) + 2} has no participant or no condition")
    if people["participant"].duplicated().any():
        raise ConfigError(f"{path}: participant {people.loc[people['participant'].duplicated(), 'participant'].iloc[0]} "
                          "is listed twice")
    for column in METRICS:
        values = pd.to_numeric(people[column], errors="coerce")
        bad = values.isna() & people[column].notna()
        if bad.any():
            raise ConfigError(f"{path}: {column} on line {int(bad.to_numpy().argmax()) + 2} is "
                              f"{people[column][bad].iloc[0]!r}, not a number")
        low, high, what = RANGES[column]
        outside = (values < low) | (values > high)
        if outside.any():
            line = int(outside.to_numpy().argmax())
            allowed = f"at least {low:g}" if math.isinf(high) else f"from {low:g} to {high:g}"
            raise ConfigError(f"{path}: {column} on line {line + 2} is {values.iloc[line]:g}, which no participant "
                              f"can have: it is {allowed} ({what})")
        people[column] = values
    return people


Measured = Mapping[str, Mapping[str, tuple[float, float]]]


def measured_table(result: Measured | Sequence[Measured]) -> str:
    """The measures beside the paper's, with each one's distance in the paper's SEMs (a markdown table).

    ``result`` is one run's :func:`measured`, or several runs' (the seeds of a cohort, or one run a
    condition): a condition that several runs have is given as the mean of their means, its distance is
    that mean's, and a last column gives each run's own distance, in the order of the runs."""
    from overhang_framework.behaviour.analysis import markdown_table

    runs = [result] if isinstance(result, Mapping) else list(result)
    conditions: list[str] = []
    for one in runs:
        conditions += [c for c in one if c not in conditions]
    several = any(sum(c in one for one in runs) > 1 for c in conditions)

    def z(mean: float, paper) -> float:
        return (mean - paper[0]) / paper[1] if paper else math.nan

    rows = []
    for condition in conditions:
        have = [one[condition] for one in runs if condition in one]
        for metric in METRICS:
            paper = TARGETS.get(condition, {}).get(metric)
            means = [row[metric][0] for row in have]
            mean = float(np.mean(means))
            shown = f"{mean:.3f} ± {have[0][metric][1]:.3f}" if len(have) == 1 else \
                f"{mean:.3f} (mean of {len(have)} runs)"
            distance = z(mean, paper)
            row = [condition, metric, shown, f"{paper[0]:.3f} ± {paper[1]:.3f}" if paper else "",
                   "" if math.isnan(distance) else f"{distance:+.2f}"]
            if several:
                row.append(", ".join(f"{z(m, paper):+.2f}" for m in means) if paper and len(have) > 1 else "")
            rows.append(row)
    header = ["condition", "measure", "simulated", "paper", "distance (paper SEMs)"]
    return markdown_table(header + (["each run's distance"] if several else []), rows)


def measured_summary(results: Sequence[Measured]) -> dict:
    """The figures of :func:`measured_table` as numbers: per condition and measure the mean of the runs' means
    (``mean``), the number of runs, the paper's ``paper`` and ``sem``, the ``distance`` in the paper's SEMs and
    ``distance_md`` (in bold within one SEM, as the docs show it)."""
    out: dict = {}
    for condition in dict.fromkeys(c for one in results for c in one):
        have = [one[condition] for one in results if condition in one]
        out[condition] = {}
        for metric in METRICS:
            mean = float(np.mean([row[metric][0] for row in have]))
            paper = TARGETS.get(condition, {}).get(metric)
            entry = {"mean": mean, "runs": len(have)}
            if paper:
                z = (mean - paper[0]) / paper[1]
                entry.update(paper=paper[0], sem=paper[1], distance=z,
                             distance_md=f"**{z:+.2f}**" if abs(z) <= 1 else f"{z:+.2f}")
            out[condition][metric] = entry
    return out


#: How the figure of :func:`measured_figure` names each measure.
METRIC_LABELS = {"reward_per_trial": "reward per trial", "stable_pct": "stable (%)", "avg_overhang": "average overhang",
                 "decision_time": "decision time (s)", "gamma": "Γ"}


def _short_labels(labels: Sequence[str]) -> list[str]:
    """``labels`` without the part that they all begin with (cut at a ``-``, ``_`` or ``/``)."""
    if len(labels) < 2:
        return list(labels)
    shared = os.path.commonprefix(list(labels))
    cut = max(shared.rfind("-"), shared.rfind("_"), shared.rfind("/")) + 1
    return [label[cut:] or label for label in labels]


def measured_figure(results: Sequence[Measured], labels: Sequence[str], path: Path):
    """Draw the measures of ``results`` (one :func:`measured` a run) beside the paper's and write the PNG ``path``
    atomically: a row of panels per condition, a panel per measure; in each, the paper's mean with a band of one
    of its SEMs, and each run's mean with its SEM, left to right in the order of the runs (named by ``labels``).
    Returns the figure (closed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from overhang_framework.results import atomic_output

    conditions: list[str] = []
    for one in results:
        conditions += [c for c in one if c not in conditions]
    if not conditions:
        raise ConfigError("no condition to draw: the runs given have no participants")
    labels = _short_labels(labels)
    fig, axes = plt.subplots(len(conditions), len(METRICS), figsize=(2.6 * len(METRICS), 2.6 * len(conditions)),
                             squeeze=False)
    for row, condition in zip(axes, conditions):
        runs = [(label, one[condition]) for label, one in zip(labels, results) if condition in one]
        if len(runs) > 1:  # name the runs of a row by what differs between them
            runs = list(zip(_short_labels([label for label, _ in runs]), [one for _, one in runs]))
        for ax, metric in zip(row, METRICS):
            paper = TARGETS.get(condition, {}).get(metric)
            if paper:
                ax.axhspan(paper[0] - paper[1], paper[0] + paper[1], color="0.85", label="paper ± SEM")
                ax.axhline(paper[0], color="0.3", linewidth=1)
            x = np.arange(len(runs))
            ax.errorbar(x, [m[metric][0] for _, m in runs], yerr=[m[metric][1] for _, m in runs], fmt="o",
                        color="tab:blue", label="simulated ± SEM")
            ax.set_xticks(x, [label for label, _ in runs], rotation=20, ha="right", fontsize=8)
            ax.set_xlim(-0.6, len(runs) - 0.4)
            ax.set_title(f"{METRIC_LABELS[metric]}\n{condition.replace('_', '-')}", fontsize=9)
            ax.grid(axis="y", alpha=0.3)
    handles, names = axes[0][0].get_legend_handles_labels()
    fig.legend(handles, names, loc="upper center", ncol=2, fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0, 1, 0.95))
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return fig


def run_log(run_dir: Path) -> tuple[pd.DataFrame, Optional[int]]:
    """A participants run's log (``log.jsonl``), or, while the run goes on, the participants it has finished
    (``parts/``) with their number; :class:`ConfigError` when the directory has neither."""
    from overhang_framework.behaviour import read_log
    from overhang_framework.behaviour.log import to_frame
    from overhang_framework.behaviour.simulation import LOG, PARTS, _read_part

    run_dir = Path(run_dir)
    if (run_dir / LOG).exists():
        return read_log(run_dir / LOG), None
    parts = [_read_part(p) for p in sorted((run_dir / PARTS).glob("*.jsonl"))] if (run_dir / PARTS).is_dir() else []
    records = [r for part in parts if part for r in part]
    if not records:
        raise ConfigError(f"{run_dir} has no {LOG} and no finished participants in {PARTS}/: give the directory "
                          "of a participants run")
    return to_frame(records), sum(1 for part in parts if part)


def run_world(run_dir: Path, overrides: Sequence[str] = ()):
    """The world a participants run simulated (its ``run.json``), or the run config's with ``overrides``."""
    from overhang_framework.behaviour.analysis import build_world
    from overhang_framework.plugins import Registry
    from overhang_framework.rundir import run_config

    world = run_config(run_dir).get("world") if not overrides else None
    if isinstance(world, dict):
        try:
            return Registry().create("world", dict(world))
        except (ValueError, KeyError, TypeError):
            pass

    return build_world(list(overrides))


# ----------------------------------------------------------------------------------------------- library

def library_trials(run_dir: Path, world_overrides: Sequence[str] = ("world.physics=static",)) -> pd.DataFrame:
    """One row per trial of a participants run: the participant's parameters, reward, stood, Γ of the completed
    tower (NaN otherwise) and the calls of each decision (a JSON list)."""
    from overhang_framework.behaviour import read_log
    from overhang_framework.behaviour.analysis import build_world, with_groups
    from overhang_framework.behaviour.gamma import trial_towers, with_gammas
    from overhang_framework.behaviour.log import in_step_order

    run_dir = Path(run_dir)
    for name in ("log.jsonl", "participants.csv"):
        if not (run_dir / name).exists():
            raise ConfigError(f"{run_dir} has no {name}: give the directory of a finished participants run")
    df = with_groups(read_log(run_dir / "log.jsonl"))
    if df["timed_out"].fillna(False).any():
        raise ConfigError(f"{run_dir}: its log has timeouts; run the library with "
                          "conditions.time_limited.time_limit=null (timeouts are applied afterwards)")
    towers = with_gammas(trial_towers(df), build_world(list(world_overrides)))
    ordered = in_step_order(df)
    calls = ordered.groupby(["participant", "trial"], sort=False)["predictor_calls"].agg(lambda s: [int(c) for c in s])
    rewards = ordered.groupby(["participant", "trial"], sort=False)["reward"].agg(lambda s: float(s.dropna().iloc[-1]))
    rows = towers[["participant", "task_id", "trial", "completed", "gamma"]].copy()
    key = list(zip(rows["participant"], rows["trial"]))
    rows["reward"] = [rewards[k] for k in key]
    rows["stood"] = rows.pop("completed").astype(bool)
    rows["gamma"] = np.where(rows["stood"], rows["gamma"], np.nan)
    rows["calls"] = [json.dumps(calls[k]) for k in key]
    people = pd.read_csv(run_dir / "participants.csv").rename(columns={"id": "participant"})
    out = rows.merge(people, on="participant", how="left", validate="many_to_one")
    return out.sort_values(["participant", "trial"]).reset_index(drop=True)


class Library:
    """The trials of one condition of the library, as arrays, with the proposal they were drawn from."""

    def __init__(self, trials: pd.DataFrame, proposal: Mapping[str, Distribution], condition: str):
        t = trials[trials["condition"] == condition].sort_values(["participant", "trial"])
        if t.empty:
            raise ConfigError(f"the library has no trial of condition {condition!r}")
        self.condition = condition
        people = t.drop_duplicates("participant")
        self.people = list(people["participant"])
        index = {p: i for i, p in enumerate(self.people)}
        self.who = np.array([index[p] for p in t["participant"]])
        self.theta = {name: people[name].to_numpy(dtype=float) for name in PARAMS if name in people}
        missing = [name for name in PARAMS if name not in self.theta or np.isnan(self.theta[name]).any()]
        if missing:
            raise ConfigError(f"the library's participants do not all draw {', '.join(missing)}; the proposal "
                              "must draw sigma, depth, beta and lapse")
        #: the axes of :data:`AXES` every participant of the library draws (each a free number of a candidate)
        self.axes = tuple(name for name in AXES if name in people and people[name].notna().all())
        for name in self.axes:
            self.theta[name] = people[name].to_numpy(dtype=float)
        self.log_q = sum(proposal[name].log_density(self.theta[name]) for name in (*PARAMS, *self.axes))
        self.reward = t["reward"].to_numpy(dtype=float)
        self.stood = t["stood"].to_numpy(dtype=bool).astype(float)
        self.gamma = t["gamma"].to_numpy(dtype=float)
        lists = [json.loads(c) for c in t["calls"]]
        width = max(len(c) for c in lists)
        self.calls = np.full((len(lists), width), np.nan)
        for i, c in enumerate(lists):
            self.calls[i, :len(c)] = c

    @property
    def free(self) -> list[tuple[str, float, float]]:
        """A candidate's free numbers with this library: :data:`FREE` and one per axis it draws."""
        return list(FREE) + [AXES[name] for name in self.axes]

    #: The spreads of a candidate's axes (set for a library drawn narrowly, so that a candidate is no wider
    #: than the proposal it is predicted from).
    risk_concentration: float = RISK_CONCENTRATION
    axis_spread: float = AXIS_SPREAD

    def candidate(self, vector: Sequence[float], noise: float = 0.3) -> Candidate:
        return Candidate.from_vector(vector, noise, self.axes, self.risk_concentration, self.axis_spread)

    def weights(self, candidate: Candidate) -> np.ndarray:
        dists = candidate.distributions()
        missing = [name for name in self.axes if name not in dists]
        if missing:
            raise ConfigError(f"the library draws {', '.join(missing)}: a candidate must give its distribution")
        log_p = sum(dists[name].log_density(self.theta[name]) for name in (*PARAMS, *self.axes))
        log_w = log_p - self.log_q
        if not np.isfinite(log_w).any():
            return np.zeros_like(log_w)
        w = np.exp(log_w - np.nanmax(log_w[np.isfinite(log_w)]))
        return np.where(np.isfinite(w), w, 0.0)

    def predict(self, candidate: Candidate, time_limit: Optional[float]) -> dict:
        """The candidate cohort's Table 1 measures and Γ in this condition, with the effective sample size."""
        m = candidate.t0 + candidate.per_call * self.calls  # median time of each decision
        s = max(candidate.noise, 1e-9)
        present = ~np.isnan(self.calls)
        with np.errstate(divide="ignore", invalid="ignore"):
            if time_limit is None:
                ok = np.ones_like(m)
                mean_time = m * math.exp(s * s / 2)
            else:
                ok = norm.cdf((math.log(time_limit) - np.log(m)) / s)
                mean_time = m * math.exp(s * s / 2) * norm.cdf((math.log(time_limit) - np.log(m) - s * s) / s) \
                    + time_limit * (1 - ok)
        ok = np.where(present, ok, 1.0)
        reach = np.concatenate([np.ones((len(m), 1)), np.cumprod(ok, axis=1)[:, :-1]], axis=1) * present
        finished = np.prod(ok, axis=1)  # no decision of the trial timed out
        records = reach.sum(axis=1)
        seconds = np.nansum(np.where(present, reach * mean_time, 0.0), axis=1)
        n = len(self.people)

        def per_person(values):
            return np.bincount(self.who, weights=values, minlength=n)

        trials = per_person(np.ones_like(self.reward))
        reward = per_person(self.reward * finished) / trials
        stood = per_person(self.stood * finished)
        overhang = per_person(self.reward * self.stood * finished) / np.where(stood > 0, stood, np.nan)
        has_gamma = ~np.isnan(self.gamma)
        g_weight = per_person(np.where(has_gamma, self.stood * finished, 0.0))
        gamma = per_person(np.where(has_gamma, self.gamma * self.stood * finished, 0.0)) / \
            np.where(g_weight > 0, g_weight, np.nan)
        time = per_person(seconds) / per_person(records)
        w = self.weights(candidate)
        total = w.sum()
        out = {"ess": float(total ** 2 / (w ** 2).sum()) if total > 0 else 0.0}
        for name, values in (("reward_per_trial", reward), ("stable_pct", 100 * stood / trials),
                             ("avg_overhang", overhang), ("decision_time", time), ("gamma", gamma)):
            ok_v = ~np.isnan(values) & (w > 0)
            out[name] = float(np.dot(w[ok_v], values[ok_v]) / w[ok_v].sum()) if ok_v.any() else math.nan
        return out


def distances(predicted: Mapping[str, float], targets: Mapping[str, tuple[float, float]]) -> dict[str, float]:
    """Each measure's distance from its target in the target's SEMs (signed: above the target is positive)."""
    return {k: (predicted[k] - mean) / sem for k, (mean, sem) in targets.items()}


def loss(vector: Sequence[float], library: Library, targets: Mapping[str, tuple[float, float]],
         time_limit: Optional[float], min_ess: float = MIN_ESS, noise: float = 0.3) -> float:
    cand = library.candidate(vector, noise)
    got = library.predict(cand, time_limit)
    z = distances(got, targets)
    if any(not np.isfinite(v) for v in z.values()):
        return 1e6
    penalty = 0.0 if got["ess"] >= min_ess else 100.0 * (min_ess - got["ess"]) / min_ess
    return float(sum(v * v for v in z.values()) + penalty)


def fit_condition(library: Library, targets: Optional[Mapping[str, tuple[float, float]]] = None,
                  time_limit: Optional[float] = math.nan, seed: int = 0, maxiter: int = 200, min_ess: float = MIN_ESS,
                  abc_draws: int = 20_000) -> dict:
    """The best candidate of one condition (differential evolution) and the ABC region: the candidates of a
    seeded uniform draw whose measures all lie within one SEM of the targets (default: the paper's, with the
    paper's time limit of the library's condition)."""
    from scipy.optimize import differential_evolution

    targets = dict(targets or TARGETS[library.condition])
    if time_limit is not None and math.isnan(time_limit):
        time_limit = TIME_LIMITS.get(library.condition)
    bounds = [(lo, hi) for _, lo, hi in library.free]
    best = differential_evolution(loss, bounds, args=(library, targets, time_limit, min_ess), seed=seed,
                                  maxiter=maxiter, tol=1e-8, polish=True, updating="immediate")
    cand = library.candidate(best.x)
    predicted = library.predict(cand, time_limit)
    rng = np.random.default_rng(seed)
    draws = rng.uniform([lo for lo, _ in bounds], [hi for _, hi in bounds], size=(abc_draws, len(bounds)))
    accepted = []
    for v in draws:
        c = library.candidate(v)
        got = library.predict(c, time_limit)
        z = distances(got, targets)
        if got["ess"] >= min_ess and all(np.isfinite(x) and abs(x) <= 1 for x in z.values()):
            accepted.append(c)
    region = {}
    if accepted:
        for name, values in (("mean_depth", [c.mean_depth for c in accepted]), ("sigma", [c.sigma for c in accepted]),
                             ("beta", [c.beta for c in accepted]), ("lapse", [c.lapse for c in accepted]),
                             *((axis, [dict(c.axes)[axis] for c in accepted]) for axis in library.axes)):
            region[name] = [float(np.quantile(values, q)) for q in (0.05, 0.5, 0.95)]
    return {"candidate": cand, "loss": float(best.fun), "predicted": predicted,
            "z": distances(predicted, targets), "accepted": len(accepted), "draws": abc_draws,
            "region": region}


def proposal_distributions(cohort_name: str = "proposal") -> dict[str, Optional[Distribution]]:
    """The proposal's distributions, from the shipped cohort config."""
    from overhang_framework.behaviour.simulation import CONFIG_NAME, check_config
    from overhang_framework.preflight import compose_checked

    # an unknown cohort is one line naming the cohorts there are
    checked = check_config(compose_checked([f"cohort={cohort_name}", "world.physics=static", "predictor=hybrid",
                                            "conditions.time_limited.time_limit=null"], config_name=CONFIG_NAME))
    return dict(checked.cohort.parameters)


def fit(trials: pd.DataFrame, out: Path, seed: int = 0, maxiter: int = 200, abc_draws: int = 20_000,
        proposal: Optional[Mapping[str, Distribution]] = None, min_ess: float = MIN_ESS,
        name: str = "paper_calibrated", risk_concentration: float = RISK_CONCENTRATION,
        axis_spread: float = AXIS_SPREAD) -> dict:
    """Fit each of the paper's conditions the library has; write ``calibration.json`` and ``<name>.yaml`` (a
    cohort config) to ``out``."""
    import yaml

    from overhang_framework.results import atomic_write_json, atomic_write_text

    proposal = dict(proposal or proposal_distributions())
    results = {}
    conditions = [c for c in TARGETS if c in set(trials["condition"])]
    if not conditions:
        raise ConfigError(f"the library has no trial of the paper's conditions ({', '.join(TARGETS)})")
    for condition in conditions:
        library = Library(trials, proposal, condition)
        library.risk_concentration, library.axis_spread = risk_concentration, axis_spread
        results[condition] = fit_condition(library, seed=seed, maxiter=maxiter, abc_draws=abc_draws, min_ess=min_ess)
    out.mkdir(parents=True, exist_ok=True)
    summary = {c: {"candidate": r["candidate"].config(), "mean_depth": r["candidate"].mean_depth,
                   "loss": r["loss"], "predicted": r["predicted"], "z": r["z"], "paper": TARGETS[c],
                   "abc": {"accepted": r["accepted"], "draws": r["draws"], "region": r["region"]}}
               for c, r in results.items()}
    atomic_write_json(out / "calibration.json", summary)
    cohort = {"name": name, "participants": {c: n for c, n in (("time_limited", 43), ("unconstrained", 38))
                                             if c in results},
              "n_tasks": None, "parameters": {"switch": {"dist": "categorical", "values": [3, 4, 5],
                                                          "p": [0.25, 0.5, 0.25]}},
              "by_condition": {c: r["candidate"].config() for c, r in results.items()},
              "decision_time": {"t0": 2.0, "per_call": 0.07, "noise": 0.3}, "motor": {"sd": 0.02, "retries": 5}}
    header = ["# The paper's people, fitted by simulation to the paper's Table 1 and Γ, condition by condition",
              "# (docs/fidelity.md): python -m overhang_framework.behaviour.calibrate fit TRIALS --out DIR.",
              "# Each measure's distance from the paper's, in the paper's SEMs (+ above, - below):"]
    header += [f"#   {c}: " + ", ".join(f"{k} {v:+.2f}" for k, v in r["z"].items()) for c, r in summary.items()]
    header += ["# The cohort selects its predictor, the hybrid (its IPE takes each participant's sigma):",
               f"#   python -m overhang_framework.participants cohort={name}",
               "defaults:", "  - override /predictor@_global_.predictor: hybrid"]
    atomic_write_text(out / f"{name}.yaml",
                      "\n".join(header) + "\n" + yaml.safe_dump(cohort, sort_keys=False, default_flow_style=None))
    return summary


def parser() -> argparse.ArgumentParser:
    """The command's argument parser."""
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.behaviour.calibrate",
                                 description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="command", required=True)
    lib = sub.add_parser("library", help="one row per trial of a participants run (the library)")
    lib.add_argument("run_dir", type=Path)
    lib.add_argument("--out", required=True, type=Path)
    lib.add_argument("--world", nargs="*", default=["world.physics=static"], help="world overrides for Γ")
    f = sub.add_parser("fit", help="fit both conditions to the paper's Table 1 and Γ")
    f.add_argument("trials", type=Path)
    f.add_argument("--out", required=True, type=Path)
    f.add_argument("--seed", type=int, default=0)
    f.add_argument("--maxiter", type=int, default=200)
    f.add_argument("--abc-draws", type=int, default=20_000)
    f.add_argument("--proposal", default="proposal", help="the cohort the library was drawn from")
    f.add_argument("--min-ess", type=float, default=MIN_ESS, help="the least effective sample of a candidate")
    f.add_argument("--name", default="paper_calibrated", help="the name of the cohort written")
    f.add_argument("--risk-concentration", type=float, default=RISK_CONCENTRATION,
                   help="the concentration of a candidate's beta distribution of risk")
    f.add_argument("--axis-spread", type=float, default=AXIS_SPREAD,
                   help="the lognormal sigma of a candidate's percept and hand")
    m = sub.add_parser("measure", help="the ten measures of participants runs, beside the paper's")
    m.add_argument("run_dirs", type=Path, nargs="+", metavar="run",
                   help="a participants run (one still running: its finished participants), or a CSV that "
                        "--save wrote; several: the seeds of a cohort, or one run a condition")
    m.add_argument("--world", nargs="*", default=None,
                   help="world overrides for Γ (default: the world each run simulated, from its run.json)")
    m.add_argument("--save", type=Path, default=None, metavar="CSV",
                   help="write the per-participant measures of the one run given (small enough to keep; "
                        "measure reads it back as a run)")
    m.add_argument("--figure", type=Path, default=None, metavar="PNG",
                   help="also draw the measures beside the paper's, each run's mean with its SEM")
    m.add_argument("--json", type=Path, default=None, metavar="FILE",
                   help="also write the table's figures to a JSON file (per condition and measure: the mean of the "
                        "runs' means, the paper's mean and SEM, the distance in its SEMs)")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = parser().parse_args(argv)
    try:
        if args.command == "measure":
            if args.save is not None and len(args.run_dirs) != 1:
                raise ConfigError(f"--save writes one run's participants; {len(args.run_dirs)} runs were given")
            kept = [str(r) for r in args.run_dirs if r.is_file()]
            if kept and args.world is not None:
                raise ConfigError(f"--world changes the Γ of a run's towers, and {kept[0]} keeps Γ already computed; "
                                  "give the run directory instead")
            results = []
            for run_dir in args.run_dirs:
                if run_dir.is_file():
                    people = read_people(run_dir)
                else:
                    df, finished = run_log(run_dir)
                    if finished is not None:
                        print(f"{run_dir}: still running; its {finished} finished participants", file=sys.stderr)
                    people = people_measures(df, run_world(run_dir, args.world or ()))
                if args.save is not None:
                    from overhang_framework.results import atomic_output

                    args.save.parent.mkdir(parents=True, exist_ok=True)
                    with atomic_output(args.save) as tmp:
                        people.to_csv(tmp, index=False, float_format="%.10g")
                    print(f"{args.save}: {len(people)} participants", file=sys.stderr)
                results.append(measured_people(people))
            print(measured_table(results))
            if args.json is not None:
                from overhang_framework.results import atomic_write_json

                atomic_write_json(args.json, measured_summary(results))
            if args.figure is not None:
                names = [r.stem if r.is_file() else r.name for r in args.run_dirs]
                if len(set(names)) < len(names):  # runs of the same name in different places
                    names = [str(r.with_suffix("")) if r.is_file() else str(r) for r in args.run_dirs]
                measured_figure(results, names, args.figure)
                print(f"written: {args.figure}", file=sys.stderr)
            return 0
        if args.command == "library":
            from overhang_framework.results import atomic_output

            table = library_trials(args.run_dir, args.world)
            with atomic_output(args.out) as tmp:
                table.to_csv(tmp, index=False)
            print(f"{args.out}: {len(table)} trials of {table['participant'].nunique()} participants")
            return 0
        if not args.trials.exists():
            raise ConfigError(f"{args.trials}: no such file (make it with the library command)")
        summary = fit(pd.read_csv(args.trials), args.out, args.seed, args.maxiter, args.abc_draws,
                      proposal_distributions(args.proposal), args.min_ess, args.name, args.risk_concentration,
                      args.axis_spread)
        for condition, r in summary.items():
            z = ", ".join(f"{k} {v:+.2f}" for k, v in r["z"].items())
            print(f"{condition}: mean depth {r['mean_depth']:.2f}; distance from the paper in its SEMs: {z}; "
                  f"ABC kept {r['abc']['accepted']} of {r['abc']['draws']}")
        print(f"written: {args.out / 'calibration.json'}, {args.out / (args.name + '.yaml')}")
        return 0
    except ConfigError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

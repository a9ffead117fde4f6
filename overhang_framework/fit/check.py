"""Posterior predictive check of a fit: ``python -m overhang_framework.fit.check FITDIR``.

Does each participant's fitted model *behave* like the participant? For every participant of the fit
(``FITDIR/fits.csv``; the pooled conditions are left out), the check takes the best model by BIC (or
the model ``--model`` names) with its fitted parameters (``sigma`` and the hybrid's ``switch`` point on
their grids, ``beta``, ``lapse``, the depth) and lets it do the participant's own trials again,
``--replicas`` times. A replica is the fitted model exactly as the likelihood sees it: in every state
it chooses among the world's grid actions with the softmax of the model's score table
(:mod:`~overhang_framework.fit.scores`, common random numbers) mixed with the lapse; the world's physics
says whether the tower stands, and the trial ends at the first collapse or the last block.

Each participant's data and each replica give the same statistics (:data:`STATISTICS`):

* from Table 1: the reward per trial, the stable proportion (%), the overhang over successful trials;
* Γ, the order dependency of their completed towers (the paper's Fig. 3b);
* per-step agreement: the mean probability the model gives the executed grid action, and the share of
  placements whose grid action the model ranks first (ties included);
* how far a placed block reaches past the edge of the blocks it rests on (metres; negative: inside).

The replicas of a participant give each statistic an interval: with ``R`` replicas, from the ``k``-th
smallest to the ``k``-th largest value, ``k = max(1, floor(0.025 (R + 1)))``. Were the data one more
draw of the model, it would fall outside that interval with probability ``2k / (R + 1)``: 5% with the
default ``R = 39`` (the replicas' range). An observed value outside it is *flagged*. Each condition is
checked the same way on the mean over its participants (replica ``r`` of the condition is the mean of
its participants' replicas ``r``).

The model has no decision time, so trials that ended on a timeout are left out of the participant's
data and are not replicated. Placements the fit could not map onto the grid count in the behavioural
statistics but not in the agreement ones (they have no grid action).

Writes ``FITDIR/check/`` (or ``--out``): ``check.md`` (what was found, in sentences, then the tables),
``participants.csv`` (participant x statistic: observed, the replicas' median and interval, flagged),
``conditions.csv``, ``check.png`` (observed against simulated with intervals, for each participant and each
condition's mean, flagged in red) and
``parts/`` (each participant's replicas, written as they finish: a stopped check continues where it
was). Score tables come from and go to the fit's score cache (``--cache``), so the states the fit has
already scored cost nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.errors import OverhangError
from overhang_framework.results import atomic_write_json, atomic_write_text

#: Replicas per participant: with 39, the replicas' range is a 95% interval (see the module docstring).
REPLICAS = 39
#: The statistics compared: (column, label, format).
STATISTICS = (("reward_per_trial", "reward per trial", ".3f"), ("stable_pct", "stable proportion (%)", ".1f"),
              ("avg_overhang", "overhang over successful trials", ".3f"), ("gamma", "Γ", ".3f"),
              ("p_executed", "probability of the executed action", ".3f"),
              ("first", "placements ranked first (%)", ".1f"), ("past_edge", "reach past the edge below (m)", ".3f"))
#: Where the check writes, inside the fit directory, unless ``--out`` says otherwise.
CHECK = "check"
PARTS = "parts"
#: The score cache of a fit (conf/fit.yaml's default).
DEFAULT_CACHE = "~/.cache/overhang_framework/scores.sqlite"


class CheckError(OverhangError):
    """A fit directory the check cannot use."""


def interval_rank(replicas: int) -> int:
    """``k``: the interval of ``replicas`` values runs from the k-th smallest to the k-th largest."""
    return max(1, int(math.floor(0.025 * (replicas + 1))))


def coverage(replicas: int) -> float:
    """The level of the replicas' interval: were the data one more replica, the chance it falls inside."""
    return 1 - 2 * interval_rank(replicas) / (replicas + 1)


def interval(values: Sequence[float]) -> tuple[float, float]:
    """The replicas' interval of :func:`interval_rank` (its level: :func:`coverage`); NaN values are left out, NaN when none is left."""
    x = np.sort(np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=float))
    if not x.size:
        return float("nan"), float("nan")
    k = interval_rank(x.size)
    return float(x[k - 1]), float(x[x.size - k])


# --- statistics of a log -------------------------------------------------------------------------------

def past_edge(records: pd.DataFrame) -> float:
    """The mean over placed blocks resting on blocks (not the ground) of how far the block reaches past the
    outer edge of the blocks under it: ``max(right - max right of supports, min left of supports - left)``."""
    values = []
    for before, width, x, layer in zip(records["tower_before"], records["width"], records["x"], records["layer"]):
        if x is None or pd.isna(x) or layer is None or pd.isna(layer) or int(layer) == 0:
            continue
        left, right = float(x) - float(width) / 2, float(x) + float(width) / 2
        under = [(bx - bw / 2, bx + bw / 2) for bw, bx, bl in before if int(bl) == int(layer) - 1
                 and min(right, bx + bw / 2) - max(left, bx - bw / 2) > 1e-9]
        if under:
            values.append(max(right - max(r for _, r in under), min(lft for lft, _ in under) - left))
    return float(np.mean(values)) if values else float("nan")


def log_statistics(df: pd.DataFrame, world, p_executed: Sequence[float], first: Sequence[bool]) -> dict:
    """The behavioural statistics of one participant's records ``df`` (a log DataFrame), with the agreement
    statistics from the probabilities ``p_executed`` and ranks ``first`` of its mapped placements."""
    from overhang_framework.behaviour import gamma, table1
    from overhang_framework.behaviour.analysis import with_groups

    df = with_groups(df)
    row = table1.per_participant(df).iloc[0]
    towers = gamma.per_participant(gamma.tower_gammas(df, world))
    placed = df[~df["timed_out"].astype(bool)]
    return {"reward_per_trial": float(row["reward_per_trial"]), "stable_pct": float(row["stable_pct"]),
            "avg_overhang": float(row["avg_overhang"]),
            "gamma": float(towers["gamma"].iloc[0]) if len(towers) else float("nan"),
            "p_executed": float(np.mean(p_executed)) if len(p_executed) else float("nan"),
            "first": 100.0 * float(np.mean(first)) if len(first) else float("nan"),
            "past_edge": past_edge(placed)}


# --- the fitted model of a participant -----------------------------------------------------------------

@dataclass
class Fitted:
    """A participant's model to check: its fits.csv row and the model (predictor config and depth)."""

    participant: str
    condition: str
    label: str
    model: Any  # fit.scores.Model
    beta: float
    lapse: float
    index: int

    def describe(self) -> str:
        parts = [self.label]
        if self.model.sigma is not None and self.model.family != "hybrid":
            parts.append(f"σ {self.model.sigma:g}")
        if self.model.switch is not None:
            parts.append(f"switch {self.model.switch}")
        if self.model.risk:
            parts.append(f"risk {self.model.risk:g}" + (f" ({self.model.risk_form})" if self.model.risk_form != "power" else ""))
        if self.model.hand:
            parts.append(f"hand {self.model.hand:g} m")
        if self.model.percept:
            parts.append(f"percept {self.model.percept:g} m")
        return ", ".join(parts) + f", β {self.beta:.3g}, lapse {self.lapse:.3g}"


def read_fit(fitdir: Path) -> tuple[dict, pd.DataFrame]:
    """``fit.json`` and ``fits.csv`` of a fit directory, or a one-line :class:`CheckError`."""
    description, fits = fitdir / "fit.json", fitdir / "fits.csv"
    if not fitdir.is_dir():
        raise CheckError(f"{fitdir} is not a directory; give the --out directory of a fit")
    for path in (description, fits):
        if not path.is_file():
            raise CheckError(f"{fitdir} has no {path.name}; give the --out directory of a finished fit "
                             "(python -m overhang_framework.fit LOG --out DIR)")
    try:
        spec = json.loads(description.read_text())
        table = pd.read_csv(fits)
    except (ValueError, OSError) as err:
        raise CheckError(f"{fitdir}: cannot read fit.json or fits.csv ({err})") from None
    missing = [k for k in ("logs", "models", "context") if k not in spec]
    if missing:
        raise CheckError(f"{description} is not a fit description (no {missing[0]!r})")
    need = ["participant", "condition", "model", "family", "depth", "sigma", "beta", "lapse", "bic"]
    absent = [c for c in need if c not in table.columns]
    if absent:
        raise CheckError(f"{fits} is not a fits.csv of the fit command (no column {absent[0]!r})")
    return spec, table


def _zero_if_blank(value: Any) -> float:
    """A grid value of fits.csv: 0 (none) where the model space had no such grid."""
    return 0.0 if value is None or pd.isna(value) else float(value)


def _same(a: Any, b: Any) -> bool:
    a_na = a is None or (isinstance(a, float) and math.isnan(a))
    b_na = b is None or (isinstance(b, float) and math.isnan(b))
    if a_na or b_na:
        return a_na and b_na
    return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)


def fitted_models(spec: Mapping[str, Any], fits: pd.DataFrame, model: Optional[str] = None) -> list[Fitted]:
    """Each participant's model to check: the best by BIC, or the row of ``model`` (a label of fits.csv)."""
    from overhang_framework.fit.equivalence import best_sets, per_participant, with_neutral
    from overhang_framework.fit.scores import Model

    people = per_participant(fits)
    if model is None:
        # a participant's best models predict the same on their data: the first of a tied set stands for it
        best = best_sets(with_neutral(fits))
        first = {str(r.participant): r.members[0] for r in best.itertuples(index=False)}
        rows = people[[first.get(str(p)) == str(m) for p, m in zip(people["participant"], people["model"])]]
        rows = rows.reset_index(drop=True)
    else:
        labels = sorted(set(people["model"]))
        if model not in labels:
            raise CheckError(f"--model {model!r} is not a model of this fit; models: {', '.join(labels)}")
        rows = people[people["model"] == model].reset_index(drop=True)
    variants: dict[str, list[tuple[dict, dict]]] = {}
    for label, config, *risk in spec["models"]:
        variants.setdefault(str(label), []).append((dict(config), dict(risk[0]) if risk else {}))
    out = []
    for index, r in enumerate(rows.sort_values("participant", kind="stable").itertuples(index=False)):
        switch = getattr(r, "switch", None)
        risk, hand, percept = (_zero_if_blank(getattr(r, name, None)) for name in ("risk", "hand", "percept"))
        found = [m for m in (Model(c, int(r.depth), str(r.family), float(k.get("risk", 0.0)),
                                   str(k.get("risk_form", "power")), float(k.get("percept", 0.0)))
                             for c, k in variants.get(str(r.model), []))
                 if _same(m.sigma, r.sigma if m.sigma is not None else None)
                 and (m.switch is None or pd.isna(switch) or m.switch == int(switch))
                 and _same(m.risk, risk) and _same(m.hand, hand) and _same(m.percept, percept)]
        if not found:
            raise CheckError(f"fits.csv's {r.model} of {r.participant} (sigma {r.sigma}, switch {switch}, risk {risk}, "
                             f"hand {hand}, percept {percept}) is not among the models of fit.json; the directory "
                             "mixes two fits")
        out.append(Fitted(str(r.participant), str(r.condition), str(r.model), found[0], float(r.beta), float(r.lapse),
                          index))
    return out


# --- replicas ------------------------------------------------------------------------------------------

def replicate(tables, world, trials: Sequence[tuple[str, tuple]], fitted: Fitted, rng: np.random.Generator
              ) -> tuple[list[dict], list[float], list[bool]]:
    """One replica of a participant: the fitted model does ``trials`` (task id, sequence) in that order.
    Returns the records (as a behaviour log's) and each decision's probability of its executed action and
    whether the model ranks it first."""
    from overhang_framework.fit.likelihood import choice_probabilities
    from overhang_framework.interfaces import Task
    from overhang_framework.search import ties

    records, probs, firsts = [], [], []
    for trial, (task_id, sequence) in enumerate(trials, 1):
        state = world.initial_state(Task(task_id, tuple(sequence)))
        stood, step = True, 0
        while not state.done:
            actions = world.legal_actions(state)
            if not actions:
                break
            scores = np.asarray(tables.table(state), dtype=float)
            if fitted.model.percept:
                i = _perceived_choice(tables, world, state, fitted, rng)
                probs.append(decision_probability(tables, state, i, fitted.model.percept, fitted.beta,
                                                  fitted.lapse))
            else:
                p = choice_probabilities(scores, fitted.beta, fitted.lapse)
                i = int(rng.choice(len(p), p=p / p.sum()))
                probs.append(float(p[i]))
            firsts.append(bool(i in set(ties(scores).tolist())))
            action = actions[i]
            before = [[b.width, b.x, b.layer] for b in state.geometry.blocks]
            step += 1
            record = {"log_version": 1, "participant": fitted.participant, "condition": fitted.condition,
                      "task_id": task_id, "sequence": list(sequence), "trial": trial, "step": step,
                      "width": state.next_width, "tower_before": before, "decision_time": 0.0,
                      "source": "simulated"}
            state = world.step(state, action)
            stable = bool(world.is_stable(state.geometry))
            stood = stood and stable
            ends = not stable or state.done
            record.update(x=float(action.x), layer=int(action.layer), stable=stable,
                          overhang=world.overhang(state.geometry),
                          reward=world.reward(state.geometry, stood) if ends else None, timed_out=False)
            records.append(record)
            if not stable:
                break
    return records, probs, firsts


def _perceived_choice(tables, world, state, fitted: Fitted, rng: np.random.Generator) -> int:
    """The index in ``world.legal_actions(state)`` of a choice of a participant with perceptual noise: a lapse,
    or a softmax choice on the tower it sees, placed at the nearest placement the real tower allows."""
    from overhang_framework.perception import perceive
    from overhang_framework.fit.likelihood import choice_probabilities
    from overhang_framework.fit.percept import seen_to_real

    if rng.random() < fitted.lapse:
        return int(rng.integers(len(world.legal_actions(state))))
    seen = perceive(state, fitted.model.percept, rng)
    p = choice_probabilities(np.asarray(tables.table(seen), dtype=float), fitted.beta, 0.0)
    return int(seen_to_real(world, state, seen)[int(rng.choice(len(p), p=p / p.sum()))])


def decision_probability(tables, state, chosen: int, percept: float, beta: float, lapse: float) -> float:
    """The probability of the action of index ``chosen`` in ``state`` under a model with perceptual noise
    ``percept`` (the fit's estimate over its percepts, :mod:`overhang_framework.fit.percept`)."""
    from overhang_framework.fit.percept import perceived_decisions

    return float(perceived_decisions(tables, [state], [chosen], percept).probabilities(beta, lapse)[0])


def observed_agreement(tables, world, placements, states: str, fitted: Fitted) -> tuple[list[float], list[bool]]:
    """The probability the fitted model gives each executed (mapped) placement, and whether it ranks it first."""
    from overhang_framework.fit.fitting import map_placements
    from overhang_framework.fit.likelihood import choice_probabilities
    from overhang_framework.search import ties

    mapped = map_placements(world, placements, states)
    probs, firsts = [], []
    for state, chosen in zip(mapped.states, mapped.chosen):
        scores = np.asarray(tables.table(state), dtype=float)
        if fitted.model.percept:
            probs.append(decision_probability(tables, state, chosen, fitted.model.percept, fitted.beta,
                                              fitted.lapse))
        else:
            probs.append(float(choice_probabilities(scores, fitted.beta, fitted.lapse)[chosen]))
        firsts.append(bool(chosen in set(ties(scores).tolist())))
    return probs, firsts


def spec_models(spec: Mapping[str, Any]) -> list:
    """Every model of the fit's space (fit.json's ``models``: label and predictor config)."""
    from overhang_framework.fit.scores import Model

    out = []
    for label, config, *risk in spec.get("models", []):
        family, _, planner = str(label).rpartition("/")
        depth = 1 if planner == "myopic" else int(planner.lstrip("D"))
        k = dict(risk[0]) if risk else {}
        out.append(Model(dict(config), depth, family, float(k.get("risk", 0.0)), str(k.get("risk_form", "power")),
                         float(k.get("percept", 0.0))))
    return out


def _setup(context: Mapping[str, Any], cache: Optional[str], models: Sequence = ()) -> dict:
    from overhang_framework.fit.run import Predictors
    from overhang_framework.fit.scores import ScoreCache
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", dict(context["world"]))
    value = registry.create("value", dict(context["value"]), world=world)
    return {"world": world, "value": value, "context": dict(context), "predictors": Predictors(registry, world),
            "cache": ScoreCache(cache), "tables": {}, "models": list(models)}


def _tables(env: dict, model):
    from overhang_framework.fit.scores import ScoreTables

    from overhang_framework.fit.scores import share_memory, share_tables

    key = model.key(env["context"])
    if key not in env["tables"]:
        predictors = env["predictors"]
        wanted = [model]
        if model.switch is not None:  # the fit kept a hybrid's table under the switch point that computed it
            built = predictors(dict(model.predictor))
            late = getattr(built, "late", None)
            wanted += [m for m in env.get("models", []) if m.depth == model.depth and (
                (m.family == model.family and m.switch is not None)
                or (late is not None and predictors.built.get(predictors.key(dict(m.predictor))) is late))]
        for m in wanted:
            k = m.key(env["context"])
            if k not in env["tables"]:  # a model with a percept asks the tables of the same model without it
                env["tables"][k] = ScoreTables(env["world"], env["value"], predictors(dict(m.predictor)),
                                               dataclasses.replace(m, percept=0.0), env["context"], env["cache"])
        share_memory(list(env["tables"].values()))
        share_tables(list(env["tables"].values()))
    return env["tables"][key]


def check_participant(env: dict, item: Mapping[str, Any]) -> dict:
    """The observed statistics and every replica's of one participant (a worker's item)."""
    from overhang_framework.behaviour.log import to_frame
    from overhang_framework.fit.fitting import log_placements
    from overhang_framework.parallel import tick

    fitted: Fitted = item["fitted"]
    world = env["world"]
    tables = _tables(env, fitted.model)
    df = to_frame(item["records"])
    placements = log_placements(df)
    probs, firsts = observed_agreement(tables, world, placements, item["states"], fitted)
    observed = log_statistics(df, world, probs, firsts)
    replicas = []
    for r in range(item["replicas"]):
        rng = np.random.default_rng(np.random.SeedSequence([int(item["seed"]), fitted.index, r]))
        records, probs, firsts = replicate(tables, world, item["trials"], fitted, rng)
        replicas.append(log_statistics(to_frame(records), world, probs, firsts))
        (env.get("on_replica") or tick)()
    return {"participant": fitted.participant, "condition": fitted.condition, "model": fitted.describe(),
            "observed": observed, "replicas": replicas}


# --- the report ----------------------------------------------------------------------------------------

def _num(value: Any) -> float:
    """A statistic as a float (NaN where a part's JSON holds null)."""
    return float("nan") if value is None else float(value)


def participant_table(parts: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """participant x statistic: observed, the replicas' median and interval, and whether it is flagged."""
    rows = []
    for part in parts:
        for name, label, _ in STATISTICS:
            values = [_num(rep[name]) for rep in part["replicas"]]
            lo, hi = interval(values)
            obs = _num(part["observed"][name])
            finite = [v for v in values if np.isfinite(v)]
            outside = bool(np.isfinite(obs) and np.isfinite(lo) and (obs < lo or obs > hi))
            rows.append({"participant": part["participant"], "condition": part["condition"], "model": part["model"],
                         "statistic": name, "observed": obs,
                         "simulated": float(np.median(finite)) if finite else float("nan"), "low": lo, "high": hi,
                         "replicas": len(finite), "flagged": outside})
    return pd.DataFrame(rows)


def condition_table(parts: Sequence[Mapping[str, Any]]) -> pd.DataFrame:
    """condition x statistic: the mean over its participants, observed against the replicas' means."""
    rows = []
    for condition in sorted({p["condition"] for p in parts}):
        mine = [p for p in parts if p["condition"] == condition]
        n = min(len(p["replicas"]) for p in mine)
        for name, label, _ in STATISTICS:
            obs = np.array([_num(p["observed"][name]) for p in mine], dtype=float)
            reps = np.array([[_num(p["replicas"][r][name]) for p in mine] for r in range(n)], dtype=float)
            with np.errstate(invalid="ignore"), _quiet():
                observed = float(np.nanmean(obs)) if np.isfinite(obs).any() else float("nan")
                means = [float(np.nanmean(row)) if np.isfinite(row).any() else float("nan") for row in reps]
            lo, hi = interval(means)
            finite = [m for m in means if np.isfinite(m)]
            rows.append({"condition": condition, "participants": len(mine), "statistic": name, "observed": observed,
                         "simulated": float(np.median(finite)) if finite else float("nan"), "low": lo, "high": hi,
                         "flagged": bool(np.isfinite(observed) and np.isfinite(lo) and (observed < lo or observed > hi))})
    return pd.DataFrame(rows)


class _quiet:
    def __enter__(self):
        import warnings

        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        return self._w.__exit__(*exc)


def findings(people: pd.DataFrame, conditions: pd.DataFrame, replicas: int, which: str) -> list[str]:
    """What the check found, one bullet per finding."""
    expected = 1 - coverage(replicas)
    checked = people[(people["replicas"] > 0) & people["observed"].notna()]
    flagged = checked[checked["flagged"]]
    n = len(checked)
    share = len(flagged) / n if n else float("nan")
    out = []
    verdict = ("about what chance gives when the models generated the data" if n and share <= 2 * expected
               else "more than chance gives when the models generated the data: the models miss something")
    out.append(f"- **Participants:** {len(flagged)} of {n} participant statistics ({share:.0%}) fall outside the "
               f"{1 - expected:.0%} interval of {replicas} replicas of {which} (about {expected:.0%} would, were "
               f"the data one more replica): {verdict}.")
    by_stat = []
    for name, label, _ in STATISTICS:
        rows = checked[checked["statistic"] == name]
        if len(rows):
            hits = rows[rows["flagged"]]
            if len(hits):
                above = int((hits["observed"] > hits["high"]).sum())
                by_stat.append(f"{label} for {len(hits)} of {len(rows)} ({above} above the interval, "
                               f"{len(hits) - above} below)")
    if by_stat:
        out.append("- **Flagged statistics:** " + "; ".join(by_stat) + ".")
    people_flagged = checked.groupby("participant")["flagged"].sum()
    worst = people_flagged[people_flagged >= 2].sort_values(ascending=False)
    if len(worst):
        names = ", ".join(f"{p} ({int(c)})" for p, c in worst.head(8).items())
        out.append(f"- **Participants with two or more flagged statistics:** {names}.")
    cond_flags = conditions[conditions["flagged"]]
    if len(conditions):
        if len(cond_flags):
            items = "; ".join(f"{r.condition}: {dict((s[0], s[1]) for s in STATISTICS)[r.statistic]} "
                              f"({r.observed:.3g} observed, {r.low:.3g} to {r.high:.3g} simulated)"
                              for r in cond_flags.itertuples())
            out.append(f"- **Conditions:** {len(cond_flags)} of {len(conditions)} condition means fall outside the "
                       f"replicas' interval: {items}.")
        else:
            out.append(f"- **Conditions:** every condition mean of every statistic ({len(conditions)}) is within "
                       "the replicas' interval.")
    return out


def figure(people: pd.DataFrame, conditions: pd.DataFrame, out: Path, level: float) -> None:
    """``check.png``: observed against simulated; ``level`` is the replicas' interval (:func:`coverage`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from overhang_framework.behaviour.analysis import save_figure

    cols = 4
    rows = math.ceil(len(STATISTICS) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.4 * cols, 3.2 * rows), squeeze=False)
    for ax, (name, label, _) in zip(axes.ravel(), STATISTICS):
        t = people[(people["statistic"] == name) & people["observed"].notna() & people["simulated"].notna()]
        for flagged, colour in ((False, "#2f6db5"), (True, "#c0392b")):
            s = t[t["flagged"] == flagged]
            if len(s):
                ax.errorbar(s["simulated"], s["observed"],
                            xerr=[s["simulated"] - s["low"], s["high"] - s["simulated"]], fmt="o", ms=3.5,
                            color=colour, ecolor=colour, alpha=0.75, elinewidth=0.8,
                            label="outside the interval" if flagged else "within")
        c = conditions[(conditions["statistic"] == name) & conditions["observed"].notna()
                       & conditions["simulated"].notna()]
        for r in c.itertuples():
            colour = "#c0392b" if r.flagged else "#222222"
            ax.errorbar([r.simulated], [r.observed], xerr=[[r.simulated - r.low], [r.high - r.simulated]], fmt="D",
                        ms=6, color=colour, ecolor=colour, elinewidth=1.4, zorder=5)
            ax.annotate(str(r.condition), (r.simulated, r.observed), textcoords="offset points", xytext=(5, 5),
                        fontsize=7, color=colour)
        if len(t):
            lo = float(np.nanmin(t[["low", "observed"]].to_numpy()))
            hi = float(np.nanmax(t[["high", "observed"]].to_numpy()))
            pad = 0.05 * (hi - lo or 1.0)
            ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="#999999", lw=0.8, zorder=0)
        ax.set_title(label, fontsize=9)
        ax.set_xlabel(f"simulated (median, {level:.0%} interval)", fontsize=8)
        ax.set_ylabel("observed", fontsize=8)
        ax.tick_params(labelsize=7)
    for ax in axes.ravel()[len(STATISTICS):]:
        ax.axis("off")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], marker="o", ls="", color="#2f6db5", label="participant, within its interval"),
               Line2D([], [], marker="o", ls="", color="#c0392b", label="outside its interval (flagged)"),
               Line2D([], [], marker="D", ls="", color="#222222", label="condition mean")]
    fig.legend(handles=handles, loc="lower right", fontsize=8, frameon=False, bbox_to_anchor=(0.98, 0.12))
    fig.suptitle("Posterior predictive check: each participant (dots) and each condition's mean (diamonds) against "
                 "replicas of the fitted models", fontsize=10)
    fig.tight_layout()
    save_figure(fig, out / "check.png")


def _cell(value: float, fmt: str) -> str:
    return "–" if value is None or not np.isfinite(value) else format(value, fmt)


def report(parts: Sequence[Mapping[str, Any]], out: Path, replicas: int, which: str, seconds: float,
           skipped: Sequence[str] = ()) -> str:
    from overhang_framework.behaviour.analysis import markdown_table

    people = participant_table(parts)
    conditions = condition_table(parts)
    atomic_write_text(out / "participants.csv", people.to_csv(index=False))
    atomic_write_text(out / "conditions.csv", conditions.to_csv(index=False))
    figure(people, conditions, out, coverage(replicas))
    fmt = {name: f for name, _, f in STATISTICS}
    lines = ["# Posterior predictive check", "",
             f"{len(parts)} participants, {which}, {replicas} replicas each ({seconds:.0f} s).", ""]
    lines += findings(people, conditions, replicas, which)
    if skipped:
        lines.append(f"- **Left out:** {', '.join(skipped)}: every trial ended on a timeout, and the model has no "
                     "decision time to replay that.")
    lines += ["", "## Conditions", "",
              "The mean over each condition's participants, observed, and the median and "
              f"{coverage(replicas):.0%} interval of the same mean over the replicas. ✗: outside the interval.", ""]
    body = []
    for r in conditions.itertuples():
        label = dict((s[0], s[1]) for s in STATISTICS)[r.statistic]
        body.append([r.condition, label, _cell(r.observed, fmt[r.statistic]),
                     f"{_cell(r.simulated, fmt[r.statistic])} ({_cell(r.low, fmt[r.statistic])} to "
                     f"{_cell(r.high, fmt[r.statistic])})", "✗" if r.flagged else ""])
    lines.append(markdown_table(["condition", "statistic", "observed", "simulated", ""], body))
    lines += ["", "## Participants", "",
              "Observed, then the replicas' interval; ✗ marks a value outside it.", ""]
    header = ["participant", "condition", "model"] + [label for _, label, _ in STATISTICS]
    body = []
    for part in parts:
        mine = people[people["participant"] == part["participant"]].set_index("statistic")
        cells = [part["participant"], part["condition"], part["model"]]
        for name, _, f in STATISTICS:
            r = mine.loc[name]
            cells.append(f"{_cell(r['observed'], f)} [{_cell(r['low'], f)}, {_cell(r['high'], f)}]"
                         + (" ✗" if r["flagged"] else ""))
        body.append(cells)
    lines.append(markdown_table(header, body))
    lines += ["", "Files: `participants.csv`, `conditions.csv`, `check.png`; each participant's replicas in `parts/`.",
              "", "![check.png](check.png)"]
    text = "\n".join(lines) + "\n"
    atomic_write_text(out / "check.md", text)
    return text


# --- the command ---------------------------------------------------------------------------------------

def _part_path(out: Path, participant: str) -> Path:
    safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in participant)
    return out / PARTS / f"{safe}.json"


def run(fitdir: Path, out: Optional[Path] = None, replicas: int = REPLICAS, model: Optional[str] = None,
        cache: Optional[str] = DEFAULT_CACHE, jobs: int = 1, seed: int = 0, progress: bool = True,
        participants: Optional[Sequence[str]] = None) -> dict:
    """Check every participant of the fit in ``fitdir`` (or those of ``participants``); write the report into
    ``out`` (``fitdir/check``)."""
    from overhang_framework.behaviour.log import read_log, records_of
    from overhang_framework.parallel import pool_map
    from overhang_framework.progress import progress_bar

    started = time.perf_counter()
    if isinstance(replicas, bool) or not isinstance(replicas, int) or replicas < 1:
        raise CheckError(f"--replicas must be a whole number >= 1, got {replicas!r}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise CheckError(f"--jobs must be a whole number >= 1, got {jobs!r}")
    fitdir = Path(fitdir)
    spec, fits = read_fit(fitdir)
    out = fitdir / CHECK if out is None else Path(out)
    chosen = fitted_models(spec, fits, model)
    models = spec_models(spec)
    if not chosen:
        raise CheckError(f"{fitdir / 'fits.csv'} holds no participant (only pooled conditions)")
    wanted = None if participants is None else sorted({str(p) for p in participants})
    if wanted is not None:
        missing = sorted(set(wanted) - {f.participant for f in chosen})
        if not wanted:
            raise CheckError("no participant to check: the list of participants is empty")
        if missing:
            raise CheckError(f"participant {missing[0]} is not in {fitdir / 'fits.csv'}; it has "
                             f"{', '.join(f.participant for f in chosen[:5])}{' and more' if len(chosen) > 5 else ''}")
        chosen = [f for f in chosen if f.participant in set(wanted)]
    try:
        df = read_log(spec["logs"])
    except OSError as err:
        raise CheckError(f"the fit's log cannot be read: {err}") from None
    which = f"the {model} model" if model else "each participant's best model (BIC)"
    from overhang_framework.results import file_sha256

    fitted_digest = file_sha256(fitdir / "fits.csv")
    settings = {"fit": str(fitdir.resolve()), "fits": fitted_digest, "replicas": replicas, "model": model,
                "seed": seed, "participants": wanted}
    (out / PARTS).mkdir(parents=True, exist_ok=True)
    settings_path = out / "check.json"
    if settings_path.exists():
        previous = json.loads(settings_path.read_text())
        previous.setdefault("participants", None)  # checks written before the setting existed checked everyone
        if previous.get("fits") != settings["fits"] and {k: v for k, v in previous.items() if k != "fits"} == \
                {k: v for k, v in settings.items() if k != "fits"}:
            raise CheckError(f"{out} holds a check of an earlier fits.csv; remove {out} (or use another --out) to "
                             "check these fits")
        if previous != settings:
            shown = {k: v for k, v in previous.items() if k != "fits"}
            raise CheckError(f"{out} holds a check with other settings ({shown}); use another --out or remove it")
    else:
        atomic_write_json(settings_path, settings)
    parts, items, skipped = {}, [], []
    for fitted in list(chosen):
        mine = df[df["participant"].astype(str) == fitted.participant]
        if mine["timed_out"].astype(bool).groupby(mine["trial"]).any().all():
            skipped.append(fitted.participant)  # nothing the model could replay
            chosen.remove(fitted)
    if not chosen:
        raise CheckError(f"every trial of every participant of {fitdir} ended on a timeout: nothing to replay")
    for fitted in chosen:
        path = _part_path(out, fitted.participant)
        if path.exists():
            parts[fitted.participant] = json.loads(path.read_text())
            continue
        mine = df[df["participant"].astype(str) == fitted.participant]
        timed_out = set(mine.loc[mine["timed_out"].astype(bool), "trial"])
        mine = mine[~mine["trial"].isin(timed_out)]
        firsts = mine.sort_values(["trial", "step"]).groupby("trial", sort=True).head(1)
        trials = [(str(r.task_id), tuple(float(w) for w in r.sequence)) for r in firsts.itertuples()]
        items.append({"fitted": fitted, "records": records_of(mine), "trials": trials, "replicas": replicas,
                      "seed": seed, "states": spec.get("states", "logged")})
    bar = progress_bar(total=len(items) * replicas, desc="replicas", unit="replica", disable=not progress,
                       miniters=1, mininterval=0.5, dynamic_ncols=True)
    try:
        if jobs > 1 and len(items) > 1:
            results = (result for _, result, _ in pool_map(_setup, (spec["context"], cache, models), check_participant, items,
                                                           min(jobs, len(items)), lambda: bar.update(1)))
        else:
            env = _setup(spec["context"], cache, models)
            env["on_replica"] = lambda: bar.update(1)
            results = (check_participant(env, item) for item in items)
        for result in results:
            path = _part_path(out, result["participant"])
            atomic_write_json(path, result)
            parts[result["participant"]] = json.loads(path.read_text())  # as a continued check reads it
    finally:
        bar.close()
    ordered = [parts[f.participant] for f in chosen]
    text = report(ordered, out, replicas, which, time.perf_counter() - started, skipped)
    return {"out": str(out), "participants": len(ordered), "computed": len(items),
            "seconds": time.perf_counter() - started, "report": text}


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.fit.check", description=__doc__.split("\n\n")[0])
    ap.add_argument("fitdir", help="the --out directory of a fit (fit.json, fits.csv)")
    ap.add_argument("--out", help="where to write (default: FITDIR/check)")
    ap.add_argument("--replicas", type=int, default=REPLICAS,
                    help=f"replicas per participant (default {REPLICAS}: their range is a 95%% interval)")
    ap.add_argument("--model", help="check this model of fits.csv (e.g. ipe/D2) for everyone, not each one's best")
    ap.add_argument("--participant", action="append", default=None, metavar="ID",
                    help="check only this participant (repeatable; default: every participant of fits.csv)")
    ap.add_argument("--cache", default=DEFAULT_CACHE, help=f"the score cache (default {DEFAULT_CACHE}; 'none': none)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    try:
        summary = run(Path(args.fitdir), None if args.out is None else Path(args.out), args.replicas, args.model,
                      None if args.cache == "none" else args.cache, args.jobs, args.seed, not args.no_progress,
                      args.participant)
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted: the participants checked so far are kept; run the same command to continue",
              file=sys.stderr)
        return 130
    print(summary["report"].split("\n## ")[0].strip())
    print(f"\nwrote {Path(summary['out']) / 'check.md'} ({summary['participants']} participants, "
          f"{summary['computed']} checked now, {summary['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

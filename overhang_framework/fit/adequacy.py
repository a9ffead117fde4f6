"""Does any model describe the participants? ``python -m overhang_framework.fit.adequacy FITDIR``.

A comparison says which model is best; it cannot say that the best is good. People who follow a rule outside
the model space (a heuristic no model of the space has, a risk attitude of another form) still have a best
model, and a comparison alone would name its family. This is the absolute goodness of fit that opens
``comparison.md``: each participant's best model (the first of a tied set; its members predict the same) is
set beside two yardsticks that need no model.

* **Chance**: a uniformly random legal grid action, ``log(1 / n)`` in a state of ``n`` legal actions.
* **The other participants' choices**, a lower bound on the noise ceiling. For a placement made in a state
  that at least :data:`MIN_OTHERS` placements of *other* participants of the same condition were made in
  too (towers compared with each block's x on the world's grid, the same blocks to come), the probability of
  its grid action is the others' share of it, smoothed: ``(n_a + alpha) / (N + alpha A)`` over the state's
  ``A`` legal actions, with ``alpha`` the value of :data:`ALPHAS` under which these leave-one-participant-out
  predictions are best. It is a predictor fitted to nobody's own choices, so a model of the participant
  that predicts them worse than it misses a regularity the people share. Were the model the participants'
  own choice rule, it would predict each participant better than any mixture of the others' choices, up to
  the error of its fitted parameters.

With a motor model (the fit's ``motor``) both score the placement's x as the fit did: the model its
``sum_j P(a_j) W_j``, the others' choices their shares of the planned actions placed with the same ``W``.

The comparison is per choice (nats), on the placements where both apply (shared states for the ceiling,
every mapped placement for chance), summed per participant and resampled over participants
(:data:`RESAMPLES` times; a 95% percentile interval). **No model describes the participants** when the
interval of (model - others' choices) lies below 0. With too few shared placements (fewer than
:data:`MIN_SHARED` or from fewer than 3 participants) the check says it cannot tell.

Tested on simulated cohorts (docs/fitting.md#does-any-model-describe-them): participants of the space, a
planner-free edge heuristic (``planner=edge``) and CVaR risk fitted by a space of power-form risk.

Writes ``FITDIR/adequacy.csv`` (per participant: placements, shared placements, nats a choice of the model,
chance and the others' choices) and ``FITDIR/adequacy.json`` (the summary, with the digest of the fits.csv
it describes). Score tables come from the fit's cache (``--cache``). ``--table CSV`` recomputes the summary
from a kept ``adequacy.csv`` alone (the resampling uses only its per-participant sums).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.errors import OverhangError
from overhang_framework.fit.check import DEFAULT_CACHE
from overhang_framework.results import atomic_write_json, atomic_write_text

#: Smoothing of the others' choices: the value under which their leave-one-out predictions are best is used.
ALPHAS = (0.01, 0.03, 0.1, 0.3, 1.0)
#: A placement counts for the ceiling when other participants made at least this many in its state.
MIN_OTHERS = 4
#: Fewer shared placements than this (or from fewer than :data:`MIN_PARTICIPANTS`) and the check cannot tell.
MIN_SHARED = 30
MIN_PARTICIPANTS = 3
#: Bootstrap resamples over participants, and the interval's coverage.
RESAMPLES = 2000
LEVEL = 0.95
#: What :func:`assess` concludes.
VERDICTS = ("described", "not described", "cannot tell")


class AdequacyError(OverhangError):
    """A fit directory the check cannot read."""


def state_key(state, resolution: float) -> tuple:
    """A tower as the ceiling compares towers: each block's width, x on the grid of ``resolution`` and layer, in
    placement order, and the widths still to come."""
    blocks = tuple((round(b.width, 6), int(round(b.x / resolution)), int(b.layer)) for b in state.geometry.blocks)
    return blocks, tuple(round(float(w), 6) for w in state.remaining)


def action_keys(world, state) -> list[tuple[int, int]]:
    """Each legal grid action of ``state`` as (x in grid steps, layer): comparable between towers."""
    return [(int(round(a.x / world.resolution)), int(a.layer)) for a in world.legal_actions(state)]


def choice_rows(world, fitted, tables, placements, states: str, motor=None) -> list[dict]:
    """One row per mapped placement of a participant: its state's key, its grid action's key, the legal actions'
    keys, and the log-probability the fitted model gives what was done (with a ``motor`` model, the placement's
    x, as the fit scored it; its weights go with the row, so the others' choices are scored the same way)."""
    from overhang_framework.fit.fitting import _decisions, map_placements
    from overhang_framework.fit.likelihood import decision_probabilities

    mapped = map_placements(world, placements, states, motor)
    decisions = _decisions(tables, mapped)
    probs = decision_probabilities(decisions, fitted.beta, fitted.lapse)
    return rows_of(world, fitted.participant, fitted.condition, mapped.states, mapped.chosen,
                   [math.log(max(float(p), 1e-300)) for p in probs], mapped.weights)


def rows_of(world, participant: str, condition: str, states, chosen, log_model, weights=None) -> list[dict]:
    """The rows of :func:`assess` of one participant's decisions ``states`` with the chosen actions' indices and
    the log-probabilities a model gives them (``weights``: a motor model's, one array a decision)."""
    rows = []
    for i, (state, index, lp) in enumerate(zip(states, chosen, log_model)):
        legal = action_keys(world, state)
        rows.append({"participant": participant, "condition": condition, "state": state_key(state, world.resolution),
                     "action": legal[int(index)], "legal": legal, "log_model": float(lp),
                     "weights": None if weights is None else np.asarray(weights[i], dtype=float)})
    return rows


def others_choices(rows: Sequence[Mapping[str, Any]], alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """For each row, the leave-one-participant-out log-probability of its action under the other participants'
    choices in the same state and condition (smoothed by ``alpha`` over the row's legal actions), and how many
    placements of others that rests on (those of actions legal in the row's state)."""
    counts: dict[tuple, dict[tuple, int]] = defaultdict(lambda: defaultdict(int))
    own: dict[tuple, dict[tuple, int]] = defaultdict(lambda: defaultdict(int))
    for r in rows:
        group = (r["condition"], r["state"])
        counts[group][r["action"]] += 1
        own[(group, r["participant"])][r["action"]] += 1
    logp, support = np.zeros(len(rows)), np.zeros(len(rows), dtype=int)
    for i, r in enumerate(rows):
        group = (r["condition"], r["state"])
        total, mine = counts[group], own[(group, r["participant"])]
        n = {a: total.get(a, 0) - mine.get(a, 0) for a in r["legal"]}
        others = sum(n.values())
        support[i] = others
        denominator = others + alpha * len(r["legal"])
        w = r.get("weights")
        if w is None:
            logp[i] = math.log((n[r["action"]] + alpha) / denominator)
        else:  # the others' shares as planned actions, placed with the motor model's hand: the fit's own scale
            shares = np.array([n[a] + alpha for a in r["legal"]]) / denominator
            logp[i] = math.log(max(float(shares @ w), 1e-300))
    return logp, support


def assess(rows: Sequence[Mapping[str, Any]], seed: int = 0) -> tuple[pd.DataFrame, dict]:
    """Per participant and in all: the model's nats a choice beside chance's and the others' choices'.

    Returns the participant table and the summary (``verdict`` one of :data:`VERDICTS`)."""
    if not rows:
        return pd.DataFrame(), {"verdict": "cannot tell", "why": "no mapped placement", "placements": 0}
    frame = pd.DataFrame({"participant": [r["participant"] for r in rows],
                          "condition": [r["condition"] for r in rows],
                          "log_model": [r["log_model"] for r in rows],
                          "log_chance": [-math.log(len(r["legal"])) for r in rows]})
    best_alpha, best_ll, logs = None, -np.inf, {}
    for alpha in ALPHAS:
        logp, support = others_choices(rows, alpha)
        logs[alpha] = (logp, support)
        ll = float(logp[support >= MIN_OTHERS].sum())
        if ll > best_ll:
            best_alpha, best_ll = alpha, ll
    logp, support = logs[best_alpha]
    frame["log_others"] = logp
    frame["shared"] = support >= MIN_OTHERS
    frame["vs_chance"] = frame["log_model"] - frame["log_chance"]
    frame["vs_others"] = np.where(frame["shared"], frame["log_model"] - frame["log_others"], 0.0)
    people = frame.groupby("participant", sort=True).agg(
        condition=("condition", "first"), placements=("log_model", "size"), shared=("shared", "sum"),
        model=("log_model", "mean"), chance=("log_chance", "mean"), sum_vs_chance=("vs_chance", "sum"),
        sum_vs_others=("vs_others", "sum"))
    shared = frame[frame["shared"]]
    by = shared.groupby("participant")
    people["model_shared"] = by["log_model"].mean().reindex(people.index)
    people["others_shared"] = by["log_others"].mean().reindex(people.index)
    people = people.reset_index()
    return people, summarise(people, seed, best_alpha)


#: The participant table's columns (``adequacy.csv``), from which :func:`summarise` recomputes the summary.
COLUMNS = ["participant", "condition", "placements", "shared", "model", "chance", "sum_vs_chance", "sum_vs_others",
           "model_shared", "others_shared"]


def summarise(people: pd.DataFrame, seed: int = 0, alpha: Optional[float] = None) -> dict:
    """The summary and verdict of a participant table (:data:`COLUMNS`): per-choice differences summed per
    participant, resampled over participants; ``alpha`` (the smoothing the table was made with) is recorded."""
    n_all, n_shared = people["placements"].to_numpy(float), people["shared"].to_numpy(float)
    chance_d, others_d = people["sum_vs_chance"].to_numpy(float), people["sum_vs_others"].to_numpy(float)
    weighted = lambda col, n: float(np.nansum(people[col].to_numpy(float) * n) / n.sum()) if n.sum() else None  # noqa: E731
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 74]))
    picks = rng.integers(len(people), size=(RESAMPLES, len(people)))

    def interval(sums: np.ndarray, counts: np.ndarray) -> dict:
        num, den = sums[picks].sum(axis=1), counts[picks].sum(axis=1)
        ratio = num[den > 0] / den[den > 0]
        tail = (1 - LEVEL) / 2 * 100
        return {"mean": float(sums.sum() / counts.sum()), "low": float(np.percentile(ratio, tail)),
                "high": float(np.percentile(ratio, 100 - tail))}

    summary: dict[str, Any] = {"placements": int(n_all.sum()), "participants": int(len(people)),
                               "shared_placements": int(n_shared.sum()),
                               "shared_participants": int((n_shared > 0).sum()), "alpha": alpha,
                               "min_others": MIN_OTHERS, "resamples": RESAMPLES, "level": LEVEL, "seed": int(seed),
                               "model": weighted("model", n_all), "chance": weighted("chance", n_all),
                               "vs_chance": interval(chance_d, n_all)}
    if summary["shared_placements"] < MIN_SHARED or summary["shared_participants"] < MIN_PARTICIPANTS:
        summary.update(verdict="cannot tell",
                       why=f"{summary['shared_placements']} placements from {summary['shared_participants']} "
                           f"participants were made in states that {MIN_OTHERS} or more placements of others were "
                           f"made in too (it needs {MIN_SHARED} from {MIN_PARTICIPANTS})")
        return summary
    summary["model_shared"] = weighted("model_shared", n_shared)
    summary["others_shared"] = weighted("others_shared", n_shared)
    summary["vs_others"] = interval(others_d, n_shared)
    summary["participants_worse"] = int(((n_shared > 0) & (others_d < 0)).sum())
    summary["verdict"] = "not described" if summary["vs_others"]["high"] < 0 else "described"
    return summary


def sentence(summary: Mapping[str, Any]) -> str:
    """The check's finding in one or two sentences, with its direction and sizes."""
    if not summary or not summary.get("placements"):
        return "Whether a model describes the participants cannot be said: no placement was mapped."
    c = summary["vs_chance"]
    chance = (f"The best models predict {summary['model']:.2f} nats a choice against chance's "
              f"{summary['chance']:.2f} ({c['mean']:+.2f}, 95% interval {c['low']:+.2f} to {c['high']:+.2f}, "
              f"over participants)")
    if summary["verdict"] == "cannot tell":
        return (f"Whether any model describes these participants cannot be said: {summary['why']}. "
                f"{chance}; that says a model is better than chance, not that it is right.")
    o = summary["vs_others"]
    where = (f"on the {summary['shared_placements']} placements made in states other participants of the same "
             f"condition met too")
    if summary["verdict"] == "not described":
        return (f"**No model of the space describes these participants**: {where}, the other participants' "
                f"choices predict them better than each participant's own best model, by {-o['mean']:.2f} nats a "
                f"choice (95% interval {-o['high']:.2f} to {-o['low']:.2f}; worse than the others' choices for "
                f"{summary['participants_worse']} of {summary['shared_participants']} participants), so the people "
                f"share a regularity no model has, and which family wins below is not a finding. {chance}.")
    return (f"The best models describe these participants as well as a model-free yardstick can tell: {where}, "
            f"each participant's own best model predicts them {o['mean']:+.2f} nats a choice against the other "
            f"participants' choices (95% interval {o['low']:+.2f} to {o['high']:+.2f}; worse for "
            f"{summary['participants_worse']} of {summary['shared_participants']}). {chance}.")


def read_table(path: Path) -> pd.DataFrame:
    """A participant table (``adequacy.csv``), or a one-line :class:`AdequacyError`."""
    try:
        people = pd.read_csv(path)
    except (OSError, ValueError) as err:
        why = str(getattr(err, "strerror", None) or err).strip().splitlines()[0]
        raise AdequacyError(f"{path}: cannot read a participant table ({why})") from None
    missing = [c for c in COLUMNS if c not in people.columns]
    if missing:
        raise AdequacyError(f"{path} is not an adequacy.csv: no column {missing[0]!r}; it needs {', '.join(COLUMNS)}")
    if not len(people):
        raise AdequacyError(f"{path} has no participant")
    numeric = [c for c in COLUMNS[2:8] if not pd.api.types.is_numeric_dtype(people[c])]
    if numeric:
        raise AdequacyError(f"{path}: column {numeric[0]!r} must hold numbers")
    if people["placements"].sum() <= 0 or (people[["placements", "shared"]] < 0).any().any():
        raise AdequacyError(f"{path}: placements must be counts >= 0, and some above 0")
    return people


def fits_digest(fitdir: Path) -> Optional[str]:
    """The SHA-256 of ``fitdir/fits.csv``: which fits a check describes."""
    from overhang_framework.results import file_sha256

    return file_sha256(Path(fitdir) / "fits.csv")


def read(fitdir: Path) -> Optional[dict]:
    """The summary of ``FITDIR/adequacy.json`` when it describes the fits.csv there, else None."""
    path = Path(fitdir) / "adequacy.json"
    if not path.is_file() or not (Path(fitdir) / "fits.csv").is_file():
        return None
    try:
        summary = json.loads(path.read_text())
    except ValueError:
        return None
    return summary if summary.get("fits") == fits_digest(fitdir) else None


def run(fitdir: Path, cache: Optional[str] = DEFAULT_CACHE, seed: int = 0, progress: bool = True,
        records: Optional[pd.DataFrame] = None) -> dict:
    """Assess every participant of the fit in ``fitdir``; write ``adequacy.csv`` and ``adequacy.json`` there and
    return the summary. ``records`` is the fit's behaviour log when the caller has it read."""
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.fit.check import CheckError, _setup, _tables, fitted_models, read_fit, spec_models
    from overhang_framework.fit.fitting import log_placements
    from overhang_framework.fit.motor import Motor
    from overhang_framework.progress import progress_bar

    started = time.perf_counter()
    fitdir = Path(fitdir)
    try:
        spec, fits = read_fit(fitdir)
        chosen = fitted_models(spec, fits)
    except CheckError as err:
        raise AdequacyError(str(err)) from None
    try:
        df = read_log(spec["logs"]) if records is None else records
    except OSError as err:
        raise AdequacyError(f"the fit's log cannot be read: {err}") from None
    motor = Motor.from_config(spec.get("motor"))
    env = _setup(spec["context"], cache, spec_models(spec))
    world, states = env["world"], spec.get("states", "logged")
    by_person = {str(p): g for p, g in df.groupby(df["participant"].astype(str), sort=False)}
    rows: list[dict] = []
    try:
        for fitted in progress_bar(chosen, desc="adequacy", unit="participant", disable=not progress):
            mine = by_person.get(fitted.participant)
            if mine is None:
                continue
            rows += choice_rows(world, fitted, _tables(env, fitted.model), log_placements(mine), states, motor)
    finally:
        env["cache"].close()
    people, summary = assess(rows, seed)
    summary.update(fits=fits_digest(fitdir), seconds=round(time.perf_counter() - started, 1),
                   sentence=sentence(summary))
    atomic_write_text(fitdir / "adequacy.csv", people.to_csv(index=False))
    atomic_write_json(fitdir / "adequacy.json", summary)
    return summary


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.fit.adequacy", description=__doc__.split("\n\n")[0])
    ap.add_argument("fitdir", nargs="?", help="the --out directory of a fit (fit.json, fits.csv)")
    ap.add_argument("--table", type=Path, help="recompute the summary from this adequacy.csv instead (no fit needed)")
    ap.add_argument("--summary", type=Path, help="also write the summary to this JSON file")
    ap.add_argument("--cache", default=DEFAULT_CACHE, help=f"the score cache (default {DEFAULT_CACHE}; 'none': none)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the resampling over participants")
    ap.add_argument("--no-progress", action="store_true")
    args = ap.parse_args(argv)
    if (args.fitdir is None) == (args.table is None):
        ap.error("give a fit directory or --table CSV (one of them)")
    try:
        if args.table is not None:
            summary = summarise(read_table(args.table), args.seed)
            summary["sentence"] = sentence(summary)
        else:
            summary = run(Path(args.fitdir), None if args.cache == "none" else args.cache, args.seed,
                          not args.no_progress)
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.summary is not None:
        atomic_write_json(args.summary, summary)
    print(summary["sentence"])
    if args.table is None:
        print(f"\nwrote {Path(args.fitdir) / 'adequacy.csv'} and adequacy.json ({summary['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Fitting with the participant's own prediction noise in the likelihood:
``python -m overhang_framework.fit.marginal LOG --out DIR``.

The fit's score tables score each decision state with one fixed draw of the IPE's simulations, while a
simulated participant (and, the model says, a person) draws fresh simulations at every decision. Here the
likelihood of a choice is the probability with which a participant of the model chooses it
(:class:`overhang_framework.fit.choice.BankChoice`): the average, over ``draws`` Monte Carlo samples of the
participant's noise, of the softmax over the planner's root scores, each node of the search drawing ``K`` of a
bank of ``bank`` noise draws per node (the IPE's noise distribution as the fit sees it). ``K``, the number of
mental simulations, is a parameter of the model, fitted on a grid beside ``sigma``, the depth and the risk.

For each participant and each grid point, ``beta`` and the lapse are fitted by L-BFGS-B on the stored score
samples; each model index (``ipe/D2``) keeps its best grid point. ``--jobs N`` fits participants on ``N``
processes; each participant's rows are kept in ``DIR/parts`` as it ends, so a stopped run continues where it
stopped (``DIR/marginal.json`` records the logs' contents and the settings, and another fit into the same
directory is refused). ``fits.csv`` has the fit's columns and ``K``;
``comparison.md`` is the fit's comparison (:mod:`overhang_framework.fit.compare`). The samples of a state are
drawn from a generator seeded by the state and the run's seed, the same for every model (common random numbers
between models).

The families are the IPE alone (``ipe``) and, with ``--switch N``, the stage-switch hybrid that sends towers of
``N`` blocks and more to the shipped CNN (``hybrid``; deterministic answers, the same under every draw; the switch
fitted on the grid's), on the world's grid, without a call budget (a budgeted participant's search completes depth
1 when the budget is below what depth 2 needs, so its depth-1 model is its own). ``--hand`` fits the hand the
planner plans for on a grid; ``--percept`` the perceptual noise: each state is seen as ``--percepts`` towers
(standard normal draws that are a function of the state, the same for every model), each with an equal share of
the draws, and a seen placement is credited to the real placement it becomes (docs/fitting.md, "The participant's
own noise"). ``--motor-sd`` scores each placement's x with the executed placement's motor noise
(:mod:`overhang_framework.fit.motor`).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import itertools
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from overhang_framework.fit.choice import BANK_SIZE, BankChoice, ChoiceParams, VerdictBank
from overhang_framework.fit.likelihood import padded_weights
from overhang_framework.fit.percept import PerceivedDecisions
from overhang_framework.interfaces import State

#: Monte Carlo samples of a participant's noise per decision state.
DRAWS = 500
#: Towers seen per decision state by a model with a percept (each with an equal share of the ``DRAWS``).
PERCEPTS = 20
#: Towers the hybrid's CNN remembers in a fit: every tower of a participant's depth-2 searches under a hand (about
#: 225,000 for 90 decisions), so that the other switch points and grid points find them.
CNN_CACHE = 2_000_000
#: The parts' column of each decision's log-probability of what was done (its grid action, or with a motor model its
#: x) under the row's model (not in fits.csv).
LOGP = "choice_logp"


class SampledDecisions(PerceivedDecisions):
    """A participant's decisions under a model with its own noise: ``scores`` ``(n, draws, m)``, the root scores of
    each decision under each sample (``-inf`` past each state's actions), and the chosen indices; the likelihood
    is that of a percept's (:class:`~overhang_framework.fit.percept.PerceivedDecisions`) whose draws all see the
    real tower: ``P(a) = (1 - lapse) * mean_draws softmax_beta(scores)_a + lapse / size``. With a motor model's
    ``weights`` ``(n, m)`` (:mod:`overhang_framework.fit.motor`) it is the executed x's probability,
    ``sum_j P(a_j) W_j``."""

    def __init__(self, scores: np.ndarray, chosen: np.ndarray, sizes: np.ndarray,
                 weights: Optional[np.ndarray] = None, targets: Optional[np.ndarray] = None):
        sizes = np.asarray(sizes, dtype=float)
        chosen = np.asarray(chosen, dtype=int)
        if weights is None and targets is None:
            hit = np.zeros(scores.shape, dtype=bool)
            hit[np.arange(len(chosen)), :, chosen] = True
            super().__init__(scores, hit, sizes)
        else:
            if weights is not None:
                weights = np.asarray(weights, dtype=float)
                base = weights
            else:  # the chosen real action, one-hot over the real actions
                base = np.zeros((len(chosen), int(sizes.max(initial=1))))
                base[np.arange(len(chosen)), chosen] = 1.0
            if targets is None:
                hit = base[:, None, :]
            else:  # each seen action's real placement's weight
                targets = np.asarray(targets, dtype=int)
                rows = np.arange(len(chosen))[:, None, None]
                hit = np.where(targets >= 0, base[rows, np.maximum(targets, 0)], 0.0)
            super().__init__(scores, hit, sizes, None if weights is None else weights.sum(axis=1) / sizes)
        self.weights, self.targets = weights, targets
        self.chosen = chosen
        self._cache = None

    @classmethod
    def of(cls, samples: Sequence[np.ndarray], chosen: Sequence[int],
           weights: Optional[Sequence[np.ndarray]] = None,
           targets: Optional[Sequence[np.ndarray]] = None,
           sizes: Optional[Sequence[int]] = None) -> "SampledDecisions":
        """From each decision's ``(draws, m)`` score samples; with a percept, ``targets``: each sample's seen actions'
        real indices (:meth:`overhang_framework.fit.choice.BankChoice.perceived_samples`), and ``sizes``: the real
        states' numbers of legal actions."""
        if targets is not None and sizes is None:
            raise ValueError("a percept's samples need the real states' sizes")
        n = len(samples)
        draws = max((s.shape[0] for s in samples), default=1)
        m = max((s.shape[1] for s in samples), default=1)
        scores = np.full((n, draws, m), -np.inf)
        for i, s in enumerate(samples):
            scores[i, : s.shape[0], : s.shape[1]] = s
        padded = None
        if targets is not None:
            padded = np.full((n, draws, m), -1, dtype=int)
            for i, t in enumerate(targets):
                padded[i, : t.shape[0], : t.shape[1]] = t
        sizes = np.array([s.shape[1] for s in samples] if targets is None else sizes, dtype=float)
        width = m if targets is None else int(sizes.max(initial=1))
        return cls(scores, np.asarray(chosen, dtype=int), sizes, padded_weights(weights, width), padded)

    def subset(self, rows: np.ndarray) -> "SampledDecisions":
        return SampledDecisions(self.scores[rows], self.chosen[rows], self.sizes[rows],
                                None if self.weights is None else self.weights[rows],
                                None if self.targets is None else self.targets[rows])

    def _centred(self):
        if self._cache is None:
            s = self.scores
            inside = np.isfinite(s)
            top = np.where(inside, s, -np.inf).max(axis=2, keepdims=True)
            centred = np.where(inside, s - top, 0.0)
            picked = centred[np.arange(len(self)), :, self.chosen] if self.targets is None else None
            self._cache = (centred, inside, picked)
        return self._cache

    def value_and_grad(self, beta: float, lapse: float) -> tuple[float, np.ndarray]:
        """The log-likelihood and its gradient in ``(beta, lapse)`` (one pass over the samples)."""
        centred, inside, picked = self._centred()
        w = np.where(inside, np.exp(beta * centred), 0.0)
        total = w.sum(axis=2)
        mean_score = (w * centred).sum(axis=2) / total
        if self.weights is None and self.targets is None:
            soft = np.exp(beta * picked) / total  # (n, draws): the chosen action's softmax
            dsoft = soft * (picked - mean_score)
            uniform = 1 / self.sizes
        else:  # the softmax's mass on the motor model's weights or the percepts' hits, and its derivative in beta
            hit = self.hit
            soft = (w * hit).sum(axis=2) / total
            dsoft = (w * hit * centred).sum(axis=2) / total - soft * mean_score
            uniform = 1 / self.sizes if self.lapse_weight is None else self.lapse_weight
        q = soft.mean(axis=1)
        dq = dsoft.mean(axis=1)
        p = np.maximum((1 - lapse) * q + lapse * uniform, 1e-300)
        grad = np.array([float(((1 - lapse) * dq / p).sum()), float(((uniform - q) / p).sum())])
        return float(np.log(p).sum()), grad


@dataclass(frozen=True)
class Grid:
    """The model space: the IPE's sigmas, the numbers of simulations ``K``, the depths, the risks, the hand the
    planner plans for (metres; 0: none), the perceptual noise (metres; 0: none) and the families by their switch
    point: 0 the IPE alone (family ``ipe``), any other the stage-switch hybrid that sends towers of that many
    blocks and more to the shipped CNN (family ``hybrid``, its switch fitted on the grid's)."""

    sigmas: tuple = (0.02, 0.03, 0.05)
    Ks: tuple = (1, 10, 50)
    depths: tuple = (1, 2)
    risks: tuple = (0.0,)
    risk_form: str = "power"
    hands: tuple = (0.0,)
    percepts: tuple = (0.0,)
    switches: tuple = (0,)

    def settings(self) -> dict:
        """As ``marginal.json`` records it (an axis at its default left out, as it was recorded before the axis)."""
        out = dataclasses.asdict(self)
        for name in ("hands", "percepts", "switches"):
            if tuple(out[name]) == tuple(getattr(Grid, name)):
                del out[name]
        return out

    def families(self) -> list[tuple[str, tuple]]:
        """``(family, switch points)``: ``ipe`` with ``(0,)`` and ``hybrid`` with the grid's other switches."""
        out = [("ipe", (0,))] if 0 in self.switches else []
        hybrid = tuple(int(s) for s in self.switches if s)
        return out + ([("hybrid", hybrid)] if hybrid else [])


def _seed(state: State, seed: int) -> np.random.Generator:
    from overhang_framework.search import state_key

    digest = hashlib.blake2b(repr(state_key(state)).encode(), digest_size=8).digest()
    return np.random.default_rng(np.random.SeedSequence([int(seed), int.from_bytes(digest, "little"), 0x5A3]))


def fit_participant(world, value, states: Sequence[State], chosen: Sequence[int], grid: Grid, draws: int = DRAWS,
                    bank_size: int = BANK_SIZE, seed: int = 0, banks: Optional[dict] = None,
                    weights: Optional[Sequence[np.ndarray]] = None, percepts: int = PERCEPTS) -> list[dict]:
    """One row per model index (family and depth): the best grid point's parameters and likelihood (``weights``: a
    motor model's, :mod:`overhang_framework.fit.motor`; ``percepts``: towers seen per state where the percept is
    above 0). ``banks`` keeps the verdict banks by sigma and the hybrid's CNN (``"late"``) between calls."""
    from overhang_framework.fit.fitting import fit_softmax

    banks = {} if banks is None else banks
    sizes = [len(world.legal_actions(s)) for s in states]
    rows = []
    for family, switches in grid.families():
        late = None
        if family == "hybrid":
            if "late" not in banks:
                from overhang_framework.plugins import Registry

                banks["late"] = Registry().create("predictor", {"name": "cnn", "cache_size": CNN_CACHE}, world=world)
            late = banks["late"]
        for depth in grid.depths:
            best = None
            for sigma, hand, switch in itertools.product(grid.sigmas, grid.hands, switches):
                bank = banks.setdefault(sigma, VerdictBank(world, sigma=float(sigma), size=bank_size, seed=seed))
                trees: dict = {}  # a tree's answers are the hand's and the switch's: shared by their K, risks, percepts
                for percept, K, risk in itertools.product(grid.percepts, grid.Ks, grid.risks):
                    params = ChoiceParams(depth=int(depth), K=int(K), beta=1.0, risk=float(risk),
                                          risk_form=grid.risk_form, hand=float(hand), percept=float(percept),
                                          switch=int(switch))
                    choice = BankChoice(world, value, bank, params, draws=draws, seed=seed, trees=trees, late=late)
                    if percept:
                        pairs = [choice.perceived_samples(s, draws, percepts, _seed(s, seed)) for s in states]
                        samples, targets = [a for a, _ in pairs], [b for _, b in pairs]
                    else:
                        samples = [choice.score_samples(s, draws, _seed(s, seed)) for s in states]
                        targets = None
                    decisions = SampledDecisions.of(samples, chosen, weights, targets, sizes)
                    fit = fit_softmax(decisions)
                    if best is None or fit.loglik > best[0].loglik + 1e-9:
                        best = (fit, sigma, K, risk, hand, percept, switch, decisions)
            fit, sigma, K, risk, hand, percept, switch, decisions = best
            # each choice's probability of what was done under the best grid point: whether any model describes the
            # participant (fit.adequacy) asks it
            chosen_p = decisions.probabilities(fit.beta, fit.lapse) if len(states) else []
            axes = (grid.sigmas, grid.Ks, grid.risks, grid.hands, grid.percepts, switches)
            k = 2 + sum(len(set(g)) > 1 for g in axes)
            n = len(states)
            row = {"model": f"{family}/{'myopic' if depth == 1 else f'D{depth}'}", "family": family,
                   "depth": int(depth), "sigma": float(sigma), "K": int(K), "risk": float(risk), "hand": float(hand),
                   "percept": float(percept), "beta": fit.beta, "lapse": fit.lapse, "loglik": fit.loglik, "k": k,
                   "n": n, "bic": k * math.log(n) - 2 * fit.loglik if n else math.nan, "aic": 2 * k - 2 * fit.loglik,
                   LOGP: ";".join(f"{math.log(max(float(p), 1e-300)):.9g}" for p in chosen_p)}
            if family == "hybrid":
                row["switch"] = int(switch)
            rows.append(row)
    return rows


def recovery(fits: pd.DataFrame, truth: pd.DataFrame) -> dict:
    """How a fit recovers simulated participants (``truth``: participants.csv, with ``depth``, ``sigma`` and,
    when drawn, ``risk`` and ``K``): the best model's depth, and at the true depth (the fit's deepest for a
    participant who planned deeper) the fitted risk, sigma and K
    (with a drawn ``K``, how often it is the truth and the table of true against fitted)."""
    from overhang_framework.fit.compare import per_participant
    from overhang_framework.fit.equivalence import with_neutral

    from overhang_framework.fit.equivalence import best_sets

    fits = per_participant(with_neutral(fits))
    truth = truth.set_index(truth["id"].astype(str))
    people = [p for p in truth.index if p in set(fits["participant"].astype(str))]
    best = best_sets(fits)  # each participant's best models by BIC, models of equal likelihood as one
    best = best.set_index(best["participant"].astype(str))
    deepest = int(fits["depth"].max())  # a participant planning deeper than the fit's depths: its deepest model
    # at the true depth, the best of the families (a parameter the tied models do not share left empty)
    by_depth = {int(d): best_sets(f).set_index(best_sets(f)["participant"].astype(str))
                for d, f in fits.groupby("depth")}
    at = {p: by_depth[min(int(truth.loc[p, "depth"]), deepest)].loc[p] for p in people}
    true_risk = {p: float(truth.loc[p, "risk"]) if "risk" in truth.columns and pd.notna(truth.loc[p, "risk"])
                 else 0.0 for p in people}
    averse = [float(at[p]["risk"]) for p in people if true_risk[p] > 0]
    neutral = [float(at[p]["risk"]) for p in people if true_risk[p] == 0]
    out = {"participants": len(people),
           "depth": int(sum(float(best.loc[p, "depth"]) == int(truth.loc[p, "depth"]) for p in people)),
           "risk": int(sum(math.isclose(float(at[p]["risk"]), true_risk[p], abs_tol=1e-9) for p in people)),
           "risk_of_averse": float(np.mean(averse)) if averse else None,
           "averse": len(averse), "neutral": len(neutral),
           "averse_right": int(sum(math.isclose(float(at[p]["risk"]), true_risk[p], abs_tol=1e-9)
                                   for p in people if true_risk[p] > 0)),
           "neutral_right": int(sum(float(at[p]["risk"]) == 0 for p in people if true_risk[p] == 0)),
           "risk_of_neutral": float(np.mean(neutral)) if neutral else None,
           "sigma_error": float(np.mean([abs(float(at[p]["sigma"]) - float(truth.loc[p, "sigma"])) for p in people]))}
    if "hand" in truth.columns and truth["hand"].notna().any():
        def planned(p):  # the hand the planner plans for: hand x steadiness when drawn
            hand = float(truth.loc[p, "hand"]) if pd.notna(truth.loc[p, "hand"]) else 0.0
            steady = truth.loc[p, "steadiness"] if "steadiness" in truth.columns else None
            return hand * float(steady) if steady is not None and pd.notna(steady) else hand

        true_hand = {p: planned(p) for p in people}
        out["hand"] = int(sum(math.isclose(float(at[p]["hand"]), true_hand[p], abs_tol=1e-9) for p in people))
    if fits["family"].nunique() > 1:  # which family and depth is each participant's best
        out["best_models"] = {str(m): int(n) for m, n in best.loc[people, "model"].value_counts().sort_index().items()}
    if "switch" in fits.columns and "switch" in truth.columns:  # the hybrid's switch where the hybrid is best
        hybrid = [p for p in people if str(at[p]["family"]) == "hybrid"]
        out["hybrid_at_true_depth"] = len(hybrid)
        out["switch"] = int(sum(float(at[p]["switch"]) == float(truth.loc[p, "switch"]) for p in hybrid))
    if "K" in fits.columns:
        out["K"] = [int(at[p]["K"]) if pd.notna(at[p]["K"]) else None for p in people]
        out["K_counts"] = {f"K{k}": out["K"].count(k) for k in sorted({k for k in out["K"] if k is not None})}
        drew = [p for p in people if "K" in truth.columns and pd.notna(truth.loc[p, "K"])]
        if drew:  # the participants who drew their own K
            fitted = {p: k for p, k in zip(people, out["K"])}
            true_K = {p: int(truth.loc[p, "K"]) for p in drew}
            out["K_right"] = int(sum(fitted[p] == true_K[p] for p in drew))
            out["K_drawn"] = len(drew)
            out["K_confusion"] = {f"true{t}": {f"fitted{f}": sum(1 for p in drew if true_K[p] == t and fitted[p] == f)
                                               for f in sorted({v for v in fitted.values() if v is not None})}
                                  for t in sorted(set(true_K.values()))}
    return out


def against(fits: pd.DataFrame, other: pd.DataFrame) -> dict:
    """Each participant's best log-likelihood in ``fits`` against the best in ``other`` over the same families and
    depths (``other``'s rows of the families and depths ``fits`` has): how many are higher, and the median and
    mean difference (nats a participant)."""
    from overhang_framework.fit.equivalence import per_participant

    fits, other = per_participant(fits), per_participant(other)
    other = other[other["family"].isin(set(fits["family"])) & other["depth"].isin(set(fits["depth"]))]
    mine = fits.groupby(fits["participant"].astype(str))["loglik"].max()
    theirs = other.groupby(other["participant"].astype(str))["loglik"].max()
    common = mine.index.intersection(theirs.index)
    d = (mine[common] - theirs[common]).to_numpy()
    return {"participants": int(len(common)), "higher": int((d > 0).sum()),
            "median_gain": float(np.median(d)) if len(d) else None, "mean_gain": float(np.mean(d)) if len(d) else None}


def _numbers(text: str, kind=float) -> tuple:
    try:
        values = tuple(kind(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of numbers: {text!r}") from None
    if not values:
        raise argparse.ArgumentTypeError("an empty list")
    return values


def main(argv: Optional[Sequence[str]] = None) -> int:
    from overhang_framework.behaviour.log import read_log, require_records
    from overhang_framework.errors import OverhangError
    from overhang_framework.fit.fitting import log_placements, map_placements
    from overhang_framework.plugins import Registry
    from overhang_framework.progress import progress_bar
    from overhang_framework.results import atomic_write_text

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.fit.marginal",
                                     description="Fit the IPE family with the participant's own prediction noise in "
                                                 "the likelihood; K (mental simulations) fitted on a grid.")
    parser.add_argument("logs", nargs="*", type=Path, help="behaviour logs (log.jsonl)")
    parser.add_argument("--out", type=Path, default=None, help="where fits.csv and comparison.md go")
    parser.add_argument("--recovery", type=Path, nargs=2, metavar=("FITS", "TRUTH"), default=None,
                        help="print, as JSON, how the fits of FITS (a fits.csv) recover the simulated participants of "
                             "TRUTH (their participants.csv), and fit nothing")
    parser.add_argument("--against", type=Path, default=None, metavar="FITS",
                        help="with --recovery: also compare each participant's best log-likelihood with that of FITS "
                             "(another fit's fits.csv) over the same family and depths")
    parser.add_argument("--sigma", type=_numbers, default=Grid.sigmas, help="IPE noise grid (default 0.02,0.03,0.05)")
    parser.add_argument("--K", type=lambda t: _numbers(t, int), default=Grid.Ks, help="K grid (default 1,10,50)")
    parser.add_argument("--depths", type=lambda t: _numbers(t, int), default=Grid.depths, help="depths (default 1,2)")
    parser.add_argument("--risk", type=_numbers, default=Grid.risks, help="risk grid (default 0)")
    parser.add_argument("--hand", type=_numbers, default=Grid.hands,
                        help="grid of the hand the planner plans for, metres (default 0: none)")
    parser.add_argument("--percept", type=_numbers, default=Grid.percepts,
                        help="grid of the perceptual noise, metres (default 0: none)")
    parser.add_argument("--percepts", type=int, default=PERCEPTS,
                        help=f"towers seen per state where the percept is above 0 (default {PERCEPTS})")
    parser.add_argument("--switch", type=lambda t: _numbers(t, int), default=Grid.switches,
                        help="the families by switch point: 0 the IPE alone, N the hybrid sending towers of N blocks "
                             "and more to the shipped CNN (default 0)")
    parser.add_argument("--condition", action="append", default=None,
                        help="fit only the participants of this condition (repeatable; default: all)")
    parser.add_argument("--first", type=int, default=None, metavar="N",
                        help="fit only the first N participants (by id, after --condition): a stated subsample")
    parser.add_argument("--draws", type=int, default=DRAWS, help=f"noise samples per state (default {DRAWS})")
    parser.add_argument("--bank", type=int, default=BANK_SIZE, help=f"noise draws per node (default {BANK_SIZE})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--physics", default="static", help="the world's physics (default static)")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    parser.add_argument("--motor-sd", type=float, default=None, metavar="METRES",
                        help="score each placement's x with motor noise of this sd (docs/fitting.md, motor noise in "
                             "the likelihood; 5 retries, to the millimetre); default: its nearest grid action")
    args = parser.parse_args(argv)
    if args.recovery is not None:
        import json

        try:
            fits, truth = pd.read_csv(args.recovery[0]), pd.read_csv(args.recovery[1])
        except (OSError, ValueError) as err:
            print(f"error: --recovery: {getattr(err, 'strerror', None) or err}", file=sys.stderr)
            return 2
        out = recovery(fits, truth)
        if args.against is not None:
            try:
                other = pd.read_csv(args.against)
            except (OSError, ValueError) as err:
                print(f"error: --against: {getattr(err, 'strerror', None) or err}", file=sys.stderr)
                return 2
            out["against"] = against(fits, other)
        print(json.dumps(out, sort_keys=True))
        return 0
    if not args.logs or args.out is None:
        print("error: give the behaviour logs and --out DIR (or --recovery FITS TRUTH)", file=sys.stderr)
        return 2
    try:
        if any(k < 1 for k in args.K) or any(d < 1 for d in args.depths) or min(args.draws, args.bank, args.jobs) < 1:
            raise OverhangError("K, depths, --draws, --bank and --jobs must be whole numbers >= 1")
        if any(not 0 <= r < 1 for r in args.risk) or any(s < 0 for s in args.sigma) or any(h < 0 for h in args.hand) \
                or any(x < 0 for x in args.percept):
            raise OverhangError("risks must be from 0 to below 1, sigmas, hands and percepts >= 0")
        if any(s < 0 for s in args.switch) or args.percepts < 1:
            raise OverhangError("switch points must be whole numbers >= 0 (0: the IPE alone) and --percepts >= 1")
        from overhang_framework.fit.motor import Motor

        if args.motor_sd is not None and not 0 < args.motor_sd <= 0.5:
            raise OverhangError(f"--motor-sd must be a number of metres above 0 and at most 0.5, got {args.motor_sd}")
        motor = None if args.motor_sd is None else Motor(float(args.motor_sd))
        df = require_records(read_log([str(p) for p in args.logs]), args.logs)
        registry = Registry()
        world = registry.create("world", {"name": "overhang", "physics": args.physics})
    except (OverhangError, OSError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    grid = Grid(tuple(args.sigma), tuple(args.K), tuple(args.depths), tuple(args.risk),
                hands=tuple(float(h) for h in args.hand), percepts=tuple(float(x) for x in args.percept),
                switches=tuple(int(x) for x in args.switch))
    placements = log_placements(df)
    people = sorted({p.participant for p in placements})
    conditions = {p.participant: p.condition for p in placements}
    if args.condition:
        people = [p for p in people if conditions[p] in args.condition]
    if args.first is not None:
        if args.first < 1:
            print(f"error: --first must be a whole number >= 1, got {args.first}", file=sys.stderr)
            return 2
        people = people[: args.first]
    import json

    from overhang_framework.results import file_sha256

    settings = {"logs": [file_sha256(p) for p in args.logs], "grid": grid.settings(), "draws": args.draws,
                "bank": args.bank, "seed": args.seed, "physics": args.physics}
    if args.condition:
        settings["conditions"] = sorted(set(args.condition))
    if args.first is not None:
        settings["first"] = args.first
    if motor is not None:  # a fit without one keeps the settings it had
        settings["motor"] = motor.describe()
    if any(grid.percepts):
        settings["percepts"] = args.percepts
    if any(grid.switches):  # the CNN by its weights
        from overhang_framework.fit.scores import content_identity

        settings["cnn"] = content_identity({"name": "cnn"})
    args.out.mkdir(parents=True, exist_ok=True)
    kept = args.out / "marginal.json"
    if kept.is_file() and json.loads(kept.read_text()) != json.loads(json.dumps(settings)):
        print(f"error: {args.out} holds a fit of other logs or settings ({kept}); use another --out", file=sys.stderr)
        return 2
    atomic_write_text(kept, json.dumps(settings, indent=2, sort_keys=True))
    parts = args.out / "parts"
    parts.mkdir(exist_ok=True)

    def part(participant: str) -> Path:
        return parts / (hashlib.sha256(participant.encode()).hexdigest()[:16] + ".csv")

    todo = [p for p in people if not part(p).is_file()]
    if len(todo) < len(people):
        print(f"{len(people) - len(todo)} participants' fits kept in {parts} from a stopped run", file=sys.stderr)
    started = time.perf_counter()
    units = [(participant, conditions[participant],
              map_placements(world, [p for p in placements if p.participant == participant], "logged", motor))
             for participant in todo]
    setup_args = (args.physics, grid, args.draws, args.bank, args.seed, args.percepts)
    bar = progress_bar(total=len(units), desc="participants", unit="participant")
    try:
        if args.jobs > 1 and len(units) > 1:
            from overhang_framework.parallel import pool_map

            results = ((item[0], rows) for item, rows, _ in pool_map(_setup, setup_args, _work, units, args.jobs,
                                                                       lambda: None, in_flight=args.jobs))
        else:
            state = _setup(*setup_args)
            results = ((unit[0], _work(state, unit)) for unit in units)
        for participant, rows in results:
            atomic_write_text(part(participant), pd.DataFrame(rows).to_csv(index=False))
            bar.update(1)
    except KeyboardInterrupt:
        print(f"interrupted: the finished participants' fits are kept in {parts}; run the same command to "
              "continue", file=sys.stderr)
        return 130
    finally:
        bar.close()
    seconds = time.perf_counter() - started
    frames = [pd.read_csv(part(p)) for p in people]
    fits = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    choices = fits.pop(LOGP) if LOGP in fits.columns else None
    atomic_write_text(args.out / "fits.csv", fits.to_csv(index=False))
    from overhang_framework.fit.compare import comparison

    fitness = _adequacy(args.out, world, fits, choices, placements, args.seed, motor)
    comparison(fits, args.out, adequacy=fitness, motor=None if motor is None else motor.describe())
    print(f"fitted {len(units)} participants x {len(grid.depths)} depths in {seconds:.0f} s ({len(people)} in "
          f"fits.csv); wrote {args.out / 'fits.csv'} and {args.out / 'comparison.md'}")
    return 0


def _adequacy(out: Path, world, fits: pd.DataFrame, choices: Optional[pd.Series], placements, seed: int,
              motor=None) -> Optional[dict]:
    """Whether any model describes the participants (:mod:`overhang_framework.fit.adequacy`), from each one's best
    model's probabilities of their grid actions (kept in the parts); written to ``out/adequacy.*``. None (and
    nothing written) when some part predates those probabilities."""
    from overhang_framework.fit import adequacy
    from overhang_framework.fit.equivalence import best_sets, with_neutral
    from overhang_framework.fit.fitting import map_placements
    from overhang_framework.results import atomic_write_json, atomic_write_text

    if choices is None or choices.isna().any():
        return None
    best = best_sets(with_neutral(fits))
    first = {str(r.participant): r.members[0] for r in best.itertuples(index=False)}
    rows = []
    for i, r in fits.iterrows():
        participant = str(r["participant"])
        if first.get(participant) != str(r["model"]):
            continue
        mapped = map_placements(world, [p for p in placements if p.participant == participant], "logged", motor)
        logp = [float(v) for v in str(choices[i]).split(";") if v]
        if len(logp) != len(mapped.states):
            return None
        rows += adequacy.rows_of(world, participant, str(r["condition"]), mapped.states, mapped.chosen, logp,
                                 mapped.weights)
    people, summary = adequacy.assess(rows, seed)
    summary.update(fits=adequacy.fits_digest(out), sentence=adequacy.sentence(summary))
    atomic_write_text(out / "adequacy.csv", people.to_csv(index=False))
    atomic_write_json(out / "adequacy.json", summary)
    return summary


def _setup(physics: str, grid: Grid, draws: int, bank: int, seed: int, percepts: int = PERCEPTS) -> dict:
    """A worker's world, value and banks (each worker draws the same bank: a node's draws follow its key)."""
    from overhang_framework.plugins import Registry

    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": physics})
    return {"world": world, "value": registry.create("value", {"name": "overhang"}, world=world), "grid": grid,
            "draws": draws, "bank": bank, "seed": seed, "banks": {}, "percepts": percepts}


def _work(state: dict, unit) -> list[dict]:
    """One participant's rows: ``unit`` is (participant, condition, its mapped placements)."""
    participant, condition, mapped = unit
    rows = fit_participant(state["world"], state["value"], mapped.states, mapped.chosen, state["grid"],
                           state["draws"], state["bank"], state["seed"], state["banks"], mapped.weights,
                           state["percepts"])
    return [{"participant": participant, "condition": condition, **row, "unmapped": mapped.unmapped} for row in rows]


if __name__ == "__main__":
    sys.exit(main())

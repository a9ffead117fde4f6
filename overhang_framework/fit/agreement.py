"""The simulator against the likelihood: ``python -m overhang_framework.fit.agreement --out DIR``.

For each case (a decision state and a simulated participant's parameters: depth, the IPE's ``K``, softmax,
lapse, risk, the hand it plans for, its percept), simulates ``choices`` decisions with the participants' own
code (:func:`overhang_framework.behaviour.participants.decide`) and fresh draws of every stochastic part, and
compares their frequencies with the likelihood's ``P(a)`` (:meth:`overhang_framework.fit.choice.BankChoice.prob`)
by a G-test per case, with Holm's correction over the cases at ``alpha`` (0.01). Both draw the IPE's noise from
one bank of 200 static-physics noise draws per node (:class:`~overhang_framework.fit.choice.VerdictBank`);
nothing else is shared: the simulated choices, the likelihood's Monte Carlo and the bank have seeds of their own.

Beside it the same choices are tested against the likelihood the fit's score tables gave before the
participant's own noise entered it (one fixed draw of the noise per node,
:func:`~overhang_framework.fit.choice.fixed_draw_prob`), with the test's power to reject that likelihood.

Writes ``agreement.csv`` (one row per case, kept as each case ends: a stopped run continues where it stopped),
``cases/case-<n>.json`` (each case's counts and both likelihoods' probabilities, from which its row is
recomputed) and ``agreement.md`` (what was found, in sentences, and the table). ``--quick`` runs a small grid with fewer
choices (about a minute); ``--only N`` runs the cases whose number is given (repeatable).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

import numpy as np

from overhang_framework.fit.choice import BankChoice, ChoiceParams, VerdictBank, fixed_draw_prob, g_power, g_test, holm
from overhang_framework.interfaces import State

#: The family-wise level of the tests.
ALPHA = 0.01
#: The bank's seed and size, and the seeds of the simulated choices and of the likelihood's Monte Carlo.
BANK_SEED, SAMPLE_SEED, PROB_SEED, OLD_SEED = 2026, 7, 11, 13


@dataclass
class Agreement:
    """One state's test: the sampled counts, the likelihood's probabilities, the G-test, and what it cost."""

    counts: np.ndarray
    probs: np.ndarray
    g: float
    dof: int
    p: float
    sample_seconds: float
    prob_seconds: float
    #: the largest share, over the actions, of the likelihood's Monte Carlo variance in a count's variance
    mc_share: float = 0.0

    @property
    def choices(self) -> int:
        return int(self.counts.sum())


def agreement(model: Any, state: State, choices: int, rng: np.random.Generator,
              prob: Optional[Callable[[State], np.ndarray]] = None) -> Agreement:
    """Sample ``choices`` choices of ``model`` in ``state`` with ``rng`` and test them against ``prob`` (the
    model's own by default)."""
    actions = model.world.legal_actions(state)
    started = time.perf_counter()
    counts = np.zeros(len(actions))
    for _ in range(int(choices)):
        counts[int(model.sample(state, rng))] += 1
    sampled = time.perf_counter() - started
    started = time.perf_counter()
    probs = np.asarray((prob or model.prob)(state), dtype=float)
    timed = time.perf_counter() - started
    if probs.shape != counts.shape:
        raise AssertionError(f"prob gives {probs.size} probabilities for a state of {counts.size} legal actions")
    g, dof, p = g_test(counts, probs)
    share = 0.0
    error = getattr(model, "prob_error", None)
    if prob is None and callable(error):
        se = np.asarray(error(state), dtype=float)
        var = probs * (1 - probs) / max(choices, 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(var > 0, se ** 2 / var, 0.0)
        share = float(ratio.max()) if ratio.size else 0.0
    return Agreement(counts, probs, g, dof, p, sampled, timed, share)


def rejects(model: Any, states: Sequence[State], choices: int, alpha: float, seed: int,
            prob: Optional[Callable[[State], np.ndarray]] = None) -> tuple[list[bool], list[Agreement]]:
    """Which states the test rejects (Holm at ``alpha``) when ``prob`` (the model's own by default) is the
    likelihood, and each state's test."""
    results = [agreement(model, state, choices, np.random.default_rng([seed, k]), prob)
               for k, state in enumerate(states)]
    return holm([r.p for r in results], alpha), results


# --- the grid ------------------------------------------------------------------------------------------

#: The decision states: (name, task widths, placements made as (x, layer)).
STATES = {
    "A": ((1.2, 0.6, 1.2, 0.6, 1.8, 0.6), ((0.4, 1),)),         # 4 placements left
    "B": ((1.2, 0.6, 1.2, 0.6, 1.8), ((0.4, 1),)),              # 3 left: depth 3 searches to the end
    "C": ((1.8, 1.2, 0.6, 1.2, 0.6, 1.8), ((0.4, 1), (0.9, 2))),  # 3 left, a tower leaning out
}


@dataclass(frozen=True)
class Case:
    """One test: a state, the participant's parameters, the choices simulated and the likelihood's draws."""

    state: str
    params: ChoiceParams
    choices: int
    draws: int


def _c(state: str, choices: int, draws: int, **params) -> Case:
    return Case(state, ChoiceParams(**{"beta": 8.0, **params}), choices, draws)


#: The full grid: every axis on and off, depths 1 and 2 at 20,000 choices, depth 3 at 5,000; K 1, 10 and 50; the
#: hybrid's CNN part.
CASES = (
    _c("A", 20_000, 100_000, depth=1, K=1),
    _c("A", 20_000, 100_000, depth=1, K=10),
    _c("A", 20_000, 100_000, depth=1, K=50),
    _c("C", 20_000, 100_000, depth=1, K=10, beta=15.0),
    _c("A", 20_000, 100_000, depth=1, K=10, lapse=0.1),
    _c("A", 20_000, 100_000, depth=1, K=10, risk=0.5),
    _c("A", 20_000, 100_000, depth=1, K=10, risk=0.3, risk_form="cvar"),
    _c("A", 20_000, 100_000, depth=1, K=10, hand=0.05),
    _c("A", 20_000, 80_000, depth=1, K=10, percept=0.03),
    _c("A", 20_000, 60_000, depth=2, K=1),
    _c("A", 20_000, 60_000, depth=2, K=10),
    _c("A", 20_000, 60_000, depth=2, K=50),
    _c("C", 20_000, 60_000, depth=2, K=10, lapse=0.05, risk=0.5),
    _c("A", 20_000, 60_000, depth=2, K=10, hand=0.05),
    _c("B", 5_000, 20_000, depth=2, K=10, percept=0.03),
    _c("B", 5_000, 20_000, depth=3, K=10),
    _c("C", 5_000, 20_000, depth=3, K=50, risk=0.5, lapse=0.05),
    # the stage-switch hybrid: the IPE judges the towers of 3 blocks, the CNN those of 4
    _c("A", 20_000, 60_000, depth=2, K=10, switch=4),
    # the paper-like person under time pressure: the CNN, a planned hand, a percept, risk and lapses
    _c("A", 5_000, 20_000, depth=1, K=50, switch=3, hand=0.13, percept=0.03, risk=0.9, lapse=0.07),
)

#: A small grid for a quick look (and the default test suite's run of the command).
QUICK = (
    _c("A", 3_000, 20_000, depth=1, K=10),
    _c("A", 3_000, 20_000, depth=1, K=1, hand=0.05, lapse=0.1),
    _c("B", 600, 4_000, depth=2, K=10, risk=0.5),
)


def build_state(world, name: str) -> State:
    from overhang_framework.geometry import Action
    from overhang_framework.interfaces import Task

    widths, placed = STATES[name]
    state = world.initial_state(Task(f"agreement-{name}", widths))
    for x, layer in placed:
        state = world.step(state, Action(x, layer))
    return state


def run_case(number: int, case: Case, world, value, bank: VerdictBank, keep: Optional[Path] = None) -> dict:
    """One case's row: the test against the likelihood, and against the fixed-draw likelihood of the fit's tables;
    with ``keep``, the counts and both likelihoods' probabilities go to ``keep/case-<number>.json``."""
    state = build_state(world, case.state)
    model = BankChoice(world, value, bank, case.params, draws=case.draws, seed=PROB_SEED + number)
    result = agreement(model, state, case.choices, np.random.default_rng([SAMPLE_SEED, number]))
    old = fixed_draw_prob(model, state, seed=OLD_SEED + number)
    g_old, dof_old, p_old = g_test(result.counts, old)
    if keep is not None:
        from overhang_framework.results import atomic_write_json

        atomic_write_json(keep / f"case-{number}.json", {
            "case": number, "counts": result.counts.astype(int).tolist(), "probs": result.probs.tolist(),
            "prob_error": model.prob_error(state).tolist(), "fixed_draw_probs": old.tolist()})
    freq = result.counts / max(result.counts.sum(), 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        gap = float(np.sum(np.where(freq > 0, freq * (np.log(result.probs) - np.log(old)), 0.0)))
    return {"case": number, "state": case.state, **{k: v for k, v in asdict(case.params).items() if k != "hand_nodes"},
            "actions": len(result.probs), "choices": case.choices, "draws": case.draws,
            "g": result.g, "dof": result.dof, "p": result.p, "mc_share": result.mc_share,
            "g_old": g_old, "dof_old": dof_old, "p_old": p_old, "power_old": g_power(result.probs, old, case.choices, ALPHA),
            "loss_old": gap,
            "sample_seconds": result.sample_seconds, "prob_seconds": result.prob_seconds}


def report(rows: list[dict], total: int) -> str:
    """``agreement.md``: what was found, in sentences, then the table."""
    import pandas as pd

    from overhang_framework.behaviour.analysis import markdown_table

    df = pd.DataFrame(rows).sort_values("case")
    new = holm(list(df["p"]), ALPHA)
    old = holm(list(df["p_old"]), ALPHA)
    done = f"{len(df)} of {total} cases" if len(df) < total else f"all {total} cases"
    lines = ["# The simulator against the likelihood", "",
             f"- **The likelihood** (the participant's own noise marginalised) is rejected for {sum(new)} of {done} "
             f"(G-test per case, Holm's correction at {ALPHA:g}); the smallest p is {df['p'].min():.3g}.",
             f"- **The fixed-draw likelihood** (one draw of the noise per node, as the fit's score tables gave) is "
             f"rejected for {sum(old)} of them on the same choices; the test's power to reject it was "
             f"{df['power_old'].min():.2f} to {df['power_old'].max():.2f} (median {df['power_old'].median():.2f}). "
             f"It gives the simulated choices {_loss(df, 'median')} nats less log-likelihood per choice than the "
             f"likelihood does (median over the cases; {_loss(df, 'min')} to {_loss(df, 'max')}).",
             f"- The likelihood's Monte Carlo variance is at most {df['mc_share'].max():.0%} of a count's sampling "
             "variance in any cell, too little to make a G-test reject.", "",
             markdown_table(["case", "state", "depth", "K", "beta", "lapse", "risk", "hand", "percept", "actions",
                             "choices", "G (df)", "p", "Holm", "old G (df)", "old p", "old Holm", "power vs old",
                             "seconds"],
                            [[r.case, r.state, r.depth, r.K, f"{r.beta:g}", f"{r.lapse:g}",
                              f"{r.risk:g}" + (" cvar" if r.risk and r.risk_form == "cvar" else ""), f"{r.hand:g}",
                              f"{r.percept:g}", r.actions, r.choices, f"{r.g:.1f} ({r.dof})", f"{r.p:.3g}",
                              "reject" if a else "keep", f"{r.g_old:.1f} ({r.dof_old})", f"{r.p_old:.3g}",
                              "reject" if b else "keep", f"{r.power_old:.2f}",
                              f"{r.sample_seconds + r.prob_seconds:.0f}"]
                             for r, a, b in zip(df.itertuples(), new, old)]),
             "", "Command: `python -m overhang_framework.fit.agreement --out DIR` (the full grid; `--quick`, a small one).",
             "Each participant's IPE draws its noise from one bank of 200 static-physics noise draws per node, as the "
             "likelihood does; the choices are simulated by `behaviour.participants.decide` with the lookahead planner, "
             "a softmax and no call budget."]
    return "\n".join(lines) + "\n"


def main(argv: Optional[Sequence[str]] = None) -> int:
    import pandas as pd

    from overhang_framework.plugins import Registry
    from overhang_framework.results import atomic_write_text

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.fit.agreement",
                                     description="Test the fit's likelihood against the simulated participants' own "
                                                 "choice frequencies (G-tests, Holm).")
    parser.add_argument("--out", type=Path, required=True, help="where agreement.csv and agreement.md go")
    parser.add_argument("--quick", action="store_true", help="a small grid with fewer choices (about a minute)")
    parser.add_argument("--only", type=int, action="append", default=None, help="run only this case (repeatable)")
    parser.add_argument("--summary", type=Path, default=None,
                        help="also write the findings' figures to this JSON file")
    args = parser.parse_args(argv)
    cases = QUICK if args.quick else CASES
    if args.only and any(not 0 <= k < len(cases) for k in args.only):
        print(f"error: --only takes case numbers from 0 to {len(cases) - 1}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "agreement.csv"
    rows = pd.read_csv(path).to_dict("records") if path.is_file() else []
    done = {int(r["case"]) for r in rows}
    registry = Registry()
    world = registry.create("world", {"name": "overhang", "physics": "static"})
    value = registry.create("value", {"name": "overhang"}, world=world)
    bank = VerdictBank(world, sigma=0.03, seed=BANK_SEED)
    for number, case in enumerate(cases):
        if number in done or (args.only and number not in args.only):
            continue
        started = time.perf_counter()
        (args.out / "cases").mkdir(exist_ok=True)
        row = run_case(number, case, world, value, bank, args.out / "cases")
        rows.append(row)
        atomic_write_text(path, pd.DataFrame(rows).sort_values("case").to_csv(index=False))
        print(f"case {number} ({case.state}, {case.params.label()}): p = {row['p']:.3g}, fixed-draw p = "
              f"{row['p_old']:.3g}, {time.perf_counter() - started:.0f} s", flush=True)
    if rows:
        atomic_write_text(args.out / "agreement.md", report(rows, len(cases)))
        print(f"wrote {args.out / 'agreement.md'}")
        if args.summary is not None:
            from overhang_framework.results import atomic_write_json

            atomic_write_json(args.summary, summary(rows, len(cases)))
    return 0


def _loss(df, how: str) -> str:
    if "loss_old" not in df.columns:
        return "?"
    return f"{float(getattr(df['loss_old'].astype(float), how)()):.3f}"


def summary(rows: list[dict], total: int) -> dict:
    """The findings' figures of :func:`report` as plain numbers."""
    import pandas as pd

    df = pd.DataFrame(rows).sort_values("case")
    seconds = df["sample_seconds"] + df["prob_seconds"]
    return {"cases": int(len(df)), "total": int(total), "rejected": int(sum(holm(list(df["p"]), ALPHA))),
            "rejected_old": int(sum(holm(list(df["p_old"]), ALPHA))), "min_p": float(df["p"].min()),
            "max_p_old": float(df["p_old"].max()), "power_old_min": float(df["power_old"].min()),
            "power_old_median": float(df["power_old"].median()), "mc_share_max": float(df["mc_share"].max()),
            "choices": int(df["choices"].sum()), "minutes": float(seconds.sum() / 60),
            "loss_old_median": float(df["loss_old"].astype(float).median()) if "loss_old" in df.columns else None}


if __name__ == "__main__":
    sys.exit(main())

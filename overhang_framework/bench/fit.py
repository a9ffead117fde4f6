"""The cost of exact likelihoods: ``python -m overhang_framework.bench.fit [--log LOG ...]``.

Prints, for each model of the fit's model space (IPE, CNN and hybrid, each myopic,
D=2 and D=3), the cost of one decision state's score table (seconds and predictor
calls, every root action's score exact, on a fresh expander and no cache), on
decision states sampled from a behaviour log; and how much reuse saves:

* **states shared across participants**: the decisions of the log against its
  distinct decision states, with the logged towers (the fit's default) and with
  the grid states of ``states=grid`` (opt-in);
* **subtrees shared across the steps of a trial**: a trial's tables computed on
  one expander (as the fit does) against a fresh expander per table.

It then projects the cold-cache cost of fitting the log in one process (tables x
distinct decision states as the fit builds them by default, ``states=logged``, one
table per sigma of a grid) from the measured seconds per table.

With ``--space``, it also times the fit's default model space (``conf/space/default.yaml``: the IPE's sigma grid,
the CNN, the hybrid at every switch point; myopic and D=2), or with ``--space NAME`` another
(``--space explanations``: the explanations of people's errors, docs/people.md), on whole trials, as one fit process computes them
(predictors shared, one expander per model), with the tables that are the same numbers shared
(:func:`~overhang_framework.fit.scores.share_tables`: the hybrid's switch points) and without, alternating
trial by trial, and prints tables computed, seconds and the largest difference between the two.

With ``--compare``, each model whose family has a reference setting (:data:`REFERENCES`:
the way it was computed before the engine's speed-ups, e.g. the CNN unfused and asked
state by state) is also timed that way on the same states, alternating state by state,
and the run prints both times, their ratio and the largest difference between the two
score tables. Predictors' answer caches are emptied before every timed table. With
``--reference nnls`` the reference is today's code with the LP stage's systems built in NumPy and
solved one SciPy call per system (:data:`REFERENCES_NNLS`; the IPE and the hybrid).

Without ``--log``, the log is the synthetic study of
``python -m overhang_framework.bench.analysis`` (paper size, ``--scale`` of it).
Measured on whatever else the machine is doing: the figures are of this run.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

#: The benchmark's models: family -> predictor config.
FAMILIES = {"ipe": {"name": "ipe", "K": 50, "sigma": 0.03}, "cnn": {"name": "cnn"}, "hybrid": {"name": "hybrid"}}
#: ``--compare``: family -> the predictor config that computes its tables as before the speed-ups.
_BEFORE_STATIC = {"lp_nnls": False, "compiled": False}
REFERENCES = {"ipe": {"name": "ipe", "K": 50, "sigma": 0.03, "scenes": "objects", "backend_params": _BEFORE_STATIC},
              "cnn": {"name": "cnn", "fused": False, "batch_size": 512},
              "hybrid": {"name": "hybrid", "early_params": {"scenes": "objects", "backend_params": _BEFORE_STATIC},
                         "late_params": {"fused": False, "batch_size": 512}}}
#: ``--compare --reference nnls``: today's code with the LP stage's systems built in NumPy and solved one SciPy
#: call per system.
_SCIPY_NNLS = {"nnls": "scipy"}
REFERENCES_NNLS = {"ipe": {"name": "ipe", "K": 50, "sigma": 0.03, "backend_params": _SCIPY_NNLS},
                   "hybrid": {"name": "hybrid", "early_params": {"backend_params": _SCIPY_NNLS}}}


def _timed_table(world, value, predictor, model, context, state) -> tuple[float, int, np.ndarray]:
    """Seconds, predictor calls and scores of one cold table (fresh expander, the predictor's cache emptied)."""
    from overhang_framework.fit.scores import ScoreTables

    clear = getattr(predictor, "clear_cache", None)
    if callable(clear):
        clear()
    tables = ScoreTables(world, value, predictor, model, context, None)
    t0 = time.perf_counter()
    scores = tables.table(state)
    return time.perf_counter() - t0, tables.stats.predictor_calls, scores


def _log(args, world_overrides: Sequence[str]) -> Path:
    if args.log:
        return Path(args.log)
    from overhang_framework.behaviour.analysis import build_world
    from overhang_framework.behaviour.log import write_log
    from overhang_framework.bench.analysis import CONDITIONS, synthetic_log
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    tasks = tasks_from_config(compose_config(list(world_overrides)).tasks)
    conditions = {c: (max(1, round(n * args.scale)), *rest) for c, (n, *rest) in CONDITIONS.items()}
    world = build_world(list(world_overrides))
    judge = build_world([*world_overrides, "world.physics=static"])
    records = synthetic_log(world, tasks, args.seed, conditions, judge=judge)
    path = Path(tempfile.mkdtemp()) / "synthetic.jsonl"
    write_log(records, path)
    return path


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.bench.fit", description=__doc__.split("\n\n")[0])
    ap.add_argument("--log", help="behaviour log whose decision states to use (default: a synthetic paper-size one)")
    ap.add_argument("--world", action="append", default=[], metavar="OVERRIDE",
                    help="world override, e.g. world.physics=static (repeatable)")
    ap.add_argument("--scale", type=float, default=1.0, help="synthetic log's participants, share of the paper's 81")
    ap.add_argument("--states", type=int, default=6, help="decision states timed per model (default 6)")
    ap.add_argument("--depths", default="1,2,3", help="depths to time (default 1,2,3)")
    ap.add_argument("--families", default="ipe,cnn,hybrid")
    ap.add_argument("--cell-seconds", type=float, default=240.0,
                    help="stop timing a model after this many seconds (at least one table each; default 240)")
    ap.add_argument("--trials", type=int, default=3, help="trials timed for the reuse across steps (default 3)")
    ap.add_argument("--sigmas", type=int, default=5, help="sigma grid size for the IPE's projection (default 5)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--compare", action="store_true",
                    help="also time each family's reference setting (the code before) on the same states")
    ap.add_argument("--reference", choices=("engine", "nnls"), default="engine",
                    help="with --compare, what 'before' is: the code before issue 33's engine (default), or "
                         "today's with the LP stage's systems built in NumPy and solved by SciPy one by one (nnls)")
    ap.add_argument("--space", nargs="?", const="default", default=None, metavar="NAME",
                    help="also time a fit's model space (conf/space/NAME.yaml; default: default) on --trials trials, "
                         "tables shared and not")
    ap.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    from overhang_framework.preflight import overrides_problem

    problem = overrides_problem(args.world)
    if problem is not None:
        print(f"error: --world: {problem}", file=sys.stderr)
        return 2
    if args.space is not None:
        from overhang_framework.config import group_options

        spaces = group_options("space")
        if args.space not in spaces:
            print(f"error: --space: unknown space {args.space!r}; available: {', '.join(spaces)}", file=sys.stderr)
            return 2

    from overhang_framework.behaviour.analysis import build_world
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.fit.fitting import log_placements, map_placements
    from overhang_framework.fit.scores import Model, ScoreTables
    from overhang_framework.plugins import Registry
    from overhang_framework.search import state_key

    started = time.perf_counter()
    path = _log(args, args.world)
    df = read_log(path)
    placements = log_placements(df)
    blocks = max((len(seq) for seq in df["sequence"]), default=None)  # as the fit finds its switch points
    world = build_world(list(args.world))
    registry = Registry()
    value = registry.create("value", {"name": "overhang"}, world=world)
    context = {"world": {"bench": list(args.world)}, "value": {"name": "overhang"}}
    grid = map_placements(world, placements, "grid")
    logged = map_placements(world, placements, "logged")
    n_logged = len({state_key(s) for s in logged.states})
    n_grid = len({state_key(s) for s in grid.states})
    figures: dict = {"log": str(path), "decisions": len(grid.states), "distinct_logged": n_logged,
                     "distinct_grid": n_grid, "unmapped": grid.unmapped, "tables": [], "reuse": {}}
    print(f"log {path}: {len(placements)} placements, {len(grid.states)} mapped to the grid "
          f"({grid.unmapped} unmapped)", flush=True)
    print(f"states shared across participants: {n_logged} distinct logged states "
          f"({len(logged.states) / max(n_logged, 1):.2f} decisions each), {n_grid} distinct grid states "
          f"({len(grid.states) / max(n_grid, 1):.2f} decisions each)", flush=True)

    # the timed states: distinct decision states (logged, the fit's default), sampled across steps
    rng = np.random.default_rng(args.seed)
    distinct = list({state_key(s): s for s in logged.states}.values())
    sample = [distinct[i] for i in rng.choice(len(distinct), min(args.states, len(distinct)), replace=False)]
    depths = [int(d) for d in args.depths.split(",") if d]
    families = [f for f in args.families.split(",") if f]
    predictors = {f: registry.create("predictor", dict(FAMILIES[f]), world=world) for f in families}
    chosen = REFERENCES if args.reference == "engine" else REFERENCES_NNLS
    references = {f: registry.create("predictor", dict(chosen[f]), world=world)
                  for f in families if args.compare and f in chosen}
    for f in families:  # warm up (a network's first call, a backend's start)
        for predictor in (predictors[f], references.get(f)):
            if predictor is not None:
                ScoreTables(world, value, predictor, Model(FAMILIES[f], 1), context, None).table(sample[0])
    print(f"\nscore table of one decision state (every root action exact; fresh expander, no cache; "
          f"{len(sample)} states, at most {args.cell_seconds:g} s per model):", flush=True)
    print(f"  {'model':<14}{'tables':>7}{'s/table':>10}{'calls/table':>13}{'projected cold fit':>22}", flush=True)
    for depth in depths:
        for f in families:
            model = Model(FAMILIES[f], depth)
            seconds, calls, done = [], [], 0
            before, difference, same_best = [], 0.0, 0
            t_cell = time.perf_counter()
            for state in sample:
                if f in references and done % 2 == 0:  # alternate which goes first
                    old = _timed_table(world, value, references[f], model, context, state)
                t, n_calls, scores = _timed_table(world, value, predictors[f], model, context, state)
                if f in references and done % 2 == 1:
                    old = _timed_table(world, value, references[f], model, context, state)
                if f in references:
                    before.append(old[0])
                    difference = max(difference, float(np.max(np.abs(scores - old[2]), initial=0.0)))
                    same_best += int(np.argmax(scores) == np.argmax(old[2])) if len(scores) else 1
                seconds.append(t)
                calls.append(n_calls)
                done += 1
                if time.perf_counter() - t_cell > args.cell_seconds:
                    break
            per = float(np.mean(seconds))
            variants = args.sigmas if f == "ipe" else 1
            projected = per * n_logged * variants
            row = {"model": model.label, "tables": done, "seconds_per_table": per,
                   "calls_per_table": float(np.mean(calls)), "projected_cold_seconds": projected,
                   "variants": variants}
            figures["tables"].append(row)
            print(f"  {model.label:<14}{done:>7}{per:>10.3f}{row['calls_per_table']:>13.1f}"
                  f"{projected / 60:>14.1f} min{' (x' + str(variants) + ' sigma)' if variants > 1 else '':>8}",
                  flush=True)
            if before:
                old_per = float(np.mean(before))
                row.update({"reference": dict(chosen[f]), "reference_seconds_per_table": old_per,
                            "speedup": old_per / per, "max_score_difference": difference,
                            "same_best_action": same_best})
                print(f"  {'':<14}before: {old_per:.3f} s/table, now {old_per / per:.2f}x faster; scores differ "
                      f"by at most {difference:.1e}, the same best action in {same_best} of {done} tables",
                      flush=True)
            if before and f == "hybrid" and args.reference == "engine":
                row["in_fit"] = _hybrid_in_fit(world, value, context, sample[:done], depth, blocks, before,
                                               predictors[f].switch)

    # reuse across the steps of a trial: one expander per model (the fit) against one per table
    mapped_trials = _grid_trials(world, placements)
    long = [t for t in mapped_trials if len(t) >= 4]
    chosen = [long[i] for i in rng.choice(len(long), min(args.trials, len(long)), replace=False)] if long else []
    if chosen and 2 in depths:
        f = families[0]
        model = Model(FAMILIES[f], 2)
        shared = ScoreTables(world, value, predictors[f], model, context, None)
        t0 = time.perf_counter()
        for trial in chosen:
            for state in trial:
                shared.table(state)
        t_shared, c_shared = time.perf_counter() - t0, shared.stats.predictor_calls
        t0, c_fresh = time.perf_counter(), 0
        for trial in chosen:
            for state in trial:
                fresh = ScoreTables(world, value, predictors[f], model, context, None)
                fresh.table(state)
                c_fresh += fresh.stats.predictor_calls
        t_fresh = time.perf_counter() - t0
        n_tables = sum(len(t) for t in chosen)
        figures["reuse"] = {"model": model.label, "trials": len(chosen), "tables": n_tables,
                            "shared_seconds": t_shared, "shared_calls": c_shared, "fresh_seconds": t_fresh,
                            "fresh_calls": c_fresh}
        print(f"\nsubtrees shared across the steps of a trial ({model.label}, {len(chosen)} trials, {n_tables} "
              f"tables): one expander {t_shared:.1f} s / {c_shared} calls; a fresh one per table "
              f"{t_fresh:.1f} s / {c_fresh} calls (saves {1 - t_shared / max(t_fresh, 1e-9):.0%} of the time)",
              flush=True)
    if args.space and long:
        figures["space"] = _space(world, value, context, placements, blocks, args, rng)
    figures["seconds"] = time.perf_counter() - started
    print(f"\nbenchmark took {figures['seconds']:.0f} s", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2))
    return 0


def _space(world, value, context, placements, blocks, args, rng) -> dict:
    """The fit's default model space on whole logged trials, as a fit process computes it (predictors shared,
    tables that are the same numbers shared), against each model's own tables, and against the code before the
    hybrid drew as its early part (its own draws: its all-IPE tables computed, not the IPE's)."""
    from unittest import mock

    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.fit.fitting import map_placements
    from overhang_framework.fit.run import Predictors
    from overhang_framework.fit.scores import Model, ScoreTables, share_memory, share_tables
    from overhang_framework.fit.space import model_space
    from overhang_framework.plugins import Registry

    conf = compose_config([f"space={args.space}"], config_name="fit")
    space = model_space(OmegaConf.to_container(conf.models, resolve=True), list(conf.depths), blocks)
    by_trial: dict[tuple, list] = {}
    for p in placements:
        by_trial.setdefault((p.participant, p.trial), []).append(p)
    trials = [map_placements(world, ps, "logged").states for ps in by_trial.values()]
    trials = [trials[i] for i in rng.choice(len(trials), min(args.trials, len(trials)), replace=False)]
    built = Predictors(Registry(), world)
    models = [m for index in space for m in index.variants]
    names = ("shared", "each", "before")
    arms = {a: {"seconds": 0.0, "computed": 0} for a in names}
    difference = 0.0
    print(f"\nthe fit's {args.space} model space ({len(models)} models) on {len(trials)} logged trials "
          f"({sum(len(t) for t in trials)} states): as a fit computes it, each model's own tables, and "
          "hybrids drawing their own (before):", flush=True)
    own_draws = mock.patch.object(Model, "draw_settings", lambda self: self.predictor)
    for n, trial in enumerate(trials):
        results = {}
        for arm in names[n % 3:] + names[:n % 3]:  # rotate which goes first
            for predictor in list(built.built.values()):
                clear = getattr(predictor, "clear_cache", None)
                if callable(clear):
                    clear()
            with own_draws if arm == "before" else contextlib.nullcontext():
                tables = [ScoreTables(world, value, built(dict(m.predictor)), m, context, None) for m in models]
                share_memory(tables)
                if arm != "each":
                    share_tables(tables)
                t0 = time.perf_counter()
                results[arm] = [[t.table(s) for s in trial] for t in tables]
                arms[arm]["seconds"] += time.perf_counter() - t0
            arms[arm]["computed"] += sum(t.stats.computed for t in tables)
        for a, b in zip(results["shared"], results["each"]):
            for x, y in zip(a, b):
                difference = max(difference, float(np.max(np.abs(x - y), initial=0.0)))
    each = arms["each"]["seconds"] / max(arms["shared"]["seconds"], 1e-9)
    before = arms["before"]["seconds"] / max(arms["shared"]["seconds"], 1e-9)
    print(f"  before (hybrids' own draws): {arms['before']['computed']} tables, {arms['before']['seconds']:.1f} s "
          f"({before:.2f}x the time now)", flush=True)
    print(f"  each model's own tables:     {arms['each']['computed']} tables, {arms['each']['seconds']:.1f} s "
          f"({each:.2f}x)", flush=True)
    print(f"  now:                         {arms['shared']['computed']} tables, {arms['shared']['seconds']:.1f} s; "
          f"the same as each model's own to {difference:.1e}", flush=True)
    return {"space": args.space, "models": len(models), "trials": len(trials), **{f"{k}_{m}": v for k, a in arms.items() for m, v in a.items()},
            "speedup": each, "speedup_over_before": before, "max_difference": difference}


def _hybrid_in_fit(world, value, context, states, depth: int, blocks: int, before: Sequence[float],
                   switch: int) -> dict:
    """The hybrid family's tables of each of ``states`` as a fit computes them, timed: every switch point of the
    default model space, after the state's IPE tables (every sigma) and the CNN's, with the fit's shared
    predictors (:class:`~overhang_framework.fit.run.Predictors`) and shared tables, answer caches emptied before
    each state. ``before`` holds the seconds of the state's one hybrid table as computed before the engine's
    speed-ups (its own predictor, one switch point), as a fit computed it then. The table of switch point
    ``switch`` is compared with the same model's table computed alone (a predictor of its own), untimed."""
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.fit.run import Predictors
    from overhang_framework.fit.scores import ScoreTables, share_memory, share_tables
    from overhang_framework.fit.space import model_space
    from overhang_framework.plugins import Registry

    conf = compose_config([], config_name="fit")
    space = model_space(OmegaConf.to_container(conf.models, resolve=True), [depth], blocks)
    models = [m for index in space for m in index.variants]
    built = Predictors(Registry(), world)
    registry = built.registry
    chosen = [m for m in models if m.family == "hybrid" and m.predictor.get("switch") == switch]
    alone = registry.create("predictor", dict(chosen[0].predictor), world=world) if chosen else None
    seconds, computed, switches, difference, early, compared = [], 0, 0, 0.0, 0, 0
    for state in states:
        early += len(state.geometry) + 1 < switch  # the early part judges some of the towers
        for predictor in list(built.built.values()):
            clear = getattr(predictor, "clear_cache", None)
            if callable(clear):
                clear()
        tables = [ScoreTables(world, value, built(dict(m.predictor)), m, context, None) for m in models]
        share_memory(tables)
        share_tables(tables)
        hybrid = [t for t, m in zip(tables, models) if m.family == "hybrid"]
        for t in tables:
            if all(t is not h for h in hybrid):
                t.compute(state)
        t0 = time.perf_counter()
        for t in hybrid:
            t.compute(state)
        seconds.append(time.perf_counter() - t0)
        computed += sum(t.stats.computed for t in hybrid)
        switches = len(hybrid)
        if alone is not None:
            own = _timed_table(world, value, alone, chosen[0], context, state)[2]
            shared = hybrid[[t.model for t in hybrid].index(chosen[0])].table(state)
            difference = max(difference, float(np.max(np.abs(shared - own), initial=0.0)))
            compared += 1
    now, old = float(np.mean(seconds)), float(np.mean(before))
    print(f"  {'':<14}in a fit: the hybrid's {switches} switch points together {now:.3f} s a state, "
          f"{computed / max(len(states), 1):.1f} tables of them computed (the rest are the CNN's and the IPE's), "
          f"after the state's IPE and CNN tables; before, its one table {old:.3f} s: {old / now:.1f}x faster; "
          f"switch point {switch}'s table differs from the one computed alone by at most {difference:.1e}",
          flush=True)
    return {"switch_points": switches, "seconds_per_state": now, "computed_per_state": computed / max(len(states), 1),
            "reference_seconds_per_state": old, "speedup": old / now, "states": len(states),
            "max_score_difference": difference, "states_with_early_part": early, "states_compared": compared}


def _grid_trials(world, placements) -> list[list]:
    """Each trial's grid decision states, in step order (what ``map_placements`` builds, per trial)."""
    from overhang_framework.fit.fitting import map_placements

    by_trial: dict[tuple, list] = {}
    for p in placements:
        by_trial.setdefault((p.participant, p.trial), []).append(p)
    return [map_placements(world, ps, "grid").states for ps in by_trial.values()]


if __name__ == "__main__":
    raise SystemExit(main())

"""Simulated participants (``python -m overhang_framework.participants``): log, parameters, conditions, errors."""

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from overhang_framework.behaviour import read_log
from overhang_framework.config import compose_config
from overhang_framework.geometry import Action, Block, Geometry
from overhang_framework.interfaces import State

# two short tasks, static physics, a cheap IPE, 2 participants per condition
TINY = ["tasks=custom", "tasks.sequences=[[1.2,0.6,1.2],[0.6,1.2,0.6,0.6],[1.8,0.6,0.6]]",
        "world.physics=static", "predictor.K=10", "progress=false",
        "cohort.participants.time_limited=2", "cohort.participants.unconstrained=2", "cohort.n_tasks=null"]


def replace(key: str, spec: str) -> list[str]:
    """The overrides that replace the distribution at ``key`` (a dict override would merge into it)."""
    return [f"~{key}", f"+{key}={spec}"]


def simulate_into(tmp_path: Path, *overrides: str, name: str = "run") -> Path:
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    cfg = compose_config([*TINY, *overrides], config_name=CONFIG_NAME)
    out = tmp_path / name
    run(cfg, out)
    return out


def participants(out: Path) -> list[dict]:
    with open(out / "participants.csv") as fh:
        return list(csv.DictReader(fh))


def tower(blocks) -> Geometry:
    return Geometry(tuple(Block(float(w), float(x), int(layer)) for w, x, layer in blocks))


@pytest.fixture(scope="module")
def world():
    from overhang_framework.plugins import Registry

    return Registry().create("world", {"name": "overhang", "physics": "static"})


@pytest.fixture(scope="module")
def default_run(tmp_path_factory):
    return simulate_into(tmp_path_factory.mktemp("sim"), "cohort.motor.sd=0.05")


def test_the_same_seed_gives_a_byte_identical_log_and_another_seed_another(tmp_path, default_run):
    again = simulate_into(tmp_path, "cohort.motor.sd=0.05", name="again")
    assert (again / "log.jsonl").read_bytes() == (default_run / "log.jsonl").read_bytes()
    assert (again / "participants.csv").read_bytes() == (default_run / "participants.csv").read_bytes()
    other = simulate_into(tmp_path, "cohort.motor.sd=0.05", "seed=1", name="other")
    assert (other / "log.jsonl").read_bytes() != (default_run / "log.jsonl").read_bytes()
    assert (other / "participants.csv").read_bytes() != (default_run / "participants.csv").read_bytes()


def test_the_log_validates_and_names_participants_conditions_and_source(default_run):
    df = read_log(default_run / "log.jsonl")
    assert sorted(df.participant.unique()) == ["sim-tl-001", "sim-tl-002", "sim-un-001", "sim-un-002"]
    assert set(df.condition) == {"time_limited", "unconstrained"}
    assert set(df.source) == {"simulated"}
    # every participant does every task once, trials 1..3 in an order of its own
    for _, rows in df.groupby("participant"):
        assert sorted(rows.task_id.unique()) == ["custom00", "custom01", "custom02"]
        assert sorted(rows.trial.unique()) == [1, 2, 3]
    orders = {p: tuple(rows.sort_values("trial").task_id.unique()) for p, rows in df.groupby("participant")}
    assert len(set(orders.values())) > 1
    assert [r["id"] for r in participants(default_run)] == sorted(orders)


def test_motor_noise_keeps_x_legal_and_continuous(default_run, world):
    df = read_log(default_run / "log.jsonl")
    placed = df[~df.timed_out]
    assert (placed.x != placed.grid_x).mean() > 0.5  # off the 0.1 grid
    assert np.all(np.abs(placed.x - placed.grid_x) < 0.5)
    for row in placed.itertuples():
        state = State(tower(row.tower_before), tuple(row.sequence[row.step:]))
        assert world.is_legal(state, Action(row.x, int(row.layer))), row


def test_stable_is_the_worlds_verdict_on_the_logged_tower(default_run, world):
    df = read_log(default_run / "log.jsonl")
    placed = df[~df.timed_out]
    verdicts = [world.is_stable(tower([*row.tower_before, [row.width, row.x, row.layer]]))
                for row in placed.itertuples()]
    assert list(placed.stable) == verdicts


FIXED_BETA = replace("cohort.parameters.beta", "{dist: fixed, value: 7.5}")


def test_parameters_follow_the_configured_distributions(tmp_path):
    out = simulate_into(tmp_path, "cohort.participants.time_limited=20", "cohort.participants.unconstrained=0",
                        "cohort.n_tasks=1", *FIXED_BETA)
    rows = participants(out)
    assert len(rows) == 20
    assert {int(r["depth"]) for r in rows} == {1, 2}
    assert all(0 <= float(r["lapse"]) <= 1 for r in rows)
    assert all(float(r["beta"]) == 7.5 for r in rows)
    sigmas = np.array([float(r["sigma"]) for r in rows])
    assert np.all(sigmas > 0)
    # lognormal around 0.03 with sigma 0.3: the log's mean and spread
    assert abs(np.log(sigmas).mean() - math.log(0.03)) < 0.25
    assert 0.15 < np.log(sigmas).std() < 0.5
    # the parameters come from their own generator: behaviour settings leave them unchanged
    same = simulate_into(tmp_path, "cohort.participants.time_limited=20", "cohort.participants.unconstrained=0",
                         "cohort.n_tasks=1", *FIXED_BETA, "cohort.motor.sd=0.1", name="same")
    assert participants(same) == rows


DEPTH2 = replace("cohort.parameters.depth", "{dist: fixed, value: 2}")


def test_time_limited_participants_stay_within_the_call_budget_and_decide_faster(tmp_path):
    out = simulate_into(tmp_path, *DEPTH2, "conditions.time_limited.call_limit=3")
    df = read_log(out / "log.jsonl")
    limited, free = df[df.condition == "time_limited"], df[df.condition == "unconstrained"]
    assert limited.predictor_calls.max() == 3
    assert free.predictor_calls.max() > 3
    assert free.depth_completed.mean() > limited.depth_completed.mean()
    assert free.decision_time.mean() > limited.decision_time.mean()


def test_a_decision_over_the_time_limit_times_out_and_ends_the_trial(tmp_path):
    out = simulate_into(tmp_path, "cohort.decision_time.t0=10")
    df = read_log(out / "log.jsonl")
    limited, free = df[df.condition == "time_limited"], df[df.condition == "unconstrained"]
    assert limited.timed_out.all() and (limited.step == 1).all()
    assert (limited.reward == 0).all() and (limited.decision_time == 5.0).all()
    assert limited.x.isna().all()
    assert not free.timed_out.any() and (free.decision_time > 10 * 0.5).all()


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "overhang_framework.participants", *args],
                          capture_output=True, text=True, cwd=cwd)


def test_a_sweep_over_seeds_with_the_basic_launcher(tmp_path):
    proc = _cli("-m", *TINY, "cohort.participants.time_limited=1", "cohort.participants.unconstrained=1",
                "seed=0,1", f"hydra.sweep.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    jobs = sorted(p for p in tmp_path.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in jobs] == ["0", "1"]
    logs = [read_log(p / "log.jsonl") for p in jobs]
    assert all(len(df) and (p / "participants.csv").exists() for df, p in zip(logs, jobs))
    assert (jobs[0] / "log.jsonl").read_bytes() != (jobs[1] / "log.jsonl").read_bytes()


@pytest.mark.parametrize("overrides, words", [
    (["cohort.parameters.sigma.dist=gamma"], "unknown distribution 'gamma'"),
    (replace("cohort.parameters.lapse", "{dist: fixed, value: -0.1}"), "cohort.parameters.lapse must give a probability"),
    (["cohort.parameters.depth.values=[1,4,9]", "cohort.parameters.depth.p=[0.2,0.4,0.4]"],
     "cohort.parameters.depth must give a depth from 1 to 5"),
    (replace("cohort.parameters.depth", "{dist: uniform, low: 1, high: 3}"), "whole numbers"),
    (["cohort=huge"], "huge"),
    (["+cohort.participants.people=3"], "not configured"),
    (["conditions.time_limited.call_limit=0"], "call_limit must be a whole number >= 1"),
    (["predictor=veridical"], "set cohort.parameters.sigma=null"),
    (["cohrt=paper"], "unknown config key 'cohrt' (did you mean 'cohort'?)"),
], ids=["distribution", "lapse", "depth", "whole-depth", "cohort", "condition", "call-limit", "sigma", "key"])
def test_a_bad_config_is_one_line_and_exit_2_before_anything_runs(tmp_path, overrides, words):
    out = tmp_path / "run"
    tiny = [w for w in TINY if not (w.startswith("predictor.") and overrides[0].startswith("predictor="))]
    proc = _cli(*tiny, *overrides, f"hydra.run.dir={out}")
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1, proc.stderr
    assert words in proc.stderr
    assert not out.exists()


def test_every_cohort_composes_and_checks():
    from overhang_framework.config import group_options
    from overhang_framework.behaviour.simulation import CONFIG_NAME, check_config

    from overhang_framework.studies.findings import STUDIES

    cohorts = group_options("cohort")
    assert {"small", "paper", "dual_transition", "null_effect"} <= set(cohorts)
    models = {cohort: words for cohort, words, _ in STUDIES.values()}  # the studies' cohorts name their predictor
    models["proposal"] = ["predictor=hybrid"]  # the calibration's library draws the hybrid's switch point
    sizes = {}
    for name in cohorts:
        cfg = compose_config([f"cohort={name}", "world.physics=static", *models.get(name, [])],
                             config_name=CONFIG_NAME)
        checked = check_config(cfg)
        assert checked.cohort.name == name
        sizes[name] = {c.name: c.n for c in checked.cohort.conditions}
    assert sizes["paper"] == {"time_limited": 43, "unconstrained": 38}


def test_participants_spread_over_processes_give_the_same_files(tmp_path, default_run):
    spread = simulate_into(tmp_path, "cohort.motor.sd=0.05", "jobs=2", name="spread")
    assert (spread / "log.jsonl").read_bytes() == (default_run / "log.jsonl").read_bytes()
    assert (spread / "participants.csv").read_bytes() == (default_run / "participants.csv").read_bytes()
    assert not (spread / "parts").exists()


def test_a_stopped_run_continues_from_its_finished_participants(tmp_path, default_run, monkeypatch):
    import overhang_framework.behaviour.simulation as app

    real = app.simulate_participant
    calls = []

    def stop_at_third(participant, *args, **kwargs):
        calls.append(participant.id)
        if len(calls) == 3:
            raise RuntimeError("the machine went down")
        return real(participant, *args, **kwargs)

    monkeypatch.setattr(app, "simulate_participant", stop_at_third)
    with pytest.raises(RuntimeError, match="went down"):
        simulate_into(tmp_path, "cohort.motor.sd=0.05", name="stopped")
    out = tmp_path / "stopped"
    kept = sorted(p.name for p in (out / "parts").iterdir())
    assert kept == sorted(f"{c}.jsonl" for c in calls[:2]) and not (out / "log.jsonl").exists()
    calls.clear()
    simulate_into(tmp_path, "cohort.motor.sd=0.05", name="stopped")
    assert len(calls) == 2  # only the two participants not yet kept
    assert (out / "log.jsonl").read_bytes() == (default_run / "log.jsonl").read_bytes()
    assert not (out / "parts").exists()
    monkeypatch.setattr(app, "simulate_participant", real)
    # another config into the same directory is refused, unless it overwrites
    from overhang_framework.rundir import RunDirError

    with pytest.raises(RunDirError, match=r"different config \(seed: 0 -> 1\)"):
        simulate_into(tmp_path, "cohort.motor.sd=0.05", "seed=1", name="stopped")
    simulate_into(tmp_path, "cohort.motor.sd=0.05", "seed=1", "overwrite=true", name="stopped")
    assert (out / "log.jsonl").read_bytes() != (default_run / "log.jsonl").read_bytes()


def test_jobs_must_be_a_whole_number_of_processes(tmp_path):
    proc = _cli(*TINY, "jobs=0", f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode == 2 and "jobs must be a whole number >= 1" in proc.stderr, proc.stderr


def test_each_condition_can_draw_from_its_own_distributions_and_time_model(tmp_path):
    out = simulate_into(tmp_path, "cohort.participants.time_limited=6", "cohort.participants.unconstrained=6",
                        "cohort.n_tasks=1", *FIXED_BETA,
                        "+cohort.by_condition.time_limited.parameters.depth={dist: fixed, value: 1}",
                        "+cohort.by_condition.unconstrained.parameters.depth={dist: fixed, value: 2}",
                        "+cohort.by_condition.unconstrained.decision_time.t0=9")
    rows = participants(out)
    depth = {r["condition"]: {int(x["depth"]) for x in rows if x["condition"] == r["condition"]} for r in rows}
    assert depth == {"time_limited": {1}, "unconstrained": {2}}
    assert all(float(r["beta"]) == 7.5 for r in rows)  # the shared distributions still apply
    df = read_log(out / "log.jsonl")
    free, limited = df[df.condition == "unconstrained"], df[df.condition == "time_limited"]
    assert free.decision_time.min() > 9 * 0.2 and limited.decision_time.max() < free.decision_time.max()
    from overhang_framework.behaviour.participants import cohort_from_config
    from overhang_framework.errors import ConfigError

    conditions = {"time_limited": {"time_limit": 5.0}, "unconstrained": {}}
    base = {"name": "c", "participants": {"time_limited": 1, "unconstrained": 1},
            "decision_time": {"t0": 1, "per_call": 0.1, "noise": 0.1}, "motor": {"sd": 0, "retries": 0}}
    with pytest.raises(ConfigError, match=r"unknown key 'cohort.by_condition.people'.*keys of cohort.by_condition: "
                                          r"time_limited, unconstrained"):
        cohort_from_config({**base, "by_condition": {"people": {}}}, conditions)
    with pytest.raises(ConfigError, match="cohort.by_condition.unconstrained.parameters.lapse must give a probability"):
        cohort_from_config({**base, "by_condition": {"unconstrained": {"parameters": {
            "lapse": {"dist": "fixed", "value": 2}}}}}, conditions)


def test_a_cohort_can_draw_each_participants_number_of_mental_simulations(tmp_path):
    """``cohort.parameters.K``: each participant's IPE simulates its own K times; participants.csv says which, and
    the other parameters' draws are those of a cohort without it."""
    import pandas as pd

    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    base = ["world.physics=static", "progress=false", "cohort.participants.time_limited=0",
            "cohort.participants.unconstrained=6", "cohort.n_tasks=1"]
    run(compose_config(base + ["+cohort.parameters.K={dist: categorical, values: [1, 50], p: [0.5, 0.5]}"],
                       config_name=CONFIG_NAME), tmp_path / "k")
    run(compose_config(base, config_name=CONFIG_NAME), tmp_path / "plain")
    with_k, plain = pd.read_csv(tmp_path / "k" / "participants.csv"), pd.read_csv(tmp_path / "plain" / "participants.csv")
    assert set(with_k["K"]) == {1, 50} and "K" not in plain.columns
    pd.testing.assert_frame_equal(with_k.drop(columns="K"), plain)


def test_a_drawn_k_must_be_a_whole_number_of_simulations():
    from overhang_framework.behaviour.participants import cohort_from_config
    from overhang_framework.errors import ConfigError

    with pytest.raises(ConfigError, match="K must give a whole number of mental simulations >= 1|whole number of mental"):
        cohort_from_config({"name": "x", "participants": {"unconstrained": 1},
                            "parameters": {"K": {"dist": "uniform", "low": 0.5, "high": 3}}},
                           {"unconstrained": {"time_limit": None}})

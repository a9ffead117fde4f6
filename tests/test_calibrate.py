"""Calibrating a cohort by reweighting a library: closed-form timeouts, importance weights, the fit, the library."""

import json
import math

import numpy as np
import pandas as pd
import pytest

from overhang_framework.behaviour import calibrate
from overhang_framework.behaviour.participants import Distribution

PROPOSAL = {"sigma": Distribution("lognormal", (0.04, 0.8)),
            "depth": Distribution("categorical", ((1, 2, 3), (1 / 3, 1 / 3, 1 / 3))),
            "beta": Distribution("lognormal", (3.0, 1.2)), "lapse": Distribution("uniform", (0.0, 0.3))}


def synthetic_people(dists, n, rng, condition="time_limited"):
    return pd.DataFrame({"participant": [f"{condition}-{i}" for i in range(n)], "condition": condition,
                         **{k: [d.sample(rng) for _ in range(n)] for k, d in dists.items()}})


def synthetic_trials(people, rng, trials=20):
    """A known world: deeper and less lapsing participants stand more and reach further; Γ grows with depth."""
    rows = []
    for p in people.itertuples():
        for t in range(trials):
            stood = rng.random() < min(0.95, 0.45 + 0.15 * p.depth - p.lapse)
            steps = 5 if stood else int(rng.integers(1, 6))
            calls = [int(4 ** p.depth)] * steps
            rows.append({"participant": p.participant, "condition": p.condition, "trial": t + 1,
                         "reward": (1.0 + 0.15 * p.depth + 0.05 * rng.standard_normal()) if stood else 0.0,
                         "stood": stood, "gamma": 0.08 * p.depth if stood else np.nan, "calls": json.dumps(calls),
                         "sigma": p.sigma, "depth": p.depth, "beta": p.beta, "lapse": p.lapse})
    return pd.DataFrame(rows)


@pytest.fixture(scope="module")
def library():
    rng = np.random.default_rng(0)
    trials = synthetic_trials(synthetic_people(PROPOSAL, 900, rng), rng)
    return calibrate.Library(trials, PROPOSAL, "time_limited")


CANDIDATE = calibrate.Candidate((0.2, 0.5, 0.3), sigma=0.03, beta=4.0, lapse=0.05, t0=1.5, per_call=0.06)


def test_timeouts_in_closed_form_equal_those_of_drawn_decision_times(library):
    got = library.predict(CANDIDATE, time_limit=5.0)
    # the same library and weights, with every decision's time drawn and a trial ended at its first timeout
    rng = np.random.default_rng(1)
    reps, n = 400, len(library.people)
    m = CANDIDATE.t0 + CANDIDATE.per_call * library.calls
    present = ~np.isnan(library.calls)
    times = m[None] * np.exp(CANDIDATE.noise * rng.standard_normal((reps,) + m.shape))
    over = (times > 5.0) & present[None]
    first = np.where(over.any(axis=2), over.argmax(axis=2), m.shape[1])
    steps = np.arange(m.shape[1])
    happens = (steps[None, None] <= first[..., None]) & present[None]
    seconds = np.where(happens, np.minimum(times, 5.0), 0.0).sum(axis=2)
    finished = ~over.any(axis=2)

    def per(values):
        return np.bincount(library.who, weights=values.sum(axis=0), minlength=n)

    reward = per(library.reward * finished) / per(np.ones_like(finished, dtype=float))
    stood = per(library.stood * finished)
    time = per(seconds) / per(happens.sum(axis=2).astype(float))
    w = library.weights(CANDIDATE)
    drawn = {"reward_per_trial": np.dot(w, reward) / w.sum(), "decision_time": np.dot(w, time) / w.sum(),
             "stable_pct": 100 * np.dot(w, stood / per(np.ones_like(finished, dtype=float))) / w.sum()}
    assert 0.05 < 1 - got["stable_pct"] / library.predict(CANDIDATE, None)["stable_pct"] < 0.9  # timeouts bite
    for key, value in drawn.items():
        assert got[key] == pytest.approx(value, rel=0.01), key


def test_reweighting_the_library_predicts_a_cohort_simulated_directly(library):
    rng = np.random.default_rng(2)
    direct_people = synthetic_people(CANDIDATE.distributions(), 3000, rng)
    direct = calibrate.Library(synthetic_trials(direct_people, rng), CANDIDATE.distributions(), "time_limited")
    truth = direct.predict(CANDIDATE, None)  # its own proposal: every weight 1
    assert truth["ess"] == pytest.approx(3000)
    got = library.predict(CANDIDATE, None)
    assert 30 < got["ess"] < 900
    for key in ("reward_per_trial", "stable_pct", "avg_overhang", "gamma"):
        assert got[key] == pytest.approx(truth[key], rel=0.04), key


@pytest.mark.slow
def test_the_fit_recovers_a_planted_cohort_and_the_abc_region_holds_it():
    rng = np.random.default_rng(4)
    library = calibrate.Library(synthetic_trials(synthetic_people(PROPOSAL, 400, rng), rng, trials=10), PROPOSAL,
                                "time_limited")
    planted = library.predict(CANDIDATE, 5.0)
    targets = {k: (planted[k], 0.02 * abs(planted[k])) for k in calibrate.METRICS}
    result = calibrate.fit_condition(library, targets, time_limit=5.0, seed=0, maxiter=15, abc_draws=1500)
    assert all(abs(z) <= 1 for z in result["z"].values()), result["z"]
    assert result["candidate"].mean_depth == pytest.approx(CANDIDATE.mean_depth, abs=0.25)
    assert result["candidate"].lapse == pytest.approx(CANDIDATE.lapse, abs=0.04)
    node = result["candidate"].config()
    assert sum(node["parameters"]["depth"]["p"]) == pytest.approx(1.0) and set(node) == {"parameters", "decision_time"}


def test_a_library_with_timeouts_or_without_drawn_parameters_is_refused(library, tmp_path):
    from overhang_framework.errors import ConfigError

    rng = np.random.default_rng(3)
    trials = synthetic_trials(synthetic_people(PROPOSAL, 5, rng), rng).drop(columns=["beta"])
    with pytest.raises(ConfigError, match="do not all draw beta"):
        calibrate.Library(trials, PROPOSAL, "time_limited")
    with pytest.raises(ConfigError, match="no trial of condition 'unconstrained'"):
        calibrate.Library(trials, PROPOSAL, "unconstrained")
    with pytest.raises(ConfigError, match="has no log.jsonl"):
        calibrate.library_trials(tmp_path)


def test_the_library_of_a_participants_run(tmp_path):
    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    cfg = compose_config(["cohort=proposal", "predictor=hybrid", "world.physics=static", "progress=false",
                          "conditions.time_limited.time_limit=null", "cohort.participants.time_limited=3",
                          "cohort.participants.unconstrained=2", "tasks=custom",
                          "tasks.sequences=[[1.2,0.6,1.2,0.6],[0.6,1.2,0.6,0.6]]",
                          "+predictor.early_params.K=10"], config_name=CONFIG_NAME)
    run(cfg, tmp_path / "lib")
    trials = calibrate.library_trials(tmp_path / "lib")
    assert len(trials) == 5 * 2 and set(trials["condition"]) == {"time_limited", "unconstrained"}
    people = pd.read_csv(tmp_path / "lib" / "participants.csv")
    assert sorted(people["id"]) == sorted(trials["participant"].unique())
    assert trials.loc[~trials["stood"], "gamma"].isna().all()
    lengths = [len(json.loads(c)) for c in trials["calls"]]
    assert all(1 <= n <= 3 for n in lengths) and all(n == 3 for n, s in zip(lengths, trials["stood"]) if s)
    assert not math.isnan(calibrate.Library(trials, calibrate.proposal_distributions(), "time_limited")
                          .predict(CANDIDATE, 5.0)["reward_per_trial"])


def test_the_fit_writes_a_cohort_config_that_the_participants_command_accepts(tmp_path):
    import yaml

    from overhang_framework.behaviour.participants import cohort_from_config
    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME

    rng = np.random.default_rng(5)
    trials = pd.concat([synthetic_trials(synthetic_people(PROPOSAL, 60, rng, condition), rng, trials=5)
                        for condition in ("time_limited", "unconstrained")])
    trials.to_csv(tmp_path / "trials.csv", index=False)
    assert calibrate.main(["fit", str(tmp_path / "trials.csv"), "--out", str(tmp_path / "cal"), "--maxiter", "2",
                           "--abc-draws", "50"]) == 0
    summary = json.loads((tmp_path / "cal" / "calibration.json").read_text())
    assert set(summary) == {"time_limited", "unconstrained"}
    assert set(summary["time_limited"]["z"]) == set(calibrate.METRICS)
    node = yaml.safe_load((tmp_path / "cal" / "paper_calibrated.yaml").read_text())
    conditions = compose_config([], config_name=CONFIG_NAME).conditions
    from omegaconf import OmegaConf

    cohort = cohort_from_config(node, OmegaConf.to_container(conditions))
    assert {c.name: c.n for c in cohort.conditions} == {"time_limited": 43, "unconstrained": 38}
    assert cohort.parameters_for("time_limited")["depth"].kind == "categorical"
    assert calibrate.main(["fit", str(tmp_path / "none.csv"), "--out", str(tmp_path / "x")]) == 2


def test_the_shipped_cohort_is_the_shipped_library_fit_and_plans_deeper_without_time_pressure():
    """``cohort=paper_calibrated`` holds the candidates of the shipped calibration; re-predicting them from the
    shipped library gives the distances its header and calibration.json state."""
    from pathlib import Path

    import yaml

    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME

    data = Path(calibrate.__file__).resolve().parents[1] / "data" / "calibration"
    shipped = json.loads((data / "calibration.json").read_text())
    cfg = compose_config(["cohort=paper_calibrated", "predictor=hybrid"], config_name=CONFIG_NAME)
    from omegaconf import OmegaConf

    by_condition = OmegaConf.to_container(cfg.cohort.by_condition)
    assert by_condition == {c: r["candidate"] for c, r in shipped.items()}
    trials = pd.read_csv(data / "library_trials.csv.gz")
    proposal = calibrate.proposal_distributions()
    header = (Path(calibrate.__file__).resolve().parents[1] / "conf" / "cohort" / "paper_calibrated.yaml").read_text()
    depth = {}
    for condition, r in shipped.items():
        node = r["candidate"]
        p = node["parameters"]
        lapse = p["lapse"]["a"] / (p["lapse"]["a"] + p["lapse"]["b"])
        cand = calibrate.Candidate(tuple(p["depth"]["p"]), p["sigma"]["median"], p["beta"]["median"], lapse,
                                   node["decision_time"]["t0"], node["decision_time"]["per_call"])
        got = calibrate.Library(trials, proposal, condition).predict(cand, calibrate.TIME_LIMITS[condition])
        z = calibrate.distances(got, calibrate.TARGETS[condition])
        for k, v in r["z"].items():
            assert z[k] == pytest.approx(v, abs=0.05), (condition, k)  # the config's rounding only
        assert f"#   {condition}: " + ", ".join(f"{k} {r['z'][k]:+.2f}" for k in calibrate.METRICS) in header
        depth[condition] = cand.mean_depth
    assert depth["time_limited"] < depth["unconstrained"]


@pytest.mark.slow
def test_a_small_draw_of_the_calibrated_cohort_under_time_pressure_has_the_papers_reward_and_decision_time(tmp_path):
    """Eight time-limited participants of ``cohort=paper_calibrated`` on ``paper20`` (the default physics), against
    the paper's Table 1 (5 s): reward per trial and decision time near the paper's, and the two measures the
    cohort is documented to miss (docs/fidelity.md) missed in the stated direction.

    Tolerances, measured over seeds 1-5 of this draw: reward per trial 0.78-0.96 (SD 0.07 across draws), so
    within 0.15 (about two SDs) of the paper's 0.913; decision time 2.38-2.40 s, so within 0.15 s of 2.47;
    stable proportion 50-60%, below the paper's 70.2%; average overhang 1.53-1.61, above the paper's 1.321.
    """
    from overhang_framework.behaviour import table1
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    cfg = compose_config(["cohort=paper_calibrated", "predictor=hybrid", "progress=false", "seed=3",
                          "cohort.participants.time_limited=8", "cohort.participants.unconstrained=0"],
                         config_name=CONFIG_NAME)
    run(cfg, tmp_path / "draw")
    df = read_log(tmp_path / "draw" / "log.jsonl")
    df["group"] = df["condition"]
    people = table1.per_participant(df)
    assert len(people) == 8 and set(people["group"]) == {"time_limited"} and (people["trials"] == 20).all()
    paper = {k: v[0] for k, v in table1.PAPER.items()}
    got = people[["reward_per_trial", "stable_pct", "avg_overhang", "decision_time"]].mean()
    assert got["reward_per_trial"] == pytest.approx(paper["reward_per_trial"], abs=0.15)
    assert got["decision_time"] == pytest.approx(paper["decision_time"], abs=0.15)
    assert got["stable_pct"] < paper["stable_pct"]
    assert got["avg_overhang"] > paper["avg_overhang"] + 4 * table1.PAPER["avg_overhang"][1]


def test_a_library_that_draws_the_new_axes_fits_them_and_writes_them_into_the_cohort(tmp_path):
    """A known world in which risk aversion lowers the reach of standing towers and raises how many stand: a
    library drawn over the whole range of risk predicts a risk-averse cohort on an effective sample of 30 or
    more, its loss singles out the true mean risk, and the cohort config it writes draws risk, percept and hand."""
    import yaml

    from overhang_framework.behaviour.participants import cohort_from_config

    proposal = {**PROPOSAL, "risk": Distribution("uniform", (0.0, 0.95)),
                "percept": Distribution("lognormal", (0.02, 1.0)), "hand": Distribution("lognormal", (0.03, 1.0))}
    rng = np.random.default_rng(3)

    def trials_of(people):
        rows = []
        for p in people.itertuples():
            for t in range(20):
                stood = rng.random() < min(0.97, 0.45 + 0.1 * p.depth - p.lapse + 0.4 * p.risk - 2 * p.percept)
                rows.append({"participant": p.participant, "condition": p.condition, "trial": t + 1,
                             "reward": (1.7 - 0.6 * p.risk + 0.05 * rng.standard_normal()) if stood else 0.0,
                             "stood": stood, "gamma": 0.3 - 0.2 * p.risk if stood else np.nan,
                             "calls": json.dumps([4] * 5), **{k: getattr(p, k) for k in proposal}})
        return pd.DataFrame(rows)

    library = calibrate.Library(trials_of(synthetic_people(proposal, 1500, rng)), proposal, "time_limited")
    assert library.axes == ("risk", "percept", "hand") and len(library.free) == len(calibrate.FREE) + 3
    truth = [0.0, 0.0, math.log(0.03), math.log(4.0), calibrate.logit(0.08), 2.2, 0.01,
             calibrate.logit(0.7), math.log(0.01), math.log(0.03)]
    candidate = library.candidate(truth)
    assert dict(candidate.axes) == pytest.approx({"risk": 0.7, "percept": 0.01, "hand": 0.03})
    predicted = library.predict(candidate, 5.0)
    assert predicted["ess"] >= 30
    targets = {k: (v, 0.02 * abs(v) + 1e-3) for k, v in predicted.items() if k != "ess"}
    # the truth scores best along the risk axis: its loss is 0, a cohort of other mean risk is far off
    losses = {r: calibrate.loss(truth[:7] + [calibrate.logit(r)] + truth[8:], library, targets, 5.0)
              for r in (0.2, 0.45, 0.7, 0.85)}
    assert losses[0.7] < 1 and min(losses[0.2], losses[0.45], losses[0.85]) > 10 * max(losses[0.7], 0.1), losses
    node = candidate.config()
    assert set(node["parameters"]) == {"depth", "sigma", "beta", "lapse", "risk", "percept", "hand"}
    cohort = cohort_from_config({"name": "x", "participants": {"time_limited": 2},
                                 "decision_time": {"t0": 2.0, "per_call": 0.07, "noise": 0.3},
                                 "motor": {"sd": 0.02, "retries": 5},
                                 "by_condition": {"time_limited": node}}, {"time_limited": {"time_limit": 5.0}})
    assert cohort.parameters_for("time_limited")["risk"].kind == "beta"
    with pytest.raises(Exception, match="must give its distribution"):
        library.weights(CANDIDATE)


def test_measure_takes_a_run_a_running_run_and_several_runs_and_gives_each_distance_in_the_papers_sems(tmp_path, capsys):
    """``calibrate measure``: one run's ten measures; the same from the participants a run has finished
    (``parts/``); one run a condition gives the one run's numbers; a run given twice (seeds) is a mean of two
    runs with each run's distance; Γ under the world the run simulated; a directory without a run refused."""
    from overhang_framework.behaviour import read_log, table1
    from overhang_framework.behaviour.log import write_log
    from overhang_framework.config import compose_config
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    cfg = compose_config(["cohort=proposal", "predictor=hybrid", "world.physics=static", "progress=false",
                          "cohort.participants.time_limited=3", "cohort.participants.unconstrained=2", "tasks=custom",
                          "tasks.sequences=[[1.2,0.6,1.2,0.6],[0.6,1.2,0.6,0.6]]", "+predictor.early_params.K=10"],
                         config_name=CONFIG_NAME)
    run(cfg, tmp_path / "both")
    assert calibrate.run_world(tmp_path / "both").physics_name == "static"
    df = read_log(tmp_path / "both" / "log.jsonl")

    def table(*dirs) -> list[list[str]]:
        assert calibrate.main(["measure", *map(str, dirs)]) == 0
        lines = capsys.readouterr().out.strip().splitlines()[2:]
        return [[c.strip() for c in line.strip("|").split("|")] for line in lines]

    whole = table(tmp_path / "both")
    assert [r[:2] for r in whole] == [[c, m] for c in ("time_limited", "unconstrained") for m in calibrate.METRICS]
    people = table1.per_participant(df.assign(group=df["condition"])).set_index("participant")
    tl = people[people.index.str.startswith("sim-tl")]["avg_overhang"]
    row = whole[2]
    assert row[2] == f"{tl.mean():.3f} ± {tl.std(ddof=1) / math.sqrt(3):.3f}"
    assert float(row[4]) == pytest.approx((tl.mean() - 1.321) / 0.023, abs=0.006)

    # a run still going: its finished participants, one file each, in any order
    (tmp_path / "running" / "parts").mkdir(parents=True)
    for i, (who, records) in enumerate(reversed(list(df.groupby("participant")))):
        write_log(records, tmp_path / "running" / "parts" / f"{who}.jsonl")
    (tmp_path / "running" / "parts" / "sim-un-009.jsonl").write_text('{"half a rec')  # being written: skipped
    assert table(tmp_path / "running") == whole
    # one run a condition
    for condition in ("time_limited", "unconstrained"):
        (tmp_path / condition).mkdir()
        write_log(df[df["condition"] == condition], tmp_path / condition / "log.jsonl")
    assert table(tmp_path / "time_limited", tmp_path / "unconstrained") == whole
    # seeds: the mean of the runs, and each run's distance
    twice = table(tmp_path / "both", tmp_path / "running")
    assert [r[4] for r in twice] == [r[4] for r in whole]
    assert twice[2][2] == f"{tl.mean():.3f} (mean of 2 runs)" and twice[2][5] == f"{row[4]}, {row[4]}"
    # nothing to measure
    (tmp_path / "empty").mkdir()
    assert calibrate.main(["measure", str(tmp_path / "empty")]) == 2
    assert "no log.jsonl and no finished participants" in capsys.readouterr().err
    # the per-participant measures, saved small, measure as the run did; rows in any order
    saved = tmp_path / "kept" / "both.csv"
    assert calibrate.main(["measure", str(tmp_path / "both"), "--save", str(saved)]) == 0
    capsys.readouterr()
    kept = pd.read_csv(saved)
    assert list(kept.columns) == list(calibrate.PEOPLE_COLUMNS) and len(kept) == 5
    kept.iloc[::-1].to_csv(tmp_path / "reversed.csv", index=False)
    assert table(saved) == whole and table(tmp_path / "reversed.csv") == whole
    assert table(saved, tmp_path / "running") == twice
    # refused in one line: --save of several runs, a CSV of something else, a participant twice
    assert calibrate.main(["measure", str(tmp_path / "both"), str(saved), "--save", str(tmp_path / "x.csv")]) == 2
    assert "--save writes one run's participants; 2 runs were given" in capsys.readouterr().err
    (tmp_path / "other.csv").write_text("a,b\n1,2\n")
    assert calibrate.main(["measure", str(tmp_path / "other.csv")]) == 2
    assert "lacks participant, condition" in capsys.readouterr().err
    pd.concat([kept, kept.iloc[:1]]).to_csv(tmp_path / "twice.csv", index=False)
    assert calibrate.main(["measure", str(tmp_path / "twice.csv")]) == 2
    assert "is listed twice" in capsys.readouterr().err
    for name, frame, words in (("header.csv", kept.iloc[:0], "no participants"),
                               ("blank.csv", kept.assign(condition=[None] + list(kept["condition"][1:])),
                                "line 2 has no participant or no condition"),
                               ("word.csv", kept.astype({"gamma": object}).assign(gamma=["high"] + list(kept["gamma"][1:])),
                                "gamma on line 2 is 'high', not a number")):
        frame.to_csv(tmp_path / name, index=False)
        assert calibrate.main(["measure", str(tmp_path / name)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and words in err, err
    assert calibrate.main(["measure", str(saved), "--world", "world.physics=static"]) == 2
    assert "keeps Γ already computed" in capsys.readouterr().err


@pytest.mark.parametrize("column, value, words", [
    ("stable_pct", 7000.0, "stable_pct on line 3 is 7000, which no participant can have: it is from 0 to 100"),
    ("avg_overhang", -0.5, "avg_overhang on line 3 is -0.5, which no participant can have: it is from 0 to 4"),
    ("gamma", 5.0, "gamma on line 3 is 5, which no participant can have: it is from 0 to 1"),
    ("decision_time", -1.0, "decision_time on line 3 is -1, which no participant can have: it is at least 0"),
    ("reward_per_trial", 9.0, "reward_per_trial on line 3 is 9, which no participant can have"),
])
def test_measure_refuses_a_table_with_a_value_no_participant_can_have(tmp_path, capsys, column, value, words):
    rows = pd.DataFrame([{"participant": f"p{i}", "condition": c, "reward_per_trial": 1.1, "stable_pct": 70.0,
                          "avg_overhang": 1.3, "decision_time": 3.0, "gamma": 0.2}
                         for i, c in enumerate(["time_limited", "unconstrained"] * 2)])
    rows.to_csv(tmp_path / "fine.csv", index=False)
    assert calibrate.main(["measure", str(tmp_path / "fine.csv")]) == 0
    capsys.readouterr()
    rows.loc[1, column] = value
    rows.to_csv(tmp_path / "bad.csv", index=False)
    assert calibrate.main(["measure", str(tmp_path / "bad.csv")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err, err

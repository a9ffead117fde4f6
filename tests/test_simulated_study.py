"""A simulated study with a built-in difference between conditions, analysed end to end.

Every participant has search depth 2; under ``time_limited`` a budget of one
predictor call per placement truncates the search to depth 1 (myopic), under
``unconstrained`` it runs to depth 2. The analyses must show what that does, in
the direction the model implies:

* Table 1: longer decisions (more predictor calls) and a larger overhang of
  successful trials when the search is deeper;
* Γ: deeper search builds towers that depend more on their order (counterweights
  placed before the cantilevers they hold);
* Fig. 4: a depth-1 agent scores an action by its immediate overhang times its
  chance of standing, so it takes more physical risks than one that also values
  what the tower allows next; the unconstrained group's executed placements are
  therefore more plausible (a higher mean log-likelihood) under the agents' own
  predictor, the IPE, and under the veridical physics.
"""

import pandas as pd
import pytest

from overhang_framework.config import compose_config

STUDY = ["world.physics=static", "predictor.K=10", "progress=false", "jobs=2", "seed=0",
         "cohort.participants.time_limited=8", "cohort.participants.unconstrained=8", "cohort.n_tasks=6",
         "~cohort.parameters.depth", "+cohort.parameters.depth={dist: fixed, value: 2}",
         "conditions.time_limited.call_limit=1"]


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    from overhang_framework.analyze import main
    from overhang_framework.behaviour.simulation import CONFIG_NAME, run

    root = tmp_path_factory.mktemp("study")
    run(compose_config(STUDY, config_name=CONFIG_NAME), root / "sim")
    status = main([str(root / "sim" / "log.jsonl"), "--out", str(root / "analysis"), "--world", "world.physics=static",
                   "--predictors", "veridical,ipe", "--n-resamples", "2000", "--bootstrap", "200", "--quiet"])
    assert status in (0, None)
    return root / "analysis"


def test_table1_shows_longer_decisions_and_larger_overhangs_unconstrained(study):
    table = pd.read_csv(study / "table1.csv").set_index(["metric", "group"])
    mean = table["mean"]
    assert mean["decision_time", "unconstrained"] > mean["decision_time", "time_limited"] + 0.5
    assert mean["avg_overhang", "unconstrained"] > mean["avg_overhang", "time_limited"]
    assert table.loc[("decision_time", "unconstrained"), "p"] < 0.01
    assert (table["n_resamples"] == 2000).all()


def test_gamma_is_higher_for_the_deeper_search(study):
    g = pd.read_csv(study / "gamma_participants.csv").groupby("group")["gamma"].mean()
    assert g["unconstrained"] > g["time_limited"]


def test_fig4_executed_placements_are_safer_for_the_deeper_search(study):
    per = pd.read_csv(study / "fig4_placements.csv").groupby("group").mean(numeric_only=True)
    assert per.loc["unconstrained", "ll_ipe"] > per.loc["time_limited", "ll_ipe"]
    assert per.loc["unconstrained", "ll_veridical"] > per.loc["time_limited", "ll_veridical"]
    stage = pd.read_csv(study / "fig4_loglik.csv")
    assert set(stage["group"]) == {"time_limited", "unconstrained"}
    assert (study / "fig4_loglik.png").stat().st_size > 10_000

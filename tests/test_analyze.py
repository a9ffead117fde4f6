"""The behaviour analyses (python -m overhang_framework.analyze) on logs whose answers are known."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.stats import permutation_test

from overhang_framework.analyze import main
from overhang_framework.behaviour import analysis, flows, gamma, prediction, table1
from overhang_framework.behaviour.log import read_log, write_log
from overhang_framework.geometry import Geometry, overhang

STATIC = ["world.physics=static"]
ROOT = Path(__file__).resolve().parents[1]


def trial(participant, condition, task_id, sequence, number, placements, stable=None, times=None,
          timeout=False, source="human"):
    """The records of one trial placing ``placements`` ([x, layer] each); ``stable`` flags per placement
    (default all True); ``timeout`` adds a timed-out record after them."""
    stable = stable or [True] * len(placements)
    times = times or [1.0] * (len(placements) + timeout)
    tower = [[sequence[0], 0.0, 0]]
    records = []
    for k, (x, layer) in enumerate(placements, 1):
        after = tower + [[sequence[k], x, layer]]
        ends = not stable[k - 1] or (k == len(sequence) - 1 and not timeout)
        height = overhang(Geometry.from_tuples(after))
        records.append({"log_version": 1, "participant": participant, "condition": condition, "task_id": task_id,
                        "sequence": list(sequence), "trial": number, "step": k, "width": sequence[k], "x": x,
                        "layer": layer, "tower_before": [list(b) for b in tower], "stable": stable[k - 1],
                        "overhang": height, "reward": (height if all(stable[:k]) else 0.0) if ends else None,
                        "decision_time": times[k - 1], "timed_out": False, "source": source})
        tower = after
    if timeout:
        k = len(placements) + 1
        records.append({"log_version": 1, "participant": participant, "condition": condition, "task_id": task_id,
                        "sequence": list(sequence), "trial": number, "step": k, "width": sequence[k], "x": None,
                        "layer": None, "tower_before": [list(b) for b in tower], "stable": None, "overhang": None,
                        "reward": 0.0, "decision_time": times[-1], "timed_out": True, "source": source})
    return records


BRIDGE = [1.8, 0.6, 0.6, 1.8]          # docs/order_dependency.md: 4 valid orders, 2 stable (static)
BRIDGE_STEPS = [[-0.6, 1], [0.6, 1], [0.0, 2]]
STACK = [1.2, 1.2, 1.2]
STACK_STEPS = [[0.0, 1], [0.0, 2]]


def people_log(tmp_path: Path) -> Path:
    """Two time-limited and two unconstrained people; known rewards, times and towers."""
    records = []
    records += trial("t1", "time_limited", "custom01", BRIDGE, 1, BRIDGE_STEPS, times=[1, 2, 3])
    records += trial("t1", "time_limited", "custom00", STACK, 2, STACK_STEPS, times=[2, 2])
    records += trial("t2", "time_limited", "custom01", BRIDGE, 1, [[0.0, 1]], times=[1, 5], timeout=True)
    records += trial("t2", "time_limited", "custom00", STACK, 2, [[0.0, 1], [0.9, 2]], stable=[True, False],
                     times=[3, 3])
    records += trial("u1", "unconstrained", "custom01", BRIDGE, 1, BRIDGE_STEPS, times=[6, 6, 6])
    records += trial("u1", "unconstrained", "custom00", STACK, 2, [[0.3, 1], [0.6, 2]], times=[9, 9])
    records += trial("u1", "unconstrained", "custom02", [1.2, 0.6, 0.6], 3, [[0.8, 1]], stable=[False], times=[6])
    records += trial("u2", "unconstrained", "custom00", STACK, 1, STACK_STEPS, times=[4, 8])
    path = tmp_path / "people.jsonl"
    write_log(records, path)
    return path


def test_permutation_p_is_scipys_and_table1_reports_it():
    a, b = [1.0, 2.5, 3.1, 4.2, 2.2], [3.3, 4.8, 5.1, 4.4]
    ref = permutation_test((a, b), lambda x, y, axis: np.mean(x, axis=axis) - np.mean(y, axis=axis),
                           permutation_type="independent", vectorized=True, n_resamples=999,
                           alternative="two-sided", random_state=7).pvalue
    assert analysis.permutation_p(a, b, 999, 7) == pytest.approx(ref, abs=0)
    people = pd.DataFrame({"group": ["A"] * 5 + ["B"] * 4, "participant": list("abcdefghi"),
                           "total_reward": a + b, "stable_pct": a + b, "avg_overhang": a + b, "decision_time": a + b})
    tab = table1.table(people, ["A", "B"], ("A", "B"), 999, 7)
    assert set(tab.loc[tab.group == "A", "p"]) == {ref}
    assert set(tab["n_resamples"]) == {999}


def test_table1_on_a_hand_built_log(tmp_path):
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    people = table1.per_participant(df).set_index("participant")
    bridge, stack = overhang(Geometry.from_tuples([[1.8, 0, 0], [0.6, -0.6, 1], [0.6, 0.6, 1], [1.8, 0, 2]])), 0.6
    assert people.loc["t1", "total_reward"] == pytest.approx(bridge + stack)
    assert people.loc["t2", "total_reward"] == 0
    assert people.loc["t1", "stable_pct"] == 100 and people.loc["t2", "stable_pct"] == 0
    assert people.loc["u1", "avg_overhang"] == pytest.approx((bridge + 0.6 + 0.6) / 2)
    assert math.isnan(people.loc["t2", "avg_overhang"])
    assert people.loc["t1", "decision_time"] == pytest.approx(2.0)   # (1 + 2 + 3 + 2 + 2) / 5
    assert people.loc["t2", "decision_time"] == pytest.approx(3.0)   # the timeout's 5 s included
    tab = table1.table(table1.per_participant(df), ["time_limited", "unconstrained"],
                       ("time_limited", "unconstrained"), 100, 0)
    row = tab[(tab.metric == "total_reward") & (tab.group == "time_limited")].iloc[0]
    assert row["mean"] == pytest.approx((bridge + stack) / 2)
    assert row["sem"] == pytest.approx(np.std([bridge + stack, 0], ddof=1) / math.sqrt(2))
    assert row["n"] == 2


def test_gamma_per_participant_matches_order_counts(tmp_path):
    from overhang_framework.behaviour.order_dependency import order_counts

    world = analysis.build_world(STATIC)
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    towers = gamma.tower_gammas(df, world)
    # t2 placed every block in one trial, toppling the tower with the last (Γ = 1); u2 one; t1 and u1 two each
    assert sorted(towers["participant"]) == ["t1", "t1", "t2", "u1", "u1", "u2"]
    bridge = order_counts(Geometry.from_tuples([[1.8, 0, 0], [0.6, -0.6, 1], [0.6, 0.6, 1], [1.8, 0, 2]]), world)
    stack = order_counts(Geometry.from_tuples([[1.2, 0, 0], [1.2, 0, 1], [1.2, 0, 2]]), world)
    offset = order_counts(Geometry.from_tuples([[1.2, 0, 0], [1.2, 0.3, 1], [1.2, 0.6, 2]]), world)
    assert bridge.gamma == 0.5
    people = gamma.per_participant(towers).set_index("participant")["gamma"]
    assert people["t1"] == pytest.approx((bridge.gamma + stack.gamma) / 2)
    assert people["u1"] == pytest.approx((bridge.gamma + offset.gamma) / 2)
    assert people["u2"] == pytest.approx(stack.gamma)
    assert people["t2"] == 1.0


def test_fig4_veridical_loglikelihood_is_log_eps_or_log_one_minus_eps(tmp_path):
    records = trial("p", "unconstrained", "ok", [1.2, 0.6, 0.6], 1, [[0.0, 1], [0.0, 2]])
    records += trial("p", "unconstrained", "falls", [1.2, 0.6], 2, [[0.9, 1]], stable=[False])
    write_log(records, tmp_path / "log.jsonl")
    out = tmp_path / "out"
    settings = analysis.Settings(world_overrides=STATIC, predictors=["veridical"], only=["prediction"], bootstrap=50)
    analysis.run([tmp_path / "log.jsonl"], out, settings)
    rows = pd.read_csv(out / "fig4_placements.csv").sort_values(["trial", "step"])
    eps = settings.epsilon
    assert list(rows["p_veridical"]) == [1.0, 1.0, 0.0]
    np.testing.assert_allclose(rows["ll_veridical"], [math.log(1 - eps)] * 2 + [math.log(eps)])
    stage = pd.read_csv(out / "fig4_loglik.csv")
    two = stage[(stage.n_blocks == 2) & (stage.measure == "veridical")].iloc[0]
    assert two["mean"] == pytest.approx((math.log(1 - eps) + math.log(eps)) / 2)


def test_bootstrap_ci_covers_the_mean_and_is_seeded():
    rng = np.random.default_rng(1)
    counts = rng.integers(1, 6, 30)
    sums = np.array([rng.normal(2.0, 1.0, c).sum() for c in counts])
    lo, hi = analysis.bootstrap_ci(sums, counts, 500, 3)
    assert lo < sums.sum() / counts.sum() < hi
    assert (lo, hi) == analysis.bootstrap_ci(sums, counts, 500, 3)
    assert hi - lo < 1.5


def test_state_rngs_do_not_depend_on_the_rest_of_the_log():
    key = (((1.2, 0.0, 0),), (0.6,))
    assert prediction.state_seed(0, key) == prediction.state_seed(0, key) != prediction.state_seed(1, key)


def test_partial_logs_are_reported_and_the_command_writes_its_files(tmp_path, capsys):
    out = tmp_path / "out"
    status = main([str(people_log(tmp_path)), "--out", str(out), "--world", "world.physics=static",
                   "--predictors", "veridical", "--n-resamples", "200", "--bootstrap", "50", "--quiet"])
    assert status == 0
    report = (out / "report.md").read_text()
    assert "3 of 4 participants did fewer trials than the 3 tasks in the log (fewest: 1)" in report
    assert "2 of 8 trials ended before their last block (1 on a timeout, 1 on a collapse)" in report
    assert "1 trial placed every block but the last placement toppled the tower" in report
    assert "no mouse trajectories" in report
    assert "Timed-out records skipped: 1" in report
    assert "200 resamples" in report
    for name in ["table1.csv", "gamma.csv", "gamma_participants.csv", "fig3a_flows.csv", "fig4_loglik.csv",
                 "fig3a_flows.png", "fig3b_gamma.png", "fig4_loglik.png"]:
        assert (out / name).stat().st_size > 0, name
    assert (out / "fig4_loglik.png").read_bytes()[:4] == b"\x89PNG"
    tab = pd.read_csv(out / "table1.csv")
    assert set(tab["group"]) == {"time_limited", "unconstrained"}
    # the report embeds its figures, and summary.json holds its headline figures
    assert "![fig4_loglik.png](fig4_loglik.png)" in report and "![fig3b_gamma.png](fig3b_gamma.png)" in report
    summary = json.loads((out / "summary.json").read_text())
    row = tab[(tab["metric"] == "decision_time") & (tab["group"] == "unconstrained")].iloc[0]
    assert summary["table1"]["decision_time"]["unconstrained"]["mean"] == pytest.approx(row["mean"])
    assert summary["table1"]["decision_time"]["p"] == pytest.approx(row["p"])
    per = pd.read_csv(out / "fig4_placements.csv")
    assert summary["fig4"]["time_limited"]["veridical"] == pytest.approx(
        per[per["group"] == "time_limited"]["ll_veridical"].mean())
    assert set(summary["seconds"]) == {"table1", "gamma", "flows", "prediction", "total"}
    assert not list(out.glob(".*"))          # no temporary files left behind
    assert "wrote" in capsys.readouterr().out


def test_unreadable_log_is_one_line(tmp_path, capsys):
    bad = tmp_path / "bad.jsonl"
    bad.write_text("{not json\n")
    assert main([str(bad), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "line 1" in err and "\n" not in err
    assert main([str(tmp_path / "missing.jsonl"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert main([str(people_log(tmp_path)), "--out", str(tmp_path / "o"), "--predictors", "vertical",
                 "--world", "world.physics=static", "--only", "prediction", "--quiet"]) == 2
    assert "unknown predictor 'vertical'" in capsys.readouterr().err


def test_models_and_people_side_by_side(tmp_path):
    run = tmp_path / "run"
    subprocess.run([sys.executable, "-m", "overhang_framework", "tasks=custom",
                    "tasks.sequences=[[1.2,1.2,1.2],[1.8,0.6,0.6,1.8]]", "world.physics=static", "progress=false",
                    "repeats=2", f"hydra.run.dir={run}"], check=True, cwd=tmp_path, capture_output=True)
    subprocess.run([sys.executable, "-m", "overhang_framework.behaviour.convert", str(run), "--out",
                    str(tmp_path / "model.jsonl")], check=True, cwd=tmp_path, capture_output=True)
    out = tmp_path / "out"
    assert main([str(people_log(tmp_path)), str(tmp_path / "model.jsonl"), "--out", str(out), "--world",
                 "world.physics=static", "--predictors", "veridical", "--n-resamples", "100", "--bootstrap", "20",
                 "--quiet"]) == 0
    groups = {"time_limited", "unconstrained", "veridical-myopic"}
    assert set(pd.read_csv(out / "table1.csv")["group"]) == groups
    assert set(pd.read_csv(out / "gamma_participants.csv")["group"]) == groups
    assert set(pd.read_csv(out / "fig4_loglik.csv")["group"]) == groups
    assert set(pd.read_csv(out / "fig3a_flows.csv")["group"]) == groups   # custom00: people and model
    assert set(pd.read_csv(out / "table1_participants.csv").query("group == 'veridical-myopic'")["participant"]) \
        == {"veridical-myopic/0", "veridical-myopic/1"}
    report = (out / "report.md").read_text()
    assert "| veridical-myopic | 2 | 4 |" in report


def test_flow_transitions_count_trials_and_falls(tmp_path):
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    edges = flows.transitions(df, "custom00", 0.1)
    tl = edges[edges.group == "time_limited"].set_index(["step", "from_x", "from_layer", "to_x", "to_layer"])
    assert tl.loc[(1, 0.0, 0, 0.0, 1), "count"] == 2 and tl.loc[(1, 0.0, 0, 0.0, 1), "probability"] == 1
    assert tl.loc[(2, 0.0, 1, 0.0, 2), "probability"] == 0.5
    fell = tl.loc[(2, 0.0, 1, 0.9, 2)]
    assert fell["count"] == 1 and fell["fell"] == 1 and fell["probability"] == 0.5
    assert flows.choose_task(df) == "custom00"            # played in 4 trials, custom01 in 3


def test_flow_task_defaults_to_the_paper_example_and_finds_its_optimum():
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    df = pd.DataFrame({"task_id": ["a", "b", "b"], "participant": ["p", "p", "q"], "trial": [1, 2, 1],
                       "sequence": [[0.6, 1.8, 1.2, 1.8, 0.6, 1.8], [1.2, 0.6], [1.2, 0.6]]})
    assert flows.choose_task(df) == "a"
    assert flows.choose_task(df, "b") == "b"
    task = tasks_from_config(compose_config(["tasks=paper20"]).tasks)[0]
    static = flows.optimal_path(task.sequence, task.id, analysis.build_world(STATIC))
    assert static is not None and static["same_physics"] and len(static["actions"]) == len(task.sequence) - 1


def test_fig4_asks_each_distinct_state_once():
    class Counting:
        def __init__(self):
            self.requests = []

        def predict_many(self, requests, rngs):
            self.requests.extend(requests)
            return [np.full(len(actions), 0.5) for _, actions in requests]

    rows = []
    for participant, x in (("a", 0.1), ("b", 0.2)):     # same first state and action, then two actions
        rows += trial(participant, "c", "t", [1.2, 0.6, 0.6], 1, [[0.0, 1], [x, 2]])
    df = analysis.with_groups(pd.DataFrame(rows))
    done = prediction.placements(df)
    counting = Counting()
    p = prediction.probabilities(done, {"x": counting}, 0)["x"]
    assert len(p) == 4 and len(counting.requests) == 2            # the ground block alone, the block on it
    assert [len(actions) for _, actions in counting.requests] == [1, 2]

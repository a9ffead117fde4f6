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
from overhang_framework.errors import OverhangError
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
                           "total_reward": a + b, "reward_per_trial": a + b, "stable_pct": a + b, "avg_overhang": a + b,
                           "decision_time": a + b})
    tab = table1.table(people, ["A", "B"], ("A", "B"), 999, 7)
    assert set(tab.loc[tab.group == "A", "p"]) == {ref}
    assert set(tab["n_resamples"]) == {999}


def test_table1_on_a_hand_built_log(tmp_path):
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    people = table1.per_participant(df).set_index("participant")
    bridge, stack = overhang(Geometry.from_tuples([[1.8, 0, 0], [0.6, -0.6, 1], [0.6, 0.6, 1], [1.8, 0, 2]])), 0.6
    assert people.loc["t1", "total_reward"] == pytest.approx(bridge + stack)
    assert people.loc["t2", "total_reward"] == 0
    # per trial: the total over the trials each did (t1 2, u1 3: one collapsed, reward 0)
    assert people.loc["t1", "reward_per_trial"] == pytest.approx((bridge + stack) / 2)
    assert people.loc["u1", "reward_per_trial"] == pytest.approx((bridge + 1.2) / 3)
    assert list(people["trials"]) == [2, 2, 3, 1]
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
    # completed towers only: t2 toppled one tower with its last block and timed out in the other, so none
    assert sorted(towers["participant"]) == ["t1", "t1", "u1", "u1", "u2"]
    assert towers["completed"].all()
    bridge = order_counts(Geometry.from_tuples([[1.8, 0, 0], [0.6, -0.6, 1], [0.6, 0.6, 1], [1.8, 0, 2]]), world)
    stack = order_counts(Geometry.from_tuples([[1.2, 0, 0], [1.2, 0, 1], [1.2, 0, 2]]), world)
    offset = order_counts(Geometry.from_tuples([[1.2, 0, 0], [1.2, 0.3, 1], [1.2, 0.6, 2]]), world)
    assert bridge.gamma == 0.5
    people = gamma.per_participant(towers).set_index("participant")["gamma"]
    assert people["t1"] == pytest.approx((bridge.gamma + stack.gamma) / 2)
    assert people["u1"] == pytest.approx((bridge.gamma + offset.gamma) / 2)
    assert people["u2"] == pytest.approx(stack.gamma)
    assert "t2" not in people


def test_gamma_of_every_final_tower_counts_collapses_and_timeouts(tmp_path):
    from overhang_framework.behaviour.order_dependency import order_counts

    world = analysis.build_world(STATIC)
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    towers = gamma.tower_gammas(df, world, towers="final")
    assert len(towers) == 8 and sorted(towers["participant"]) == ["t1", "t1", "t2", "t2", "u1", "u1", "u1", "u2"]
    ended = towers.set_index(["participant", "task_id"])["ended"]
    assert ended["t2", "custom01"] == "timeout" and ended["t2", "custom00"] == "collapse"
    assert ended["u1", "custom02"] == "collapse" and (ended.drop([("t2", "custom01"), ("t2", "custom00"),
                                                                   ("u1", "custom02")]) == "completed").all()
    # the timeout leaves the tower it had (ground block and one block); a tower that fell has no stable order
    kept = order_counts(Geometry.from_tuples([[1.8, 0, 0], [0.6, 0.0, 1]]), world)
    toppled = order_counts(Geometry.from_tuples([[1.2, 0, 0], [1.2, 0, 1], [1.2, 0.9, 2]]), world)
    fell = order_counts(Geometry.from_tuples([[1.2, 0, 0], [0.6, 0.8, 1]]), world)
    assert kept.gamma == 0 and toppled.gamma == 1 and fell.gamma == 1
    people = gamma.per_participant(towers).set_index("participant")["gamma"]
    assert people["t2"] == pytest.approx((kept.gamma + toppled.gamma) / 2)
    completed = gamma.per_participant(gamma.tower_gammas(df, world)).set_index("participant")["gamma"]
    assert people["u1"] == pytest.approx((2 * completed["u1"] + fell.gamma) / 3)
    assert people["t1"] == completed["t1"] and people["u2"] == completed["u2"]
    with pytest.raises(OverhangError, match=r"towers: unknown reading 'all'; readings: completed, final"):
        gamma.final_towers(df, "all")


def test_the_report_counts_the_chosen_towers_and_gives_the_other_reading(tmp_path, capsys):
    log = people_log(tmp_path)
    args = ["--world", "world.physics=static", "--only", "gamma", "--n-resamples", "100", "--quiet"]
    assert main([str(log), "--out", str(tmp_path / "completed"), *args]) == 0
    assert main([str(log), "--out", str(tmp_path / "final"), *args, "--gamma-towers", "final"]) == 0
    done, final = (json.loads((tmp_path / d / "summary.json").read_text())["gamma"] for d in ("completed", "final"))
    assert done["reading"] == "completed" and final["reading"] == "final"
    assert done["time_limited"]["towers"] == 2 and final["time_limited"]["towers"] == 4
    assert done["unconstrained"]["towers"] == 3 and final["unconstrained"]["towers"] == 4
    # both runs compute both readings; each reports its own first
    assert done["readings"] == final["readings"]
    assert final["time_limited"] == final["readings"]["final"]["time_limited"]
    people = pd.read_csv(tmp_path / "final" / "gamma_participants.csv")
    assert set(people["participant"]) == {"t1", "t2", "u1", "u2"}
    assert set(pd.read_csv(tmp_path / "completed" / "gamma_participants.csv")["participant"]) == {"t1", "u1", "u2"}
    report = (tmp_path / "completed" / "report.md").read_text()
    assert "Γ counts completed towers only" in report
    assert "not a completed tower, so not in Γ (`--gamma-towers final` counts it)" in report
    assert "| `final` | time_limited | 2 | 4 of 4 (1 with no stable order here) |" in report
    assert main([str(log), "--out", str(tmp_path / "o"), "--gamma-towers", "all", "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == ("error: --gamma-towers: unknown reading 'all'; "
                                               "readings: completed, final")


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


def test_empty_log_is_one_line_and_writes_nothing(tmp_path, capsys):
    empty = tmp_path / "empty.jsonl"
    empty.write_text("")
    out = tmp_path / "o"
    assert main([str(empty), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {empty}: no records") and err.count("\n") == 1
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["empty.jsonl"]


def test_unwritable_out_is_one_line(tmp_path, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main([str(people_log(tmp_path)), "--out", str(blocker / "o"), "--only", "table1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: cannot write the output directory '{blocker / 'o'}'") and err.count("\n") == 1
    assert "choose another with --out DIR" in err


def test_an_analysis_that_fails_leaves_no_files_of_the_others(tmp_path, capsys, monkeypatch):
    def fails(*args, **kwargs):
        raise OverhangError("gamma refuses")

    monkeypatch.setattr(gamma, "section", fails)
    out = tmp_path / "o"
    out.mkdir()
    (out / "kept.txt").write_text("from before")
    assert main([str(people_log(tmp_path)), "--out", str(out), "--world", "world.physics=static",
                 "--only", "table1,gamma", "--n-resamples", "100", "--quiet"]) == 2
    assert "gamma refuses" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == ["kept.txt"]       # table1's CSVs were not left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o", "people.jsonl"]
    assert main([str(tmp_path / "people.jsonl"), "--out", str(out), "--only", "table1", "--n-resamples", "100",
                 "--quiet"]) == 0
    assert {"kept.txt", "table1.csv", "report.md"} <= {p.name for p in out.iterdir()}


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


def test_lateral_extent_by_hand_and_in_any_row_order(tmp_path):
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    people = flows.lateral(df).set_index("participant")
    # u1: (-0.6, 0.6, 0.0) on custom01, (0.3, 0.6) on custom00, 0.8 on custom02; step 3 only on custom01
    assert people.loc["u1", "placements"] == 6
    assert people.loc["u1", "abs_x"] == pytest.approx((0.6 + 0.6 + 0.0 + 0.3 + 0.6 + 0.8) / 6)
    assert people.loc["u1", "abs_x_late"] == pytest.approx(0.0)
    assert people.loc["u1", "step_x"] == pytest.approx((0.6 + 1.2 + 0.6 + 0.3 + 0.3 + 0.8) / 6)
    # t2 timed out after one placement on custom01: the timed-out record places nothing; no step 3 at all
    assert people.loc["t2", "placements"] == 3 and np.isnan(people.loc["t2", "abs_x_late"])
    assert people.loc["t2", "step_x"] == pytest.approx((0.0 + 0.0 + 0.9) / 3)
    mixed = df.sample(frac=1.0, random_state=5)
    pd.testing.assert_frame_equal(flows.lateral(mixed), flows.lateral(df))


def test_the_flows_test_which_group_stacks_more_vertically(tmp_path):
    """A group that places every block over the one below against one that steps out: the report says which,
    with the direction, over every task."""
    records = []
    for n in range(4):
        for k, task in enumerate(("custom00", "custom01")):
            records += trial(f"v{n}", "time_limited", task, [1.2] * 5, k + 1, [[0.0, 1], [0.0, 2], [0.0, 3],
                                                                             [0.1 * (n % 2), 4]])
            records += trial(f"o{n}", "unconstrained", task, [1.2] * 5, k + 1, [[0.2, 1], [0.4, 2], [0.5, 3],
                                                                              [0.5 + 0.1 * (n % 2), 4]])
    path = tmp_path / "lateral.jsonl"
    write_log(records, path)
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out), "--only", "flows", "--n-resamples", "200", "--quiet",
                 "--world", "world.physics=static"]) == 0
    report = (out / "report.md").read_text()
    assert "the mean |x| of placements from step 3 on is higher for unconstrained than for time_limited" \
        in report.replace("The mean", "the mean")
    assert "credible" in report and "| time_limited | 4 |" in report
    summary = json.loads((out / "summary.json").read_text())
    assert summary["lateral"]["time_limited"]["abs_x_late"]["mean"] == pytest.approx(0.025)
    assert summary["lateral"]["unconstrained"]["abs_x_late"]["mean"] == pytest.approx(0.525)
    assert summary["lateral"]["unconstrained"]["abs_x_late"]["n"] == 4


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


def test_finding_states_direction_credibility_and_whether_it_matches_the_paper():
    show = "{:.2f}".format
    up = ("a", "b")
    same = analysis.finding("x", up, (1.0, 2.0), 0.01, (1.0, 1.5, "<.001"), show)
    assert same.text == ("x is higher for b than for a (2.00 vs 1.00; p = .010, credible): matches the paper "
                         "(higher, 1.50 vs 1.00, p < .001)") and same.matches
    opposite = analysis.finding("x", up, (2.0, 1.0), 0.01, (1.0, 1.5, ".022"), show)
    assert "x is lower for b" in opposite.text and "opposite to the paper" in opposite.text
    assert opposite.matches is False
    lost = analysis.finding("x", up, (1.0, 1.1), 0.4, (1.0, 1.5, ".022"), show)
    assert "p = .400, not credible): does not reproduce the paper's credible difference" in lost.text
    assert lost.matches is False
    extra = analysis.finding("x", up, (1.0, 1.1), 0.001, (1.0, 1.5, ".107"), show)
    assert "differs from the paper, which found no credible difference" in extra.text and extra.matches is False
    neither = analysis.finding("x", up, (1.1, 1.0), 0.5, (1.0, 1.5, ".482"), show)
    assert "matches the paper, which found no credible difference either" in neither.text and neither.matches
    untested = analysis.finding("x", up, (1.0, 2.0), float("nan"), (1.0, 1.5, ".022"), show)
    assert "no test" in untested.text and "same direction to the paper's, untested here" in untested.text
    assert untested.matches is None
    assert analysis.finding("x", up, (1.0, 2.0), 0.2, None, show, no_paper="; none").text.endswith("; none")
    assert analysis.paper_pair(("unconstrained", "time_limited"), 0.15, 0.24) == (0.24, 0.15)
    assert analysis.paper_pair(("a", "unconstrained"), 0.15, 0.24) is None


def test_table1_and_gamma_open_with_their_finding_and_table1_compares_per_trial(tmp_path):
    out = tmp_path / "out"
    assert main([str(people_log(tmp_path)), "--out", str(out), "--world", "world.physics=static", "--only",
                 "table1,gamma", "--n-resamples", "200", "--quiet"]) == 0
    report = (out / "report.md").read_text()
    sections = {part.split("\n", 1)[0]: part.split("\n", 1)[1].strip() for part in report.split("\n## ")[1:]}
    assert sections["Table 1: overall performance"].startswith(
        "**Finding** (unconstrained against time_limited; credible: permutation p < .05; ")
    assert sections["Order dependency Γ (Fig. 3b)"].startswith("**Finding** (`completed`, completed towers")
    tab = pd.read_csv(out / "table1.csv").set_index(["metric", "group"])
    t = tab.loc["decision_time"]
    assert (f"decision time is higher for unconstrained than for time_limited ({t.loc['unconstrained', 'mean']:.2f} s "
            f"vs {t.loc['time_limited', 'mean']:.2f} s; {analysis.p_is(t.loc['time_limited', 'p'])}, ") in report
    assert "(higher, 7.27 s vs 2.47 s, p < .001)" in report
    # 5-task (here 1 to 3) totals are said to be so; per trial, the paper's total / 20
    assert "| Total reward (sum over 1–3 tasks; paper: 20) |" in report
    assert "| Reward per trial (paper: total / 20) |" in report
    assert "| 0.9125 ± 0.0285 | 0.9785 ± 0.0280 | .107 |" in report
    per = pd.read_csv(out / "table1_participants.csv")
    np.testing.assert_allclose(per["reward_per_trial"], per["total_reward"] / per["trials"])
    g = json.loads((out / "summary.json").read_text())["gamma"]
    u, t = g["unconstrained"]["participants_mean"], g["time_limited"]["participants_mean"]
    assert u < t   # t1's two towers against u1's and u2's; the groups have 1 and 2 participants: no test
    assert (f"Γ across participants is lower for unconstrained than for time_limited ({u:.3f} vs {t:.3f}; no test: "
            "a group has fewer than two participants with a value): opposite direction to the paper's, untested here "
            "(higher, 0.24 vs 0.15, p = .022).") in sections["Order dependency Γ (Fig. 3b)"]


def _shuffled(path: Path, out: Path, how: str, seed: int = 0) -> Path:
    """The log at ``path`` with its lines in another order: ``shuffle`` (seeded), ``steps`` (each trial's steps
    reversed, trials in place) or ``reverse`` (the whole file backwards)."""
    import random

    lines = path.read_text().splitlines()
    if how == "shuffle":
        random.Random(seed).shuffle(lines)
    elif how == "steps":
        key = [json.loads(line) for line in lines]
        lines = [line for _, line in sorted(zip(key, lines), key=lambda kl: (kl[0]["participant"], kl[0]["trial"],
                                                                             -kl[0]["step"]))]
    else:
        lines.reverse()
    out.write_text("\n".join(lines) + "\n")
    return out


def _report_body(path: Path) -> list[str]:
    """report.md without what depends on the run rather than the log: the log's path and the times."""
    text = path.read_text()
    return [line for line in text[:text.index("## Time")].splitlines() if not line.startswith("Logs: ")]


def test_the_whole_report_is_the_same_for_any_order_of_the_logs_lines(tmp_path):
    log = people_log(tmp_path)
    args = ["--world", "world.physics=static", "--predictors", "veridical", "--n-resamples", "200",
            "--bootstrap", "50", "--quiet"]
    assert main([str(log), "--out", str(tmp_path / "base"), *args]) == 0
    base = tmp_path / "base"
    summary = json.loads((base / "summary.json").read_text())
    assert summary["table1"]["total_reward"]["time_limited"]["mean"] > 0 and summary["gamma"]["time_limited"]["towers"]
    csvs = sorted(p.name for p in base.glob("*.csv"))
    assert {"table1.csv", "gamma.csv", "gamma_towers.csv", "fig3a_flows.csv", "fig4_placements.csv"} <= set(csvs)
    for how in ("shuffle", "steps", "reverse"):
        other = tmp_path / how
        assert main([str(_shuffled(log, tmp_path / f"{how}.jsonl", how)), "--out", str(other), *args]) == 0
        theirs = json.loads((other / "summary.json").read_text())
        assert {k: v for k, v in theirs.items() if k != "seconds"} == \
            {k: v for k, v in summary.items() if k != "seconds"}, how
        for name in csvs:
            assert (other / name).read_bytes() == (base / name).read_bytes(), (how, name)
        assert _report_body(other / "report.md") == _report_body(base / "report.md"), how


def test_each_analysis_takes_a_trials_last_step_from_a_dataframe_in_any_order(tmp_path):
    """Without the reader's sort: a DataFrame whose rows are shuffled gives every analysis the same answer."""
    df = analysis.with_groups(read_log(people_log(tmp_path)))
    mixed = df.sample(frac=1.0, random_state=3)
    steps = df.sort_values(["participant", "trial", "step"], ascending=[True, True, False])
    assert not mixed.index.equals(df.index)
    for other in (mixed, steps):
        pd.testing.assert_frame_equal(table1.trial_outcomes(other), table1.trial_outcomes(df))
        pd.testing.assert_frame_equal(table1.per_participant(other), table1.per_participant(df))
        pd.testing.assert_frame_equal(gamma.trial_towers(other), gamma.trial_towers(df))
        assert analysis.completeness(other) == analysis.completeness(df)
        pd.testing.assert_frame_equal(flows.transitions(other, "custom00", 0.1), flows.transitions(df, "custom00", 0.1))
    outcomes = table1.trial_outcomes(steps).set_index(["participant", "trial"])
    assert outcomes.loc[("t1", 1), "reward"] > 0 and outcomes.loc[("t1", 1), "stood"]

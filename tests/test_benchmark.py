"""The benchmark: splits, optima, the metric, the protocol and agents of any kind."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from overhang_framework.benchmark import score, splits

ROOT = Path(__file__).resolve().parents[1]
STATIC = ["world.physics=static", "verdicts=null", "figure=false", "progress=false"]


# ------------------------------------------------------------------------------------------------ splits

def test_task_ids_name_their_sequences_and_refuse_what_is_not_a_task():
    assert splits.task_id((1.2, 1.8, 0.6, 1.8, 1.2, 0.6)) == "w231321"
    assert splits.sequence_of("w231321") == (1.2, 1.8, 0.6, 1.8, 1.2, 0.6)
    space = splits.task_space(6)
    assert len(space) == len(set(space)) == 729
    assert all(splits.task_id(splits.sequence_of(t)) == t for t in space)
    with pytest.raises(splits.SplitError, match="not a task id"):
        splits.sequence_of("w1204")
    with pytest.raises(splits.SplitError, match="not one of"):
        splits.task_id((0.6, 0.9))


def test_the_splits_are_disjoint_and_cover_the_six_block_space():
    data = splits.load()
    test, paper20 = set(splits.split_ids("test")), set(splits.split_ids("paper20"))
    folds = [set(splits.split_ids("train", k)) for k in range(splits.FOLDS)]
    train = set().union(*folds)
    assert len(test) >= 100 and len(paper20) == 20
    assert sum(len(f) for f in folds) == len(train)  # folds disjoint
    assert not (test & paper20) and not (test & train) and not (train & paper20)
    assert test | train | paper20 == set(splits.task_space(6))
    assert max(len(f) for f in folds) - min(len(f) for f in folds) <= 1
    cross = splits.split_ids("cross")
    assert cross and all(len(splits.sequence_of(t)) == splits.CROSS_LENGTH for t in cross)
    assert paper20 == {splits.task_id(s) for s in splits.paper20_sequences()}
    assert data["seed"] == splits.SEED


def test_the_test_split_covers_every_width_mix_ground_width_and_third_of_difficulty():
    data = splits.load()
    test = splits.split_ids("test")
    assert {splits.composition(t) for t in test} == {splits.composition(t) for t in splits.task_space(6)}
    assert {t[1] for t in test} == {"1", "2", "3"}
    gaps = sorted(v["gap"] for t, v in data["measures"].items() if t not in set(splits.split_ids("paper20")))
    cuts = np.quantile(gaps, [1 / 3, 2 / 3])
    mine = np.array([data["measures"][t]["gap"] for t in test])
    thirds = [(mine <= cuts[0]).sum(), ((mine > cuts[0]) & (mine <= cuts[1])).sum(), (mine > cuts[1]).sum()]
    assert min(thirds) >= 20, thirds


def test_the_splits_are_what_their_seed_draws_and_never_change():
    data = splits.load()
    assert splits.draw(data["measures"], data["splits"]["paper20"], seed=data["seed"]) == data["splits"]
    # a published split is fixed: these digests change only if the split itself changed
    digest = {name: hashlib.sha256(",".join(splits.split_ids(name)).encode()).hexdigest()[:16]
              for name in ("test", "cross")}
    assert digest == {"test": "eae8b7a1baa5405a", "cross": "dac38904d4d53805"}


def test_check_command_says_whether_a_file_holds_its_draw(tmp_path):
    data = splits.load()
    good = tmp_path / "splits.json"
    good.write_text(json.dumps(data))
    from overhang_framework.benchmark.splits import main

    assert main(["--check", "--out", str(good)]) == 0
    data["splits"]["test"] = data["splits"]["test"][1:]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(data))
    assert main(["--check", "--out", str(bad)]) == 1
    (tmp_path / "broken.json").write_text("{")
    assert main(["--check", "--out", str(tmp_path / "broken.json")]) == 2


@pytest.mark.slow
def test_the_kept_difficulty_measures_are_what_the_agents_score_now():
    data = splits.load()
    sample = sorted(data["measures"])[::50]
    assert splits.measure(sample, progress=False) == {t: data["measures"][t] for t in sample}


# ------------------------------------------------------------------------------------------------ the metric

def _rows(values, seeds=1, budget=None):
    rows = []
    for k, v in enumerate(values):
        for s in range(seeds):
            rows.append({"task_id": f"w{k:06d}", "seed": s, "budget": budget, "reward": v * 2, "optimum": 2.0,
                         "normalised": v, "stood": v > 0, "calls": 5, "seconds": 0.1, "reason": "", "steps": 5})
    return rows


def test_the_score_is_the_mean_over_tasks_with_a_bootstrap_interval_around_it():
    rng = np.random.default_rng(1)
    values = rng.uniform(0.2, 1.0, size=60)
    result = score.summarise(_rows(values, seeds=2))
    assert result["score"] == pytest.approx(values.mean())
    assert result["ci_low"] < result["score"] < result["ci_high"]
    sem = values.std(ddof=1) / np.sqrt(len(values))
    assert result["ci_high"] - result["ci_low"] == pytest.approx(2 * 1.96 * sem, rel=0.1)
    assert result["n_tasks"] == 60 and result["seeds"] == 2 and result["stood"] == 1.0
    assert result["reward"] == pytest.approx(2 * values.mean())


def test_the_summary_does_not_depend_on_the_order_of_its_rows():
    rows = _rows(np.linspace(0, 1, 30), seeds=3)
    shuffled = [rows[i] for i in np.random.default_rng(0).permutation(len(rows))]
    assert score.summary(rows) == score.summary(shuffled)


def test_the_area_weighs_each_doubling_of_compute_alike():
    assert score.area([(1, 0.5), (4, 0.5), (16, 0.5)]) == pytest.approx(0.5)
    early = score.area([(1, 0.8), (4, 0.9), (16, 0.9), (64, 0.9), (256, 0.9)])
    late = score.area([(1, 0.1), (4, 0.2), (16, 0.3), (64, 0.6), (256, 0.9)])
    assert early > late
    # equal log spacing: the trapezoid is the mean with the ends weighted half
    assert score.area([(1, 0.0), (2, 1.0), (4, 1.0)]) == pytest.approx(0.75)
    assert score.area([(8, 0.4)]) is None
    rows = _rows([0.5, 0.7], budget=1.0) + _rows([0.6, 0.8], budget=4.0)
    result = score.summary(rows)
    assert result["curve"] == [[1.0, pytest.approx(0.6)], [4.0, pytest.approx(0.7)]]
    assert result["area"] == pytest.approx(0.65)
    assert result["score"] == pytest.approx(0.7)  # the top rung's


# ------------------------------------------------------------------------------------------------ running agents

def bench(tmp_path, *words, name="run", check=True):
    out = tmp_path / name
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.benchmark", *STATIC, *words,
                           f"hydra.run.dir={out}"], cwd=ROOT, capture_output=True, text=True, timeout=600)
    if check:
        assert proc.returncode == 0, proc.stderr[-2000:]
    return out, proc


def scores_without_time(out: Path) -> pd.DataFrame:
    return pd.read_csv(out / "scores.csv").drop(columns=["seconds"])


FIVE = "ids=[w121223,w122321,w212333,w233233,w133322]"


@pytest.mark.parametrize("command", [["python3", "examples/agents/lean.py"], ["node", "examples/agents/centre.js"]],
                         ids=["python", "node"])
def test_the_example_agents_score_identically_twice(tmp_path, command):
    word = "agent.command=[" + ",".join(command) + "]"
    a, _ = bench(tmp_path, "agent=command", word, FIVE, "seeds=1", name="a")
    b, _ = bench(tmp_path, "agent=command", word, FIVE, "seeds=1", name="b")
    first = scores_without_time(a)
    assert len(first) == 5 and first["optimum"].notna().all()
    pd.testing.assert_frame_equal(first, scores_without_time(b))
    summary = json.loads((a / "summary.json").read_text())
    assert summary["reward"] > 0 and summary["score"] <= 1.0
    assert (first["normalised"] <= 1 + 1e-9).all()


BAD_AGENT = '''
import json, sys, time
for line in sys.stdin:
    m = json.loads(line)
    if m.get("type") != "decision":
        continue
    if m["task_id"] == "w122321":
        MODE
    x, layer = m["legal"][0]
    print(json.dumps({"x": x, "layer": layer}), flush=True)
'''


@pytest.mark.parametrize("mode,reason", [
    ("sys.exit(3)", "agent crashed at placement 1 (exit code 3)"),
    ("time.sleep(60)", "agent gave no answer within 2 s at placement 1"),
    ('print(json.dumps({"x": 3.95, "layer": 1}), flush=True); continue', "illegal placement x=3.95, layer=1"),
    ('print("left", flush=True); continue', "malformed answer at placement 1"),
], ids=["crash", "hang", "illegal", "malformed"])
def test_a_failing_agent_ends_its_task_with_a_reason_and_the_run_goes_on(tmp_path, mode, reason):
    program = tmp_path / "agent.py"
    program.write_text(BAD_AGENT.replace("MODE", mode))
    out, proc = bench(tmp_path, "agent=command", f"agent.command=[{sys.executable},{program}]", "agent.timeout=2",
                      "ids=[w121223,w122321,w212333]", "seeds=2")
    rows = pd.read_csv(out / "scores.csv", keep_default_na=False)
    assert len(rows) == 6
    failed = rows[rows["task_id"] == "w122321"]
    assert (failed["reward"] == 0).all() and failed["reason"].str.startswith(reason).all(), failed["reason"].tolist()
    others = rows[rows["task_id"] != "w122321"]
    assert others["steps"].min() >= 1 and not others["reason"].str.contains("agent").any()
    assert len((out / "episodes.jsonl").read_text().splitlines()) == 6


def test_a_stopped_run_continues_and_a_directory_of_another_config_is_refused(tmp_path):
    out, _ = bench(tmp_path, FIVE, "seeds=2")
    whole = scores_without_time(out)
    lines = (out / "episodes.jsonl").read_text().splitlines()
    (out / "episodes.jsonl").write_text("\n".join(lines[:4]) + "\n" + lines[4][:30])  # stopped mid-line
    (out / "scores.csv").unlink()
    bench(tmp_path, FIVE, "seeds=2")
    pd.testing.assert_frame_equal(scores_without_time(out), whole)
    _, proc = bench(tmp_path, FIVE, "seeds=3", check=False)
    assert proc.returncode == 2 and "holds results of a different config (seeds: 2 -> 3)" in proc.stderr


def test_the_oracle_scores_one_and_a_budget_ladder_gives_a_curve(tmp_path):
    out, _ = bench(tmp_path, "planner=optimal", FIVE, "seeds=1", name="oracle")
    rows = pd.read_csv(out / "scores.csv")
    assert np.allclose(rows["normalised"], 1.0)
    out, _ = bench(tmp_path, "planner=lookahead", "planner.depth=2", FIVE, "seeds=1", "budgets=[1,4,16]",
                   name="ladder")
    summary = json.loads((out / "summary.json").read_text())
    assert [b for b, _ in summary["curve"]] == [1, 4, 16]
    assert summary["area"] is not None and 0 <= summary["area"] <= 1
    rows = pd.read_csv(out / "scores.csv")
    assert len(rows) == 15 and (rows["normalised"] <= 1 + 1e-9).all()
    assert (rows.groupby("budget")["calls"].max() <= rows.groupby("budget")["steps"].max() * rows["budget"].unique()).all()


@pytest.mark.parametrize("words,message", [
    (["split=validation"], "unknown split 'validation'; splits: test, train, cross, paper20"),
    (["ids=[w1204]"], "'w1204' is not a task id"),
    (["agent=command"], "agent=command needs agent.command"),
    (["agent=random", "budgets=[1,4]"], "agent=random takes no budget"),
    (["budgets=[0,4]"], "budgets must be a list of distinct numbers > 0"),
    (["split=train", "fold=7"], "train fold 7 does not exist; folds are 0 to 4"),
])
def test_bad_benchmark_input_gets_one_line(tmp_path, words, message):
    _, proc = bench(tmp_path, *words, check=False)
    assert proc.returncode == 2
    assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr


# ------------------------------------------------------------------------------------------------ optima

def _references(world) -> int:
    return int(world.backend.backend.counts["reference"])


@pytest.mark.parametrize("physics", ["static", "tiered"])
def test_the_lattice_search_finds_the_optimum_and_path_of_the_search_that_tries_ties(physics):
    """The search on the score lattice, with unknown inner answers settled only when their subtree could
    win, finds the same optimum and path as the plain search, asking the dear reference less."""
    from overhang_framework.optimum import OptimumSearch
    from overhang_framework.plugins import Registry

    tasks = ("w2312", "w31211") if physics == "static" else ("w2312", "w3121")
    for tid in tasks:
        got = {}
        for lattice in (False, True):
            world = Registry().create("world", {"name": "overhang", "physics": physics})
            predictor = Registry().create("predictor", {"name": "veridical"}, world=world)
            search = OptimumSearch(world, predictor, lattice=lattice)
            best, path = search.best_path(world.initial_state(splits.task(tid)))
            asked = _references(world) if physics == "tiered" else search.expander.stats.nodes_expanded
            got[lattice] = (round(best, 9), [(a.x, a.layer) for a in path], asked)
        assert got[True][:2] == got[False][:2], tid
        assert got[True][2] <= got[False][2], (tid, got)


def test_optima_command_keeps_each_task_at_once_and_resumes(tmp_path):
    out = tmp_path / "optima.json"
    words = [sys.executable, "-m", "overhang_framework.benchmark.optima", "ids=[w2312,w13122]", f"out={out}",
             "world.physics=static", "verdicts=null", "progress=false"]
    proc = subprocess.run([*words, f"hydra.run.dir={tmp_path / 'r1'}"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    optima = json.loads(out.read_text())["optima"]
    assert sorted(r["task_id"] for r in optima.values()) == ["w13122", "w2312"]
    assert all(r["reference"]["stood"] for r in optima.values())
    table = pd.read_csv(tmp_path / "r1" / "optima.csv")
    assert list(table["task_id"]) == ["w2312", "w13122"]
    proc = subprocess.run([*words, f"hydra.run.dir={tmp_path / 'r2'}"], cwd=ROOT, capture_output=True, text=True)
    assert "0 solved now" in proc.stdout
    assert json.loads(out.read_text())["optima"] == optima


def test_optima_carry_to_a_stricter_tiered_physics_only_where_the_stored_path_still_stands(tmp_path):
    from overhang_framework.benchmark.optima import carry, carry_refusal
    from overhang_framework.optimum import load_optima, optimum_key, physics_id, sequence_key
    from overhang_framework.plugins import Registry

    world = Registry().create("world", {"name": "overhang"})
    ident = physics_id(world)
    tids = ["w111112", "w111122"]
    stored = {r["task_id"]: r for r in load_optima().values() if r["physics"] == "tiered" and r["task_id"] in tids
              and r["params"] == ident["params"] and r["resolution"] == ident["resolution"]}
    assert sorted(stored) == sorted(tids)
    looser = {**ident["params"], "stable_tilt": ident["params"]["stable_tilt"] / 2}
    old = {**ident, "params": looser}
    assert carry_refusal({**old}, ident) is None
    assert "stable_tilt" in carry_refusal(ident, {**old})  # to a looser stage: refused
    assert "fall_margin" in carry_refusal({**old, "params": {**looser, "fall_margin": -0.01}}, ident)
    assert "resolution" in carry_refusal({**old, "resolution": 0.05}, ident)
    assert "only tiered" in carry_refusal({**old, "physics": "static"}, ident)
    fallen = dict(stored["w111112"], **old, actions=[[3.5, a[1]] for a in stored["w111112"]["actions"]])
    assert carry(fallen, world) is None  # a path that falls is not carried
    out = tmp_path / "optima.json"
    out.write_text(json.dumps({"optima": {sequence_key(r["sequence"], old): {**r, **old} for r in stored.values()}}))
    words = [sys.executable, "-m", "overhang_framework.benchmark.optima", f"ids=[{','.join(tids)}]", f"out={out}",
             "verdicts=null", "progress=false", "carry=true", f"hydra.run.dir={tmp_path / 'r'}"]
    proc = subprocess.run(words, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert "0 solved now, 2 carried from a physics that grants more" in proc.stdout
    from overhang_framework.benchmark.splits import task

    rows = load_optima(out)
    for tid in tids:
        row = rows[optimum_key(task(tid), world)]
        assert (row["optimum"], row["actions"], row["params"]) == (stored[tid]["optimum"], stored[tid]["actions"],
                                                                     ident["params"])
        assert row["carried"]["params"] == looser and row["reference"] == stored[tid]["reference"]
    refused = subprocess.run([*words[:-1], "world.physics=static", f"hydra.run.dir={tmp_path / 's'}"], cwd=ROOT,
                             capture_output=True, text=True, timeout=600)
    assert refused.returncode != 0 and "carry=true carries optima to a stricter tiered physics" in refused.stderr


def test_optimum_parts_of_several_jobs_merge_into_one_file(tmp_path):
    from overhang_framework.benchmark.optima import keep_part, merge, parts_dir

    out = tmp_path / "optima.json"
    out.write_text(json.dumps({"optima": {"a": {"optimum": 1.0}}}))
    keep_part(out, "b", {"optimum": 2.0})
    keep_part(out, "c", {"optimum": 3.0})
    assert merge(out) == 2
    assert json.loads(out.read_text())["optima"] == {"a": {"optimum": 1.0}, "b": {"optimum": 2.0},
                                                    "c": {"optimum": 3.0}}
    assert not parts_dir(out).exists()


def _benchmark_rows():
    from overhang_framework.optimum import DATA_FILE, load_optima

    scored = set(splits.split_ids("test")) | set(splits.split_ids("cross"))
    return sorted((r for r in load_optima(DATA_FILE).values() if r["task_id"] in scored and r["physics"] == "tiered"),
                  key=lambda r: r["task_id"])


def test_every_scored_test_task_has_an_optimum_whose_path_stood_under_the_reference():
    rows = {r["task_id"]: r for r in _benchmark_rows()}
    assert set(splits.split_ids("test")) <= set(rows)
    for row in rows.values():
        assert row["reference"]["stood"] and row["reference"]["overhang"] == pytest.approx(row["optimum"])
        assert len(row["actions"]) == len(row["sequence"]) - 1


def _replay(row):
    from overhang_framework.benchmark.optima import replay

    return replay(row, {"name": "overhang", "physics": "tiered"})


@pytest.mark.parametrize("row", _benchmark_rows()[::25], ids=lambda r: r["task_id"])
def test_a_sample_of_stored_benchmark_paths_stands_under_the_reference_again(row):
    again = _replay(row)
    assert again["stood"] and again["overhang"] == pytest.approx(row["optimum"])


@pytest.mark.slow
@pytest.mark.parametrize("row", _benchmark_rows(), ids=lambda r: r["task_id"])
def test_every_stored_benchmark_path_stands_under_the_reference_again(row):
    again = _replay(row)
    assert again["stood"] and again["overhang"] == pytest.approx(row["optimum"])


def test_random_agent_and_rendered_scenes_for_an_external_program(tmp_path):
    out, _ = bench(tmp_path, "agent=random", FIVE, "seeds=2", name="random")
    rows = pd.read_csv(out / "scores.csv", keep_default_na=False)
    assert len(rows) == 10 and (rows["normalised"] < 1).all()
    again, _ = bench(tmp_path, "agent=random", FIVE, "seeds=2", name="random2")
    pd.testing.assert_frame_equal(scores_without_time(out), scores_without_time(again))
    program = tmp_path / "looks.py"
    program.write_text('''
import json, sys
from pathlib import Path
for line in sys.stdin:
    m = json.loads(line)
    if m.get("type") == "decision":
        assert Path(m["image"]).read_bytes()[:8] == b"\\x89PNG\\r\\n\\x1a\\n"
        x, layer = min(m["legal"], key=lambda a: (-a[1], abs(a[0])))
        print(json.dumps({"x": x, "layer": layer}), flush=True)
''')
    out, _ = bench(tmp_path, "agent=command", f"agent.command=[{sys.executable},{program}]", "agent.render=true",
                   "ids=[w121223]", "seeds=1", name="render")
    rows = pd.read_csv(out / "scores.csv", keep_default_na=False)
    assert rows["reason"].tolist() == [""] and len(list((out / "images").glob("w121223-s0-*.png"))) == 5


def test_ppo_trains_on_a_benchmark_split():
    from overhang_framework.envs.ppo import task_kwargs

    sequences = task_kwargs("benchmark:train")["sequences"]
    assert len(sequences) == len(splits.split_ids("train")) and all(len(s) == 6 for s in sequences)
    assert task_kwargs("paper20") == {"tasks": "paper20"}
    with pytest.raises(splits.SplitError, match="unknown split"):
        task_kwargs("benchmark:validation")


def test_optima_jobs_of_a_multirun_share_one_file(tmp_path):
    out = tmp_path / "optima.json"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.benchmark.optima", "-m", "shard=0,1", "shards=2",
                           "ids=[w2312,w13122,w3121]", f"out={out}", "world.physics=static", "verdicts=null",
                           "progress=false", "hydra/launcher=local", "hydra.launcher.n_jobs=2",
                           f"hydra.sweep.dir={tmp_path / 'sweep'}"], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    optima = json.loads(out.read_text())["optima"]
    assert sorted(r["task_id"] for r in optima.values()) == ["w13122", "w2312", "w3121"]
    shares = [pd.read_csv(tmp_path / "sweep" / str(k) / "optima.csv")["task_id"].tolist() for k in (0, 1)]
    assert shares == [["w2312", "w3121"], ["w13122"]]


def test_leaderboard_rows_carry_their_command_and_provenance_and_replace_their_own(tmp_path):
    from overhang_framework.benchmark import leaderboard

    out, _ = bench(tmp_path, FIVE, "seeds=1", name="myopic")
    summary = json.loads((out / "summary.json").read_text())
    (out / "summary.json").write_text(json.dumps({**summary, "split": "test"}))  # as a run of the split would say
    board = tmp_path / "leaderboard.csv"
    assert leaderboard.main(["add", str(out), "--file", str(board)]) == 0
    assert leaderboard.main(["add", str(out), "--file", str(board)]) == 0  # the same agent and split: replaced
    rows = leaderboard.load(board)
    assert len(rows) == 1
    ladder = dict(leaderboard.row_of(out), curve="[[1.0, 0.5], [4.0, 0.6]]")
    leaderboard.add([ladder], board)  # the same agent and split with a budget ladder: a row of its own
    assert len(leaderboard.load(board)) == 2
    leaderboard.add([leaderboard.row_of(out)], board)  # the run without a ladder replaces only its own row
    assert sorted(bool(c) for c in leaderboard.load(board)["curve"]) == [False, True]
    leaderboard.add([ladder], board)
    rows = leaderboard.load(board)
    rows = rows[rows["curve"] == ""]
    row = rows.iloc[0]
    assert row["agent"] == "myopic + veridical" and row["split"] == "test"
    assert row["command"].startswith("python -m overhang_framework.benchmark ") and "seeds=1" in row["command"]
    assert "hydra.run.dir" not in row["command"] and json.loads(row["config"])["planner"]["name"] == "myopic"
    assert row["version"] and row["date"]
    summary = json.loads((out / "summary.json").read_text())
    assert float(row["score"]) == pytest.approx(summary["score"], abs=1e-6)
    assert "| myopic + veridical | test |" in leaderboard.markdown(rows)
    assert leaderboard.main(["figure", "--split", "test", "--out", str(tmp_path / "b.png"), "--file", str(board)]) == 0
    assert (tmp_path / "b.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow
def test_no_agent_beats_a_stored_optimum_and_the_oracle_reaches_each(tmp_path):
    """Depth-2 lookahead with the world's own verdicts on a sample of test tasks, under the default physics:
    a reward above a task's stored optimum would mean the optimum is wrong."""
    sample = "ids=[" + ",".join(splits.split_ids("test")[::20]) + "]"
    words = ["world.physics=tiered", f"verdicts={tmp_path / 'v.sqlite'}", sample, "seeds=1"]
    out, _ = bench(tmp_path, *words, "planner=lookahead", "planner.depth=2", name="d2")
    rows = pd.read_csv(out / "scores.csv")
    assert rows["optimum"].notna().all() and (rows["normalised"] <= 1 + 1e-9).all()
    assert json.loads((out / "summary.json").read_text())["above_optimum"] == []
    out, _ = bench(tmp_path, *words, "planner=optimal", name="oracle")
    assert np.allclose(pd.read_csv(out / "scores.csv")["normalised"], 1.0)

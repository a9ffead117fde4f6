"""The main job end to end: output files, summary, reproducibility, one-line errors."""

import json
import subprocess
import sys

import pytest

from overhang_framework.results import read_episodes, without_timing

QUICK = ["tasks=custom", "tasks.sequences=[[1.2,0.6,1.8],[0.6,1.2,1.2]]", "progress=false"]


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "overhang_framework", *args],
                          capture_output=True, text=True, cwd=cwd)


def test_main_job_writes_episodes_and_metrics(tmp_path):
    out = tmp_path / "run"
    proc = run_cli(*QUICK, "seed=3", f"hydra.run.dir={out}")
    assert proc.returncode == 0, proc.stderr
    assert "terminal reward" in proc.stdout and "decision time (s)" in proc.stdout
    episodes = read_episodes(out / "episodes.jsonl")
    assert [e["task_id"] for e in episodes] == ["custom00", "custom01"]
    for e in episodes:
        assert e["seed"] == 3
        assert set(e) >= {"task_id", "sequence", "steps", "reward", "overhang", "stable_throughout"}
        for s in e["steps"]:
            assert set(s) >= {"x", "layer", "predicted_stability", "stable", "decision_time", "spend"}
            assert s["spend"]["predictor_calls"] >= 1
        assert e["reward"] == (e["overhang"] if e["stable_throughout"] else 0.0)
        assert len(e["steps"]) == len(e["sequence"]) - 1 or not e["stable_throughout"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["episodes"] == 2
    assert metrics["reward_mean"] == pytest.approx(sum(e["reward"] for e in episodes) / 2)
    assert not (out / "episodes.jsonl.partial").exists()


def test_same_seed_same_episodes(tmp_path):
    runs = []
    for name in ("a", "b"):
        proc = run_cli(*QUICK, "seed=11", f"hydra.run.dir={tmp_path / name}")
        assert proc.returncode == 0, proc.stderr
        runs.append(without_timing(read_episodes(tmp_path / name / "episodes.jsonl")))
    assert runs[0] == runs[1]


@pytest.mark.parametrize("args, expected", [
    (["predictor=nonexistent"], "unknown predictor 'nonexistent'; installed predictors: "),
    (["-m", "planner=myopic,nonexistent"], "unknown planner 'nonexistent'; installed planners: "),
    (["tasks=custom", "tasks.sequences=[[0.6,0.7]]"], "illegal block width 0.7; allowed widths are 0.6, 1.2, 1.8"),
])
def test_bad_input_exits_non_zero_with_one_line(tmp_path, args, expected):
    proc = run_cli(*args, f"hydra.run.dir={tmp_path}", "hydra.sweep.dir=" + str(tmp_path / "m"))
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert expected in lines[0]
    assert "veridical" in lines[0] or "myopic" in lines[0] or "width" in lines[0]


def test_example_plugin_runs_through_the_cli(example_plugin, tmp_path, capsys):
    from overhang_framework.cli import main

    main([*QUICK, "planner=random", "planner.min_stability=0.9", f"hydra.run.dir={tmp_path}"])
    episodes = read_episodes(tmp_path / "episodes.jsonl")
    assert len(episodes) == 2
    assert all(s["predicted_stability"] >= 0.9 for e in episodes for s in e["steps"])
    assert "terminal reward" in capsys.readouterr().out

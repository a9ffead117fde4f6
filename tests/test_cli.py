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


@pytest.mark.parametrize("override, expected", [
    ("world.resolution=-1", "world 'overhang': resolution must be a positive number of metres, got -1"),
    ("world.physics=nope", "unknown physics 'nope'; allowed: pybullet, static"),
    ("+world.bogus=1", "world 'overhang' has no parameter bogus; its parameters: cache, physics,"),
    ("+world.static.bogus=1", "unknown parameter(s) bogus for physics backend 'static'; allowed: friction,"),
    ("world.pybullet.time_step=0", "PyBulletParams.time_step must be a number > 0, got 0"),
    ("world.static.friction=-1", "StaticParams.friction must be a number >= 0, got -1"),
    ("world.workers=0", "workers must be a whole number >= 1, got 0"),
    ("world.cache=maybe", "cache must be true or false, got 'maybe'"),
    ("+predictor.bogus=1", "predictor 'veridical' has no parameter bogus; its parameters: backend, backend_params"),
    ("seed=-1", "seed must be a whole number >= 0, got -1"),
    ("repeats=abc", "repeats must be a whole number >= 1, got 'abc'"),
    ("condition.time_limit=-1", "condition.time_limit must be a number of seconds > 0 or null, got -1"),
])
def test_bad_config_values_stop_before_any_episode(tmp_path, capsys, override, expected):
    from overhang_framework.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, override, f"hydra.run.dir={tmp_path}"])
    assert exit_info.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "build time" not in line]
    assert err == [f"error: {err[0][7:]}"] and expected in err[0]
    assert not (tmp_path / "episodes.jsonl").exists() and not (tmp_path / "episodes.jsonl.partial").exists()


@pytest.mark.parametrize("args", [["predictor=nope", "--cfg", "job"], ["--cfg", "job", "predictor=nope"]])
def test_unknown_names_are_caught_around_hydra_flags(args, capsys):
    from overhang_framework.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    assert "unknown predictor 'nope'" in capsys.readouterr().err


def test_glob_sweeps_are_left_to_hydra():
    from overhang_framework.cli import check_overrides

    check_overrides(["predictor=glob(*)", "-m"])  # does not raise


def test_a_crashed_worker_stops_the_run_and_keeps_finished_episodes(tmp_path, capsys, monkeypatch):
    import overhang_framework.app as app
    from overhang_framework.cli import main
    from overhang_framework.physics.pool import PoolCrashed

    real, calls = app.run_episode, []

    def crash_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise PoolCrashed("a PyBullet pool worker died while checking a batch of 9 geometries")
        return real(*args, **kwargs)

    monkeypatch.setattr(app, "run_episode", crash_on_second)
    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, f"hydra.run.dir={tmp_path}"])
    assert exit_info.value.code == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "build time" not in line]
    assert len(err) == 1 and "pool worker died" in err[0] and "episodes.jsonl.partial" in err[0]
    kept = read_episodes(tmp_path / "episodes.jsonl.partial")
    assert [e["task_id"] for e in kept] == ["custom00"]
    assert not (tmp_path / "episodes.jsonl").exists()
    assert "to resume, rerun the same command" in err[0]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert (metrics["complete"], metrics["episodes"], metrics["episodes_expected"]) == (False, 1, 2)

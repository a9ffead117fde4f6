"""Multirun sweeps: a real ``-m`` run into a temporary sweep directory, locally and with joblib."""

import json
import subprocess
import sys

import pytest

from overhang_framework.results import read_episodes

QUICK = ["tasks=custom", "tasks.sequences=[[1.2,0.6,0.6]]", "progress=false"]


@pytest.mark.parametrize("launcher", [[], ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"]],
                         ids=["basic", "joblib"])
def test_multirun_writes_one_run_per_job(tmp_path, launcher):
    proc = subprocess.run(
        [sys.executable, "-m", "overhang_framework", "-m", *QUICK, "seed=1,2",
         "condition=unconstrained,time_limited", f"hydra.sweep.dir={tmp_path}", *launcher],
        capture_output=True, text=True,
    )
    assert proc.returncode == 0, proc.stderr
    jobs = sorted(p for p in tmp_path.iterdir() if p.is_dir() and p.name.isdigit())
    assert [p.name for p in jobs] == ["0", "1", "2", "3"]
    seeds = sorted(read_episodes(p / "episodes.jsonl")[0]["seed"] for p in jobs)
    assert seeds == [1, 1, 2, 2]
    assert all((p / "metrics.json").exists() for p in jobs)


def _csv(path):
    import csv

    with open(path) as fh:
        return list(csv.DictReader(fh))


STATIC = ["tasks=custom", "tasks.sequences=[[1.2,0.6,0.6],[0.6,1.8,1.2]]", "progress=false", "world.physics=static"]


def test_a_sweep_writes_results_csv_with_its_overrides_as_columns(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "overhang_framework", "-m", *STATIC, "seed=1,2",
                           "planner=myopic,lookahead", f"hydra.sweep.dir={tmp_path}"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    rows = _csv(tmp_path / "results.csv")
    assert [(r["job"], r["status"], r["seed"], r["planner"]) for r in rows] == [
        ("0", "complete", "1", "myopic"), ("1", "complete", "1", "lookahead"),
        ("2", "complete", "2", "myopic"), ("3", "complete", "2", "lookahead")]
    for row in rows:
        metrics = json.loads((tmp_path / row["job"] / "metrics.json").read_text())
        assert float(row["reward_mean"]) == pytest.approx(metrics["reward_mean"], rel=1e-5)
        assert row["episodes"] == row["episodes_expected"] == "2"
    assert "results.csv: 4 jobs, 4 complete" in proc.stdout


def test_a_failing_job_is_reported_and_the_others_keep_their_results(tmp_path, capsys, monkeypatch):
    import overhang_framework.app as app
    import overhang_framework.episode as episode
    from overhang_framework.cli import main

    real = episode.run_episode

    def fail_for_seed_2(task, world, predictor, planner, value, rng, *args, **kwargs):
        if app.HydraConfig.get().job.override_dirname.find("seed=2") >= 0:
            raise RuntimeError("the planner lost its way\nsecond line")
        return real(task, world, predictor, planner, value, rng, *args, **kwargs)

    monkeypatch.setattr(episode, "run_episode", fail_for_seed_2)
    with pytest.raises(SystemExit) as exit_info:
        main(["-m", *STATIC, "seed=1,2,3", f"hydra.sweep.dir={tmp_path}"])
    assert exit_info.value.code == 1
    rows = {r["seed"]: r for r in _csv(tmp_path / "results.csv")}
    assert rows["1"]["status"] == rows["3"]["status"] == "complete"
    assert rows["2"]["status"] == "failed" and rows["2"]["error"] == "RuntimeError: the planner lost its way"
    out = capsys.readouterr().out
    assert "3 jobs, 2 complete, 1 failed; failed: 1 (" in out and "RuntimeError: the planner lost its way" in out


def test_rerunning_a_sweep_skips_the_finished_jobs(tmp_path):
    args = [sys.executable, "-m", "overhang_framework", "-m", *STATIC, "seed=1,2", f"hydra.sweep.dir={tmp_path}"]
    assert subprocess.run(args, capture_output=True, text=True).returncode == 0
    before = {p.name: (p / "episodes.jsonl").read_bytes() for p in tmp_path.iterdir() if p.name.isdigit()}
    (tmp_path / "1" / "episodes.jsonl").rename(tmp_path / "1" / "episodes.jsonl.partial")  # job 1 unfinished
    lines = (tmp_path / "1" / "episodes.jsonl.partial").read_text().splitlines(keepends=True)
    (tmp_path / "1" / "episodes.jsonl.partial").write_text(lines[0])
    again = subprocess.run(args, capture_output=True, text=True)
    assert again.returncode == 0, again.stderr
    assert "(2 finished earlier in this directory)" in again.stdout
    assert "(1 finished earlier in this directory)" in again.stdout
    after = {p.name: (p / "episodes.jsonl").read_bytes() for p in tmp_path.iterdir() if p.name.isdigit()}
    assert after["0"] == before["0"], "a finished job is not run again"
    assert after["1"].startswith(lines[0].encode()), "an unfinished job keeps its finished episodes"
    from overhang_framework.results import read_episodes, without_timing

    assert without_timing(read_episodes(tmp_path / "1" / "episodes.jsonl")) == \
        without_timing([json.loads(line) for line in before["1"].decode().splitlines()])


def test_episodes_spread_over_processes_equal_a_serial_run(tmp_path):
    from overhang_framework.results import read_episodes, without_timing

    common = [sys.executable, "-m", "overhang_framework", "predictor=ipe", "predictor.K=10", "repeats=2", *STATIC]
    serial = subprocess.run([*common, f"hydra.run.dir={tmp_path / 'serial'}"], capture_output=True, text=True)
    parallel = subprocess.run([*common, "jobs=2", f"hydra.run.dir={tmp_path / 'parallel'}"],
                              capture_output=True, text=True)
    assert serial.returncode == 0 and parallel.returncode == 0, parallel.stderr
    a = read_episodes(tmp_path / "serial" / "episodes.jsonl")
    b = read_episodes(tmp_path / "parallel" / "episodes.jsonl")
    assert len(a) == 4 and without_timing(a) == without_timing(b)
    # the workers' counters reach metrics.json: every placement asked the world's physics once
    placements = sum(len(e["steps"]) for e in a)
    for run in ("serial", "parallel"):
        cache = json.loads((tmp_path / run / "metrics.json").read_text())["world_stats"]["cache"]
        assert cache["hits"] + cache["misses"] == placements, (run, cache)


def test_stats_of_several_processes_merge_into_one():
    from overhang_framework.parallel import merge_stats

    a = {"cache": {"hits": 1, "misses": 3, "hit_rate": 0.25}, "physics": "tiered", "calls": 2}
    b = {"cache": {"hits": 3, "misses": 1, "hit_rate": 0.75}, "physics": "tiered", "calls": 5, "extra": 1}
    assert merge_stats([a, b]) == {"cache": {"hits": 4, "misses": 4, "hit_rate": 0.5}, "physics": "tiered",
                                   "calls": 7, "extra": 1}

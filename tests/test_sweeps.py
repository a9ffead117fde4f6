"""Multirun sweeps: a real ``-m`` run into a temporary sweep directory, locally and with joblib."""

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

"""``experiment=table2``: the paper's Table 2 from one command, and the table it prints."""

import csv
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from overhang_framework.config import compose_config
from overhang_framework.optimum import load_optima
from overhang_framework.report.table2 import model_name, render, task_sem


def test_the_experiment_sweeps_the_three_models_with_the_hybrid_predictor():
    for model, planner, depth in (("myopic", "myopic", None), ("lookahead_d2", "lookahead", 2),
                                  ("lookahead_d3", "lookahead", 3)):
        cfg = compose_config(["experiment=table2", f"model={model}"], return_hydra_config=True)
        assert cfg.predictor.name == "hybrid" and cfg.tasks.name == "paper20" and cfg.repeats == 40
        assert cfg.planner.name == planner and cfg.planner.get("depth") == depth
        assert str(cfg.hydra.mode).endswith("MULTIRUN")
        assert cfg.hydra.sweeper.params.model == "myopic,lookahead_d2,lookahead_d3"
    limited = compose_config(["experiment=table2", "condition=time_limited"], return_hydra_config=True)
    assert limited.condition.time_limit == 5.0
    assert "table2-time_limited" in limited.hydra.sweep.dir


def test_the_sem_is_across_tasks_not_runs():
    episodes = [{"task_id": t} for t in ("a", "a", "a", "b")]
    mean, sem, tasks = task_sem(episodes, [1.0, 1.0, 1.0, 3.0])
    assert mean == pytest.approx(1.5) and tasks == 2
    assert sem == pytest.approx(np.std([1.0, 3.0], ddof=1) / math.sqrt(2))  # task means 1 and 3


def test_rows_are_named_as_in_the_paper_and_printed_beside_its_values():
    assert model_name({"planner": {"name": "myopic"}}) == "Myopic"
    assert model_name({"planner": {"name": "lookahead", "depth": 3}}) == "Lookahead (D=3)"
    row = {"job": "2", "model": "Lookahead (D=3)", "status": "incomplete", "condition": "unconstrained",
           "episodes": 3, "expected": 800, "reward": 1.25, "sem": 0.5, "ratio": 0.6, "ratio_sem": 0.1,
           "decision_time": 1.5}
    text = render([row], Path("x"))
    line = next(l for l in text.splitlines() if l.startswith("| Lookahead (D=3)"))
    assert "1.180 ± 0.24" in line and "1.250 ± 0.500" in line and "3 of 800" in line
    assert "Not complete" in text and "2 (Lookahead (D=3): incomplete, 3 episodes)" in text


def test_a_bad_model_is_one_line_before_anything_runs(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "overhang_framework", "experiment=table2_quick", "model=deep",
                           f"hydra.sweep.dir={tmp_path / 'sweep'}"], capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "model" in proc.stderr and "lookahead_d3" in proc.stderr
    assert not (tmp_path / "sweep").exists()


@pytest.mark.slow
def test_the_quick_variant_runs_end_to_end(tmp_path):
    """The quick variant on one task, one run: every model runs and the table is printed and written."""
    proc = subprocess.run([sys.executable, "-m", "overhang_framework", "experiment=table2_quick",
                           "tasks.only=[paper03]", "repeats=1", "progress=false", f"hydra.sweep.dir={tmp_path}"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    with open(tmp_path / "results.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert sorted(r["model"] for r in rows) == ["lookahead_d2", "lookahead_d3", "myopic"]
    assert all(r["status"] == "complete" and r["episodes"] == "1" for r in rows)
    table = (tmp_path / "table2.md").read_text()
    optimum = next(r["optimum"] for r in load_optima().values() if r["task_id"] == "paper03")
    assert table in proc.stdout
    for name, paper in (("Myopic", "0.52 ± 0.12"), ("Lookahead (D=2)", "0.912 ± 0.10"),
                        ("Lookahead (D=3)", "1.180 ± 0.24")):
        line = next(l for l in table.splitlines() if l.startswith(f"| {name} |"))
        cells = [c.strip() for c in line.split("|")[1:-1]]
        assert cells[1] == paper
        reward = float(cells[2])
        row = next(r for r in rows if r["model"] == {"Myopic": "myopic", "Lookahead (D=2)": "lookahead_d2",
                                                       "Lookahead (D=3)": "lookahead_d3"}[name])
        assert reward == pytest.approx(float(row["reward_mean"]), abs=5e-4)
        assert float(cells[3]) == pytest.approx(reward / optimum, abs=5e-4)

"""Reports: report.md and figures from a sweep, a partial sweep, reproducible byte for byte."""

import json
import subprocess
import sys

import pytest

from overhang_framework.report.build import FIGURES, build

STATIC = ["world.physics=static", "tasks.only=[paper00,paper01]", "progress=false"]


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    proc = subprocess.run([sys.executable, "-m", "overhang_framework", "-m", *STATIC, "planner=myopic,lookahead",
                           f"hydra.sweep.dir={root}"], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    return root


def test_the_report_renders_tables_and_figures(sweep, tmp_path):
    path = build(sweep, out=tmp_path, task="paper01")
    text = path.read_text()
    assert "2 jobs: 2 complete." in text
    assert "veridical / myopic / unconstrained" in text and "veridical / lookahead D=2 / unconstrained" in text
    reward = json.loads((sweep / "1" / "metrics.json").read_text())["reward_mean"]
    assert f"{reward:.3f} ± " in text
    assert "Towers built for paper01" in text
    for name in FIGURES:
        assert (tmp_path / name).stat().st_size > 1000


def test_rerunning_the_report_writes_the_same_files(sweep, tmp_path):
    build(sweep, out=tmp_path / "a")
    build(sweep, out=tmp_path / "b")
    for name in ("report.md", *FIGURES):
        a, b = (tmp_path / "a" / name).read_bytes(), (tmp_path / "b" / name).read_bytes()
        assert a == b, name


def test_a_partial_sweep_says_what_is_missing(sweep, tmp_path):
    import shutil

    partial = tmp_path / "partial"
    shutil.copytree(sweep, partial)
    job = partial / "1"
    lines = (job / "episodes.jsonl").read_text().splitlines(keepends=True)
    (job / "episodes.jsonl").unlink()
    (job / "episodes.jsonl.partial").write_text(lines[0])
    metrics = json.loads((job / "metrics.json").read_text())
    metrics.update(complete=False, status="incomplete", episodes=1)
    (job / "metrics.json").write_text(json.dumps(metrics))
    (partial / "2" / ".hydra").mkdir(parents=True)
    (partial / "2" / ".hydra" / "overrides.yaml").write_text("- planner=mcts\n")
    text = build(partial).read_text()
    assert "3 jobs: 1 complete, 1 incomplete, 1 missing." in text
    assert "- `1` (veridical / lookahead D=2 / unconstrained): incomplete, 1 episodes finished" in text
    assert "| 1 | veridical / lookahead D=2 / unconstrained | 1 of 2 |" in text


def test_the_report_command_refuses_a_directory_without_runs(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.report", str(tmp_path)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip() == f"error: {tmp_path} holds no run (no run.json or .hydra/overrides.yaml below it)"


def test_reward_over_optimum_appears_when_optima_are_known(sweep, tmp_path, monkeypatch):
    import overhang_framework.optimum as optimum
    from overhang_framework.optimum import optimum_key_for

    config = json.loads((sweep / "0" / "run.json").read_text())["config"]
    rewards = {}
    for line in (sweep / "0" / "episodes.jsonl").read_text().splitlines():
        e = json.loads(line)
        rewards[optimum_key_for(e["sequence"], config["world"])] = {"optimum": e["reward"] * 2}
    out = tmp_path / "optima.json"
    out.write_text(json.dumps({"optima": rewards}))
    monkeypatch.setattr(optimum, "DATA_FILE", out)
    text = build(sweep, out=tmp_path).read_text()
    row = next(line for line in text.splitlines() if line.startswith("| 0 |"))
    assert row.rstrip().endswith("| 0.500 ± 0.000 |")

"""The Table 2 fidelity grid: point sets, the assessment against the paper, and a run that resumes."""

import json
import math

import pytest

from overhang_framework.report import fidelity
from overhang_framework.errors import ConfigError


def test_the_shipped_point_sets_load_and_map_to_overrides():
    points, meta = fidelity.load_points("grid")
    names = [p.name for p in points]
    assert names[0] == "paper" and fidelity.base_point(points).name == "paper"
    assert meta["x"] == "beta" and meta["lines"] == "cnn_bias"
    by = {p.name: p for p in points}
    assert by["softmax-2-bias-2"].overrides_for("lookahead_d3") == [
        "planner.choice=softmax", "planner.beta=2", "++predictor.late_params.bias=2"]
    # the myopic reward only exists for the myopic planner: the lookahead models share the base point's run
    assert by["myopic-gain"].overrides_for("lookahead_d2") == []
    assert not by["myopic-gain"].touches("lookahead_d2") and by["myopic-gain"].touches("myopic")
    out = fidelity.run_dir(points, by["myopic-gain"], "lookahead_d2", fidelity.Path("o"))
    assert out == fidelity.Path("o/paper/lookahead_d2")
    draws, _ = fidelity.load_points("draws")
    assert all(p.overrides_for("myopic")[0] == "tasks=draw" for p in draws)
    assert len({p.settings["tasks_seed"] for p in draws}) == len(draws) >= 10


@pytest.mark.parametrize("text, message", [
    ("points: {a: {sigma: 1}}", "point a of .*: unknown setting 'sigma'; allowed: choice, beta"),
    ("points: []", "needs a mapping 'points:"),
    ("points: {a: {overrides: x}}", "overrides must be a list"),
    ("points: [a", "is not valid YAML"),
])
def test_bad_point_sets_are_one_line_errors(tmp_path, text, message):
    path = tmp_path / "p.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message):
        fidelity.load_points(str(path))
    with pytest.raises(ConfigError, match="unknown point set 'nope'; shipped: draws, grid"):
        fidelity.load_points("nope")


def test_a_point_matches_only_within_every_sem_and_in_order():
    def levels(a, b, c):
        return {"myopic": {"reward": a}, "lookahead_d2": {"reward": b}, "lookahead_d3": {"reward": c}}

    good = fidelity.assess(levels(0.55, 0.95, 1.10))
    assert good["match"] and good["order"] and math.isclose(good["distance"], (0.95 - 0.912) / 0.10)  # the largest of the three
    too_high = fidelity.assess(levels(0.65, 0.95, 1.10))  # myopic 0.13 above the paper, its SEM is 0.12
    assert not too_high["match"] and not too_high["myopic_within"] and too_high["distance"] > 1
    unordered = fidelity.assess(levels(0.55, 1.00, 0.95))  # each within, but D3 below D2
    assert unordered["lookahead_d3_within"] and not unordered["order"] and not unordered["match"]
    missing = fidelity.assess(levels(0.55, math.nan, 1.1))
    assert not missing["match"] and math.isnan(missing["distance"])


def test_a_run_resumes_and_its_report_reads_the_episodes(tmp_path, capsys):
    points = tmp_path / "points.yaml"
    points.write_text("title: two points\npoints:\n  paper: {}\n  final: {myopic_reward: final}\n")
    out = tmp_path / "out"
    argv = ["run", str(points), "--out", str(out), "--repeats", "2", "--jobs", "1", "--models", "myopic",
            "--override", "tasks.only=[paper00,paper01]", "predictor=veridical", "world.physics=static"]
    assert fidelity.main(argv) == 0
    first = capsys.readouterr().out
    assert "[1/2] paper myopic" in first and "[2/2] final myopic" in first
    assert json.loads((out / "paper" / "myopic" / "wall.json").read_text())["seconds"] > 0
    assert fidelity.main(argv) == 0
    again = capsys.readouterr().out
    assert "paper myopic: done before" in again and "final myopic: done before" in again
    rows = {r["point"]: r for r in fidelity.table(fidelity.load_points(str(points))[0], out)}
    assert rows["paper"]["myopic_episodes"] == 4 and rows["final"]["myopic_episodes"] == 4
    # the myopic planner that sees only the final reward places the first blocks at random and does worse
    assert rows["final"]["myopic_reward"] < rows["paper"]["myopic_reward"]
    text = (out / "fidelity.md").read_text()
    assert text.startswith("# two points") and "| final | myopic_reward=final | " in text and "not run" in text  # D2 and D3 not run
    assert (out / "grid.csv").exists()
    assert fidelity.main(["report", str(out)]) == 0
    assert capsys.readouterr().out.startswith("# two points")


def test_the_figure_draws_the_points_that_vary_only_its_two_settings(tmp_path):
    points = [fidelity.Point("paper"), fidelity.Point("soft", {"choice": "softmax", "beta": 2}),
              fidelity.Point("biased", {"choice": "softmax", "beta": 2, "cnn_bias": 2}),
              fidelity.Point("sigma", {"ipe_sigma": 0.1})]
    rows = []
    for n, p in enumerate(points):
        row = {"point": p.name, **{k: p.value(k) for k in fidelity.SETTINGS}}
        for m in fidelity.MODELS:
            row[f"{m}_reward"], row[f"{m}_sem"] = 0.5 + 0.1 * n, 0.05
        rows.append(row)
    path = fidelity.figure(points, rows, "beta", "cnn_bias", tmp_path / "grid.png")
    assert path.stat().st_size > 10_000
    assert fidelity.figure(points[3:], rows[3:], "beta", "cnn_bias", tmp_path / "none.png") is None
    assert not (tmp_path / "none.png").exists()


def test_the_paper_levels_config_makes_every_model_choose_by_softmax():
    from overhang_framework.config import compose_config

    for model in fidelity.MODELS:
        cfg = compose_config(["experiment=table2_paper_levels", f"model={model}"], return_hydra_config=True)
        assert cfg.planner.choice == "softmax" and cfg.planner.beta == 2.2
        assert cfg.predictor.name == "hybrid" and cfg.tasks.name == "paper20" and cfg.repeats == 40


def _levels(tmp_path, models):
    """Run experiment=table2_paper_levels as it is configured (the paper's 40 runs per task, seed 0) and read
    each model's level. Myopic takes under a minute on two cores, depth 2 about 5 minutes, depth 3 about 55."""
    import subprocess
    import sys

    levels = {}
    for model in models:
        out = tmp_path / model
        proc = subprocess.run([sys.executable, "-m", "overhang_framework", "experiment=table2_paper_levels",
                               f"model={model}", "jobs=2", "seed=0", "progress=false",
                               f"hydra.sweep.dir={out}"], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr[-2000:]
        levels[model] = fidelity.level(out)
    return levels


@pytest.mark.slow
def test_the_paper_levels_config_puts_the_myopic_model_at_the_papers_level(tmp_path):
    (got,) = _levels(tmp_path, ["myopic"]).values()
    mean, sem = fidelity.PAPER["myopic"]
    assert got["episodes"] == 800 and abs(got["reward"] - mean) <= sem, got
    assert got["stood"] < 0.6  # most myopic towers fall, as the paper's level implies


@pytest.mark.slow
def test_the_paper_levels_config_puts_all_three_models_at_the_papers_levels_in_order(tmp_path):
    levels = _levels(tmp_path, list(fidelity.MODELS))
    verdict = fidelity.assess(levels)
    assert verdict["match"], {m: levels[m]["reward"] for m in fidelity.MODELS}

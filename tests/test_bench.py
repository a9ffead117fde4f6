"""The physics benchmark's smoke run ends with one JSON line holding every figure the docs quote."""

import json
import subprocess
import sys

import numpy as np
import pytest

KEYS = {"towers", "agreement_early_stop", "agreement_static", "agreement_static_critical",
        "speedup_early_stop", "speedup_static", "static_checks_per_s", "pool_speedup"}


@pytest.mark.slow
def test_quick_benchmark_prints_its_json_line(tmp_path):
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.bench", "--quick", "--quiet",
                           "--workers", "2", "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    figures = json.loads(proc.stdout.strip().splitlines()[-1])
    assert KEYS <= set(figures)
    assert figures["towers"] == 30
    for key in ("agreement_early_stop", "agreement_static", "agreement_static_critical"):
        assert 0.0 <= figures[key] <= 1.0
    assert figures["speedup_static"] > 1 and figures["static_checks_per_s"] > 0
    assert json.loads(out.read_text())["towers"] == 30


@pytest.mark.slow
def test_quick_agreement_benchmark_reports_families_stages_and_speed(tmp_path):
    out = tmp_path / "agreement.json"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.bench.agreement", "--quick", "--quiet",
                           "--workers", "2", "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    figures = json.loads(proc.stdout.strip().splitlines()[-1])
    fams = figures["families"]
    assert {"edge", "veridical candidates", "ipe candidates", "veridical placed"} <= set(fams)
    for row in fams.values():
        assert abs(sum(row["stages"].values()) - 1) < 1e-9
        assert row["tiered"]["agreement"] == 1.0
    assert figures["placed_tiered_equals_reference"] is True
    assert figures["speed"]["queries"] > 0 and figures["speed"]["tiered_per_s"] > 0
    assert json.loads(out.read_text())["seed"] == figures["seed"]


def test_edge_creep_is_reported_against_the_rest_speed():
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.bench.agreement", "--creep-only", "--quiet"],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    creep = json.loads(proc.stdout.strip().splitlines()[-1])["edge_creep"]
    assert len(creep) == 3
    for c in creep:
        assert c["passes_threshold_s"] is not None  # every exactly edge-balanced tower falls in the window
    assert creep[0]["speed_0.1_0.5s"][1] < creep[0]["rest_speed"] < creep[0]["speed_2s"]


@pytest.mark.parametrize("module", ["overhang_framework.bench.planners", "overhang_framework.bench.reference_search"])
def test_benchmarks_refuse_a_wrong_override_in_one_line(module):
    proc = subprocess.run([sys.executable, "-m", module, "world.resoluton=0.05", "--quiet"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        "error: unknown config key 'world.resoluton' (did you mean 'world.resolution'?); keys of world 'overhang': "
        "cache, name, physics, pybullet, resolution, static, tiered, verdict_file, workers"]


def test_the_lazy_benchmark_prints_each_way_and_the_same_scores(tmp_path, capsys):
    from overhang_framework.bench import lazy

    out = tmp_path / "lazy.json"
    assert lazy.main(["--states", "1", "--depths", "2", "--families", "cnn", "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    (row,) = figures["rows"]
    assert row["model"] == "cnn/D2" and row["max_score_difference"] < 1e-9
    assert row["towers"]["lazy"] <= row["towers"]["eager"] and row["towers"]["eager"] > 0
    assert "cnn/D2" in capsys.readouterr().out
    assert lazy.main(["--families", "mlp"]) == 2
    assert capsys.readouterr().err.strip() == "error: unknown family 'mlp'; allowed: cnn, hybrid, ipe"


def test_the_sigma_benchmark_counts_verdict_changes_along_each_draw():
    from overhang_framework.bench.sigma import _changes

    verdicts = np.array([[1, 1, 1, 1],    # stands at every sigma
                         [1, 1, 0, 0],    # one critical sigma
                         [0, 1, 1, 0],    # stands on an interval: two changes
                         [1, 0, 0, 1],    # stands, falls, stands again
                         [0, 0, 0, 0]], dtype=bool)
    flips, gaps = _changes(verdicts)
    assert flips.tolist() == [0, 1, 2, 2, 0]
    assert gaps.tolist() == [False, False, False, True, False]


def test_the_sigma_benchmark_prints_identical_verdicts_and_the_shares(tmp_path, capsys):
    from overhang_framework.bench import sigma

    out = tmp_path / "sigma.json"
    assert sigma.main(["--states", "1", "--placed", "1", "--K", "5", "--repeats", "1", "--step", "0.03",
                       "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["identical"] is True and figures["candidates"] > 0
    assert figures["draws"] == figures["candidates"] * 5
    assert sum(figures["changes"].values()) == pytest.approx(1.0)
    assert "one call is" in capsys.readouterr().out
    assert sigma.main(["--placed", "one"]) == 2


def test_the_mcts_settling_benchmark_plays_both_ways_and_finds_them_alike(tmp_path, capsys):
    from overhang_framework.bench import mcts_settle

    out = tmp_path / "settle.json"
    assert mcts_settle.main(["--tasks", "1", "--iterations", "4", "--out", str(out)]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    figures = json.loads(lines[-1])
    written = json.loads(out.read_text())  # the file keeps the figures (its floats rounded)
    assert written["reference_runs"] == figures["reference_runs"] and written["identical"] is True
    (row,) = figures["rows"]
    assert figures["identical"] and row["same"] and lines[1].split()[0] == row["task"]
    assert 0 <= row["lazy_reference"] <= row["eager_reference"]
    assert mcts_settle.main(["--tasks", "0"]) == 2
    assert "--tasks and --iterations must be whole numbers >= 1" in capsys.readouterr().err

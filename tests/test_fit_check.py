"""The posterior predictive check (python -m overhang_framework.fit.check): the generating model passes it,
a wrong model fails it, bad input is refused in one line, and a stopped check continues."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from overhang_framework.fit.check import coverage, interval, interval_rank, past_edge


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """Veridical myopic participants (beta 20, lapse 0.02, no motor noise), fitted with the veridical model
    and a noisy IPE (sigma 0.08)."""
    from search_fixtures import fixed_cohort

    root = tmp_path_factory.mktemp("check")
    fixed_cohort(root / "sim", {"depth": {"dist": "fixed", "value": 1}, "beta": {"dist": "fixed", "value": 20.0},
                                "lapse": {"dist": "fixed", "value": 0.02}, "sigma": None},
                 4, 6, "predictor=veridical", "cohort.motor.sd=0")
    proc = _fit(root)
    assert proc.returncode == 0, proc.stderr
    return root


def _fit(root: Path):
    return subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(root / "sim" / "log.jsonl"), "--out",
                           str(root / "fit"), "~models.cnn", "~models.hybrid", "models.ipe.K=20",
                           "models.ipe.sigma=[0.08]", "+models.veridical={predictor: veridical}", "depths=[1]",
                           "world.physics=static", f"cache={root / 'scores.sqlite'}", "progress=false",
                           "pooled=false"], capture_output=True, text=True, timeout=600)


def _check(root: Path, *args):
    return subprocess.run([sys.executable, "-m", "overhang_framework.fit.check", str(root / "fit"), "--cache",
                           str(root / "scores.sqlite"), "--no-progress", *args], capture_output=True, text=True,
                          timeout=900)


# 39 repeats of every trial under two models (50 s on a busy machine); the check's parts and refusals stay in the default suite
@pytest.mark.slow
def test_the_generating_model_passes_the_check_and_a_wrong_model_fails_it(fitted):
    proc = _check(fitted)
    assert proc.returncode == 0, proc.stderr
    people = pd.read_csv(fitted / "fit" / "check" / "participants.csv")
    assert set(people["model"].str.split(",").str[0]) == {"veridical/myopic"}
    assert len(people) == 4 * 7 and (people["replicas"] > 0).all()
    right = people["flagged"].mean()
    conditions = pd.read_csv(fitted / "fit" / "check" / "conditions.csv")
    assert right <= 0.15 and not conditions["flagged"].any(), people[people["flagged"]]
    assert "the median and 95% interval of the same mean" in (fitted / "fit" / "check" / "check.md").read_text()
    # the noisy IPE forced on everyone: it cannot build as stably as these participants did
    proc = _check(fitted, "--model", "ipe/myopic", "--out", str(fitted / "wrong"))
    assert proc.returncode == 0, proc.stderr
    wrong = pd.read_csv(fitted / "wrong" / "participants.csv")
    reward = wrong[wrong["statistic"] == "reward_per_trial"]
    assert reward["flagged"].all() and (reward["observed"] > reward["high"]).all()
    assert wrong["flagged"].mean() >= 2 * right + 0.1
    worse = pd.read_csv(fitted / "wrong" / "conditions.csv").set_index("statistic")
    assert worse.loc["stable_pct", "flagged"] and worse.loc["stable_pct", "observed"] > worse.loc["stable_pct", "high"]
    text = (fitted / "wrong" / "check.md").read_text()
    assert "the models miss something" in text and "reward per trial for 4 of 4 (4 above" in text
    assert (fitted / "wrong" / "check.png").stat().st_size > 10_000


@pytest.mark.slow
def test_a_stopped_check_continues_from_its_parts_and_other_settings_are_refused(fitted):
    out = fitted / "again"
    proc = _check(fitted, "--replicas", "3", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    parts = sorted((out / "parts").glob("*.json"))
    assert len(parts) == 4
    # three replicas' range holds one more replica with probability 2 / 4: every sentence says 50%, not 95%
    text = (out / "check.md").read_text()
    assert "50% interval of 3 replicas" in text and "the median and 50% interval of the same mean" in text
    assert "95%" not in text
    before = (out / "participants.csv").read_text()
    parts[0].unlink()  # as if stopped before its last participant
    kept = {p: p.stat().st_mtime_ns for p in parts[1:]}
    proc = _check(fitted, "--replicas", "3", "--out", str(out))
    assert proc.returncode == 0 and "1 checked now" in proc.stdout, proc.stdout + proc.stderr
    assert all(p.stat().st_mtime_ns == t for p, t in kept.items())
    assert (out / "participants.csv").read_text() == before  # the same replicas: seeded per participant
    proc = _check(fitted, "--replicas", "5", "--out", str(out))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "other settings" in proc.stderr
    # a refitted directory: the parts of the earlier fits are not reused
    fits = fitted / "fit" / "fits.csv"
    text = fits.read_text()
    try:
        fits.write_text(text.replace("veridical/myopic", "veridical/myopic", 1) + "\n")
        proc = _check(fitted, "--replicas", "3", "--out", str(out))
        assert proc.returncode == 2 and "holds a check of an earlier fits.csv" in proc.stderr, proc.stderr
    finally:
        fits.write_text(text)


@pytest.mark.parametrize("args, message", [
    (["--model", "cnn/D2"], "not a model of this fit; models: ipe/myopic, veridical/myopic"),
    (["--replicas", "0"], "--replicas must be a whole number >= 1"),
    (["--participant", "nobody"], "participant nobody is not in"),
])
def test_bad_input_is_refused_in_one_line(fitted, args, message):
    proc = _check(fitted, *args, "--out", str(fitted / "bad"))
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and message in proc.stderr, proc.stderr


def test_a_directory_without_a_fit_is_refused_in_one_line(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.fit.check", str(tmp_path)],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "has no fit.json" in proc.stderr


def test_the_interval_of_39_replicas_is_their_range_and_leaves_5_percent_out():
    values = list(np.arange(39.0))
    assert interval_rank(39) == 1 and interval(values) == (0.0, 38.0)
    assert interval_rank(79) == 2 and interval(list(np.arange(79.0))) == (1.0, 77.0)
    assert coverage(39) == pytest.approx(0.95) and coverage(19) == pytest.approx(0.90)
    assert coverage(79) == pytest.approx(0.95) and coverage(3) == pytest.approx(0.5)
    assert interval([1.0, float("nan"), 3.0]) == (1.0, 3.0) and np.isnan(interval([float("nan")])[0])
    # an exchangeable draw falls outside the range of 39 others with probability 2 / 40
    rng = np.random.default_rng(0)
    draws = rng.standard_normal((20_000, 40))
    outside = ((draws[:, 0] < draws[:, 1:].min(axis=1)) | (draws[:, 0] > draws[:, 1:].max(axis=1))).mean()
    assert outside == pytest.approx(0.05, abs=0.006)


def test_past_edge_measures_how_far_a_block_reaches_past_the_blocks_under_it():
    records = pd.DataFrame({"tower_before": [[[1.2, 0.0, 0]], [[1.2, 0.0, 0], [0.6, 0.5, 1]], [[1.2, 0.0, 0]]],
                            "width": [0.6, 1.2, 0.6], "x": [0.5, 0.3, None], "layer": [1, 2, None]})
    # 0.6 at 0.5 on a 1.2 at 0: right edge 0.8 against 0.6 -> 0.2; 1.2 at 0.3 on the 0.6 at 0.5: left edge
    # -0.3 against 0.2 -> 0.5 past on the left, right edge 0.9 against 0.8 -> 0.1: the larger, 0.5
    assert past_edge(records) == pytest.approx((0.2 + 0.5) / 2)

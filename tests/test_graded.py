"""The graded-budget study's predictions, trends and sample sizes (overhang_framework.graded)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from overhang_framework.studies import graded

LEVELS = {"limit_2_5s": 2.5, "time_limited": 5.0, "limit_10s": 10.0, "unconstrained": None}


def cohort(per_level: int, effect: float, seed: int = 0) -> pd.DataFrame:
    """Participants whose overhang grows by ``effect`` a level (sd 0.1), Γ and stable proportion flat."""
    rng = np.random.default_rng(seed)
    rows = []
    for k, level in enumerate(graded.levels_of(LEVELS)):
        for i in range(per_level):
            rows.append({"participant": f"{level}-{i:03d}", "condition": level,
                         "avg_overhang": 1.3 + effect * k + rng.normal(0, 0.1),
                         "gamma": 0.2 + rng.normal(0, 0.05), "stable_pct": 70 + rng.normal(0, 10),
                         "fitted_depth": float(rng.integers(1, 4))})
    return pd.DataFrame(rows)


def test_levels_are_ordered_by_the_time_they_leave():
    assert graded.levels_of(LEVELS) == ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"]


def test_a_planted_trend_is_found_the_right_way_and_none_is_found_where_there_is_none():
    levels = graded.levels_of(LEVELS)
    rho, p = graded.trend(cohort(30, 0.05), levels, "avg_overhang")
    assert rho > 0.25 and p < 0.001 and graded.holds(rho, p, +1) and not graded.holds(rho, p, -1)
    # no trend: the test's false-positive rate stays near alpha
    found = [graded.trend(cohort(15, 0.0, seed), levels, "avg_overhang", permutations=300, seed=seed)[1] < 0.05
             for seed in range(120)]
    assert np.mean(found) < 0.11


def test_the_answers_do_not_depend_on_the_order_of_the_rows():
    levels = graded.levels_of(LEVELS)
    df = cohort(12, 0.03)
    shuffled = df.sample(frac=1.0, random_state=3)
    pd.testing.assert_frame_equal(graded.predictions(df, levels), graded.predictions(shuffled, levels))
    pd.testing.assert_frame_equal(graded.trends(df, levels), graded.trends(shuffled, levels))


def test_each_levels_interval_holds_its_mean_and_narrows_with_more_participants():
    levels = graded.levels_of(LEVELS)
    small = graded.predictions(cohort(10, 0.05), levels)
    large = graded.predictions(cohort(200, 0.05), levels)
    at = large[large["measure"] == "overhang"].set_index("level")
    for k, level in enumerate(levels):
        truth = 1.3 + 0.05 * k
        assert at.loc[level, "ci_low"] < truth < at.loc[level, "ci_high"]
    width = lambda t: (t["ci_high"] - t["ci_low"]).mean()  # noqa: E731
    assert width(large) < width(small) / 3
    assert set(large["measure"]) == {"overhang", "stable", "gamma", "depth"}  # no fitted_risk column, no row


def test_power_grows_with_the_size_and_the_sample_size_is_the_first_to_reach_80_percent():
    levels = graded.levels_of(LEVELS)
    table = graded.power(cohort(40, 0.03), levels, [graded.MEASURES[0], graded.MEASURES[1]], sizes=(5, 20, 60),
                         resamples=60)
    over = table[table["measure"] == "overhang"].sort_values("per_level")["power"].to_numpy()
    assert over[0] < over[-1] and over[-1] >= 0.8
    sizes = graded.sample_sizes(table)
    first = table[(table["measure"] == "overhang") & (table["power"] >= 0.8)]["per_level"].min()
    assert sizes["overhang"] == first and sizes["stable"] is None  # no trend is expected of the stable proportion
    text = graded.report(graded.predictions(cohort(40, 0.03), levels), graded.trends(cohort(40, 0.03), levels),
                         table, levels, LEVELS, {lv: 40 for lv in levels})
    assert "**average overhang** grows with the time allowed, as expected" in text
    assert f"{first} participants per level give 80% power" in text
    # each power with its Monte Carlo error, from the redrawn studies it counts
    at = table[(table["measure"] == "overhang") & (table["per_level"] == first)].iloc[0]
    assert at["mc_error"] == pytest.approx(np.sqrt(at["power"] * (1 - at["power"]) / 60))
    assert f"({at['power']:.2f} ± {at['mc_error']:.2f}, the share of 60 redrawn studies" in text
    assert graded.SIZES[0] == 4 and graded.RESAMPLES >= 1000


def test_a_study_without_a_fit_claims_nothing_of_the_fitted_depth_and_says_where_a_flat_measure_differs():
    levels = graded.levels_of(LEVELS)
    df = cohort(30, 0.03)
    df["fitted_depth"] = np.nan
    df.loc[df["condition"] == "limit_2_5s", "stable_pct"] -= 15  # the shortest limit: more towers fall
    found = graded.trends(df, levels)
    assert "depth" not in set(found["measure"]) and {"overhang", "stable", "gamma"} <= set(found["measure"])
    table = graded.power(df, levels, [graded.MEASURES[0], graded.MEASURES[1]], sizes=(10, 20), resamples=20)
    text = graded.report(graded.predictions(df, levels), found, table, levels, LEVELS, {lv: 30 for lv in levels})
    assert "fitted depth" not in text
    assert "lowest at `limit_2_5s`" in text
    assert "for stable proportion (%), of which no trend is expected, the share in which none shows" in text


@pytest.mark.parametrize("values", [[np.nan] * 8, [1.0] * 8])
def test_a_measure_without_spread_has_no_trend(values):
    df = pd.DataFrame({"participant": [f"p{i}" for i in range(8)],
                       "condition": ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"] * 2,
                       "avg_overhang": values})
    rho, p = graded.trend(df, graded.levels_of(LEVELS), "avg_overhang")
    assert np.isnan(rho) and np.isnan(p) and not graded.holds(rho, p, +1)


@pytest.mark.slow
def test_the_graded_study_runs_end_to_end_at_a_small_size(tmp_path):
    """Two participants a level, two tasks each, static physics: every step, and every file of the report."""
    from overhang_framework.studies.command import main

    out = tmp_path / "graded"
    assert main(["graded_budgets", "--out", str(out), "--scale", "0.05", "--pool", "1", "--tasks", "2",
                 "--resamples", "5", "--replicas", "0", "--world", "world.physics=static", "--depths", "1",
                 "--no-progress", "--fit", "~models.ipe", "--fit", "~models.cnn",
                 "--fit", "+models.hybrid.risk=[0.0,0.9]"]) == 0
    pred = pd.read_csv(out / "predictions.csv")
    assert set(pred["level"]) == {"limit_2_5s", "time_limited", "limit_10s", "unconstrained"}
    assert {"overhang", "gamma", "lateral", "depth", "risk"} <= set(pred["measure"])
    people = pd.read_csv(out / "participants.csv")
    assert {"true_risk", "true_hand", "true_percept", "fitted_risk"} <= set(people.columns)
    assert (people.loc[people["condition"] == "time_limited", "true_risk"] == 0.9).all()
    text = (out / "study.md").read_text()
    assert text.startswith("# The graded-budget study") and "| fitted risk aversion |" in text
    assert text.splitlines()[2].startswith("**Nothing can be concluded from this study:** it has 2 participants")
    prereg = (out / "preregistration.md").read_text()  # the design writes its preregistration
    assert prereg.startswith("# Preregistration: the graded-budget study")
    assert "python -m overhang_framework.study graded_budgets --out" in prereg and "H-risk" in prereg
    assert len(pd.read_csv(out / "preregistration_effects.csv")) >= 3
    practice = pd.read_csv(out / "practice.csv")  # the design's participants did the served study's practice
    assert len(practice) == 8 and set(practice["condition"]) == set(pred["level"])
    assert "| level | screened out in the practice (simulated) | recruits for the planned size |" in prereg
    assert f"`limit_2_5s` | {int((~practice[practice['condition'] == 'limit_2_5s']['passed']).sum())} of 2" in prereg


def test_a_fitted_measure_that_only_some_best_models_have_says_over_how_many_it_is():
    """A risk-neutral family has no fitted risk: the level's mean is over those whose best model has the axis,
    and the report says how many of the level's participants that is."""
    levels = graded.levels_of(LEVELS)
    df = cohort(20, 0.03)
    df["fitted_risk"] = np.where(df["condition"] == "unconstrained", np.nan, 0.5)
    df.loc[df["participant"].isin(["limit_10s-000", "limit_10s-001"]), "fitted_risk"] = np.nan
    df.loc[df["participant"] == "unconstrained-000", "fitted_risk"] = 0.0
    pred = graded.predictions(df, levels)
    risk = pred[pred["measure"] == "risk"].set_index("level")
    assert risk["n"].to_dict() == {"limit_2_5s": 20, "time_limited": 20, "limit_10s": 18, "unconstrained": 1}
    assert (risk["participants"] == 20).all() and (pred["participants"] == 20).all()
    text = graded.report(pred, graded.trends(df, levels), pd.DataFrame(columns=["measure", "per_level", "power"]),
                         levels, LEVELS, {lv: 20 for lv in levels})
    row = next(line for line in text.splitlines() if line.startswith("| fitted risk aversion |"))
    assert "(n = 18 of 20)" in row and "(n = 1 of 20)" in row and row.count("(n = ") == 2
    assert "(n = " not in next(line for line in text.splitlines() if line.startswith("| average overhang |"))
    assert "fitted risk aversion over the k participants whose best model has the axis" in text


def test_the_sample_sizes_of_a_kept_power_table_are_printed_with_their_error(tmp_path, capsys):
    import json

    levels = graded.levels_of(LEVELS)
    table = graded.power(cohort(40, 0.03), levels, [graded.MEASURES[0]], sizes=(4, 20, 60), resamples=40)
    table.to_csv(tmp_path / "power.csv", index=False)
    assert graded.main([str(tmp_path / "power.csv")]) == 0
    out = json.loads(capsys.readouterr().out)["overhang"]
    assert out["per_level"] == graded.sample_sizes(table)["overhang"] and out["resamples"] == 40
    assert out["by_size"] == {f"n{n}": p for n, p in zip(table["per_level"], table["power"])}
    assert out["smallest_tried"] == 4 and out["mc_error"] == pytest.approx(
        np.sqrt(out["power"] * (1 - out["power"]) / 40))
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    assert graded.main([str(tmp_path / "bad.csv")]) == 2
    assert "no column 'measure'" in capsys.readouterr().err


def fit_rows(per_level: int, K_by_level: dict, seed: int = 0) -> pd.DataFrame:
    """A fit's fits.csv of a graded cohort: ``ipe/myopic`` with K and risk on grids and ``ipe/D2`` with its own
    K, the D2 model better for every third participant (so the winners' K are not the myopic model's)."""
    rng = np.random.default_rng(seed)
    rows = []
    for level, K in K_by_level.items():
        for i in range(per_level):
            pid = f"sim-{level}-{i:03d}"
            ll = -100.0 + rng.normal(0, 1)
            for model, depth, k, loglik in (("ipe/myopic", 1, K, ll), ("ipe/D2", 2, 77, ll + (3 if i % 3 == 0 else -3))):
                rows.append({"participant": pid, "condition": level, "model": model, "family": "ipe",
                             "depth": depth, "sigma": 0.02, "K": k, "risk": 0.45 if i % 2 else 0.0, "hand": 0.13,
                             "percept": 0.0, "beta": 5.0, "lapse": 0.02, "loglik": loglik, "k": 4, "n": 90,
                             "bic": -2 * loglik + 4 * np.log(90), "aic": -2 * loglik + 8, "unmapped": 0})
    return pd.DataFrame(rows)


def test_fitted_measures_come_from_one_model_fitted_to_everyone_not_from_each_winner():
    fits = fit_rows(6, {"limit_2_5s": 1, "time_limited": 10, "limit_10s": 50})
    people, models = graded.fitted(fits)
    assert models == {"K": "ipe/myopic", "risk": "ipe/myopic"}
    # every third participant's winner is ipe/D2 (K 77), yet the K compared is the myopic model's
    assert set(people["fitted_K"]) == {1.0, 10.0, 50.0}
    assert people.loc[people["participant"].str.endswith("-000"), "fitted_depth"].eq(2).all()
    assert people.groupby("condition")["fitted_K"].first().to_dict() == {"limit_10s": 50, "limit_2_5s": 1,
                                                                         "time_limited": 10}
    # a model tied with the best at another depth leaves the depth empty
    tied = fits.copy()
    first = tied["participant"] == "sim-limit_2_5s-001"
    tied.loc[first & (tied["model"] == "ipe/D2"), ["loglik", "bic", "aic"]] = \
        tied.loc[first & (tied["model"] == "ipe/myopic"), ["loglik", "bic", "aic"]].to_numpy()
    people, _ = graded.fitted(tied)
    assert np.isnan(people.set_index("participant").loc["sim-limit_2_5s-001", "fitted_depth"])


def test_a_fitted_measure_the_same_for_everyone_is_said_to_have_no_testable_trend_and_gets_no_power(tmp_path,
                                                                                                    capsys):
    fits = fit_rows(6, {"limit_2_5s": 1, "time_limited": 10, "limit_10s": 50})
    fits.loc[fits["model"] == "ipe/D2", "bic"] += 100  # every best model at depth 1
    fits.to_csv(tmp_path / "fits.csv", index=False)
    assert graded.main(["--fits", str(tmp_path / "fits.csv"), "--out", str(tmp_path / "o"), "--resamples", "3"]) == 0
    capsys.readouterr()
    text = (tmp_path / "o" / "graded.md").read_text()
    assert "- **fitted depth**: the same for every participant (1), so no trend can be tested." in text
    assert graded.main(["--fits", str(tmp_path / "fits.csv"), "--resamples", "0"]) == 0
    import json

    strict = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(f"{c} is not JSON"))
    assert strict["trends"]["depth"] == {"rho": None, "p": None, "holds": False}
    (tmp_path / "truth.csv").write_text("name,K\na,1\n")
    assert graded.main(["--fits", str(tmp_path / "fits.csv"), "--truth", str(tmp_path / "truth.csv")]) == 2
    assert "has no id (or participant) column" in capsys.readouterr().err
    assert "nan" not in text
    assert set(pd.read_csv(tmp_path / "o" / "power.csv")["measure"]) == {"risk", "K"}


def test_the_graded_study_of_a_fit_finds_a_K_that_grows_with_time_and_none_where_K_is_fixed(tmp_path, capsys):
    import json

    grows = fit_rows(8, {"limit_2_5s": 1, "time_limited": 10, "limit_10s": 50})
    flat = fit_rows(8, {"limit_2_5s": 10, "time_limited": 10, "limit_10s": 10})
    flat.loc[flat["participant"].str.endswith("-001"), "K"] = 50  # a spread, the same at every level
    truth = pd.DataFrame({"id": grows["participant"].unique()})
    truth["condition"] = truth["id"].str.split("-").str[1]
    truth["K"] = truth["condition"].map({"limit_2_5s": 1, "time_limited": 10, "limit_10s": 50})
    truth["depth"] = 1
    for name, fits in (("grows", grows), ("flat", flat)):
        fits.to_csv(tmp_path / f"{name}.csv", index=False)
    truth.to_csv(tmp_path / "truth.csv", index=False)
    assert graded.main(["--fits", str(tmp_path / "grows.csv"), "--out", str(tmp_path / "g"), "--resamples", "20",
                        "--truth", str(tmp_path / "truth.csv")]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found["levels"] == ["limit_2_5s", "time_limited", "limit_10s"]
    assert found["trends"]["K"]["holds"] and found["trends"]["K"]["rho"] > 0.8
    assert found["sample_sizes"]["K"] == 4  # a perfect trend: 4 a level, the grid's smallest
    assert found["means"]["K"] == {"limit_2_5s": 1.0, "time_limited": 10.0, "limit_10s": 50.0}
    assert found["counts"]["K"]["time_limited"] == {"K=10": 8} and found["counts"]["depth"]["limit_10s"] == {"depth=1": 5,
                                                                                                           "depth=2": 3}
    power = pd.read_csv(tmp_path / "g" / "power.csv")
    assert set(power["measure"]) == {"depth", "risk", "K"} and (power["resamples"] == 20).all()
    text = (tmp_path / "g" / "graded.md").read_text()
    assert "| fitted number of mental simulations (K) |" in text and "K of `ipe/myopic`" in text
    assert "| K | 1: 8 (8 of 8 fitted at it) | 10: 8 (8 of 8 fitted at it) | 50: 8 (8 of 8 fitted at it) |" in text
    assert graded.main(["--fits", str(tmp_path / "flat.csv"), "--out", str(tmp_path / "f"), "--resamples", "0"]) == 0
    found = json.loads(capsys.readouterr().out)
    assert not found["trends"]["K"]["holds"] and abs(found["trends"]["K"]["rho"]) < 0.2
    assert found["sample_sizes"] == {}
    # bad input: one line naming what is wrong and what is allowed
    assert graded.main(["--fits", str(tmp_path / "grows.csv"), "--out", str(tmp_path / "x"),
                        "--levels", "limit_2_5s,limit_3s"]) == 2
    err = capsys.readouterr().err
    assert "no participant of level 'limit_3s'" in err and "limit_10s" in err and len(err.splitlines()) == 1
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    assert graded.main(["--fits", str(tmp_path / "bad.csv"), "--out", str(tmp_path / "x")]) == 2
    assert "not a fit's fits.csv" in capsys.readouterr().err
    assert graded.main(["--fits", str(tmp_path / "grows.csv"), str(tmp_path / "g" / "power.csv")]) == 2
    assert "not both" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    # two separately simulated cohorts pooled: their participants told apart by the file's number
    assert graded.main(["--fits", str(tmp_path / "grows.csv"), "--fits", str(tmp_path / "flat.csv"),
                        "--truth", str(tmp_path / "truth.csv"), "--truth", str(tmp_path / "truth.csv"),
                        "--out", str(tmp_path / "both"), "--resamples", "0"]) == 0
    both = json.loads(capsys.readouterr().out)
    assert both["counts"]["K"]["limit_2_5s"] == {"K=1": 8, "K=10": 7, "K=50": 1}
    people = pd.read_csv(tmp_path / "both" / "participants.csv")
    assert len(people) == 48 and people["participant"].str.match(r"^[12]:sim-").all()
    assert "(their participants told apart by the file's number" in (tmp_path / "both" / "graded.md").read_text()
    assert graded.main(["--fits", str(tmp_path / "grows.csv"), "--fits", str(tmp_path / "flat.csv"),
                        "--truth", str(tmp_path / "truth.csv")]) == 2
    assert "give one --truth for each --fits (2)" in capsys.readouterr().err
    # without --out: the summary alone, nothing written
    assert graded.main(["--fits", str(tmp_path / "grows.csv"), "--resamples", "0"]) == 0
    assert json.loads(capsys.readouterr().out)["trends"]["K"]["holds"]


def test_a_table_kept_under_the_old_name_of_the_lateral_reach_reads_under_the_new_one(tmp_path, capsys):
    """The lateral reach was kept as "vertical" (what Fig. 3a calls its opposite); kept tables read as "lateral"."""
    kept = Path(__file__).resolve().parents[1] / "docs" / "figures" / "graded_budgets_power_behaviour.csv"
    assert "vertical" in set(pd.read_csv(kept)["measure"])
    table = graded.read_table(kept)
    assert "lateral" in set(table["measure"]) and "vertical" not in set(table["measure"])
    assert graded.main([str(kept)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert "lateral" in out and "vertical" not in out
    assert out["lateral"]["per_level"] == graded.sample_sizes(table)["lateral"]


def test_the_report_says_first_when_the_study_is_too_small_to_conclude_anything():
    levels = graded.levels_of(LEVELS)
    table = graded.power(cohort(40, 0.03), levels, [graded.MEASURES[0], graded.MEASURES[1]], sizes=(4, 10, 40),
                         resamples=40)
    need = graded.sample_sizes(table)["overhang"]
    assert need is not None and need > 4
    tiny = graded.verdict(table, dict.fromkeys(levels, 2), levels)
    assert tiny.startswith("**Nothing can be concluded from this study:** it has 2 participants in its level")
    assert "fewer than the 4 a level" in tiny
    short = graded.verdict(table, {**dict.fromkeys(levels, 40), "limit_10s": need - 1}, levels)
    assert short.startswith("**Nothing can be concluded") and f"{need - 1} participants in its level `limit_10s`" in short
    assert f"is {need} a level (the average overhang)" in short
    assert graded.verdict(table, dict.fromkeys(levels, need), levels) is None
    text = graded.report(graded.predictions(cohort(3, 0.03), levels), graded.trends(cohort(3, 0.03), levels), table,
                         levels, LEVELS, dict.fromkeys(levels, 3), study=dict.fromkeys(levels, 3))
    assert text.splitlines()[2].startswith("**Nothing can be concluded from this study:**")


def test_the_preregistration_states_the_hypotheses_the_size_and_the_power_across_effect_sizes():
    from overhang_framework.studies import prereg

    levels = graded.levels_of(LEVELS)
    pool = cohort(40, 0.04)
    halved = prereg.scaled(pool, levels, "avg_overhang", 0.5)
    means, half = (d.groupby("condition")["avg_overhang"].mean()[levels] for d in (pool, halved))
    np.testing.assert_allclose(half - half.mean(), 0.5 * (means - means.mean()))
    spread = lambda d: d.groupby("condition")["avg_overhang"].std()  # noqa: E731
    np.testing.assert_allclose(spread(halved), spread(pool))  # each participant keeps their distance from the mean
    table = graded.power(pool, levels, [m for m in graded.MEASURES if m.name in ("overhang", "gamma", "stable")],
                         sizes=(4, 8, 15, 30), resamples=60)
    effects = prereg.effect_power(pool, levels, 15, resamples=60, scales=(0.25, 1.0))
    at = effects[effects["measure"] == "overhang"].set_index("effect")["power"]
    assert at[0.25] < at[1.0]  # a smaller effect has less power at the planned size
    text = prereg.document(levels, LEVELS, table, effects, {lv: 30.0 for lv in levels}, dict.fromkeys(levels, 40),
                           False, {"commit": "abc123", "version": "0.1.0", "settings_hash": "f00d", "seed": 0,
                                   "resamples": 60}, "python -m overhang_framework.study graded_budgets --out d")
    assert "- **H-overhang** (primary): the average overhang grows (Spearman's ρ" in text
    assert "- **stable proportion (%)**: no trend" in text and "H-depth" not in text  # no fit: no fitted hypotheses
    assert "commit `abc123`" in text and "settings hash `f00d`" in text
    assert "| `limit_2_5s` | 2.5 s | about 30 min |" in text and "| `unconstrained` | none | about 30 min |" in text
    assert "python -m overhang_framework.study graded_budgets --log export.jsonl --out analysis" in text
    # Γ is flat in this cohort: no size gives every primary hypothesis its power, and the document says so
    assert prereg.planned_size(table) == (None, "gamma")
    assert "**No size of the grid gives every primary hypothesis 80% power** (the Γ has it at no size up to 30" in text
    flat_free = table[table["measure"] != "gamma"]
    n, which = prereg.planned_size(flat_free)
    assert which == "overhang" and n == graded.sample_sizes(flat_free)["overhang"]
    assert f"**{n} participants per level**" in prereg.document(levels, LEVELS, flat_free, effects, {}, {}, False,
                                                                 {"settings_hash": "f", "seed": 0, "resamples": 60},
                                                                 "c")

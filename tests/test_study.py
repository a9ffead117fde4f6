"""Planted and null studies (python -m overhang_framework.study): the findings' tests on participants whose
answer is known, power by redrawing participants, and both commands end to end at a small size."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from overhang_framework.studies.findings import FINDINGS, evaluate, power
from overhang_framework.studies.power import resample


def _people(effect: bool, n: int = 40, seed: int = 0) -> pd.DataFrame:
    """Participants built by hand: with ``effect``, every finding of the paper is there, strongly; without, none."""
    rng = np.random.default_rng(seed)
    lateral = np.random.default_rng(seed + 1000)  # its own draws: the other columns as before it was added
    rows = []
    for condition in ("time_limited", "unconstrained"):
        tl = condition == "time_limited"
        for i in range(n):
            shift = (-1 if tl else 0) if effect else 0
            hybrid = effect
            evidence = {"evidence_hybrid": -100.0 + (10 if hybrid else -10) + rng.normal(0, 1),
                        "evidence_ipe": -100.0 + rng.normal(0, 1), "evidence_cnn": -100.0 + rng.normal(0, 1)}
            rows.append({"participant": f"{condition}-{i}", "condition": condition,
                         "avg_overhang": 1.45 + 0.1 * shift + rng.normal(0, 0.05),
                         "stable_pct": 70 + rng.normal(0, 5), "gamma": 0.24 + 0.08 * shift + rng.normal(0, 0.05),
                         "abs_x_late": 0.5 + 0.06 * shift + lateral.normal(0, 0.03),
                         "ipe_vs_veridical": (0.2 if effect else -0.2) + rng.normal(0, 0.1),
                         "cnn_vs_veridical": (0.2 if effect else -0.2) + rng.normal(0, 0.1),
                         "cnn_lead": (0.2 if effect else 0.0) + rng.normal(0, 0.1),
                         "fitted_depth": (1 if tl else 2) if effect else int(rng.integers(1, 3)),
                         "best_family": "hybrid" if hybrid else "ipe",
                         "true_switch": 4, "fitted_switch": 4 + int(rng.integers(-1, 2)) if hybrid else np.nan,
                         **evidence})
    return pd.DataFrame(rows)


def test_every_finding_holds_where_it_was_built_in_and_none_where_it_was_not():
    planted = evaluate(_people(True), permutations=2000)
    assert all(planted[f.name]["holds"] for f in FINDINGS), {k: v["statistic"] for k, v in planted.items()}
    null = evaluate(_people(False, seed=1), permutations=2000)
    assert not any(null[f.name]["holds"] for f in FINDINGS if f.name != "stable")
    assert null["stable"]["holds"]  # the absence of a difference is found
    assert planted["hybrid"]["top"] == "hybrid" and null["hybrid"]["top"] != "hybrid"


def test_the_report_names_what_was_not_found_and_what_the_cohort_says_about_it():
    from pathlib import Path

    from overhang_framework.studies.findings import diagnostics
    from overhang_framework.studies.report import report
    from overhang_framework.studies.steps import Steps

    people = _people(True, n=20)
    people["true_depth"] = np.where(np.arange(len(people)) % 2, 1, 2)
    people.loc[people["condition"] == "time_limited", "gamma"] = 0.5  # the Γ effect turned round
    people["true_switch"] = np.where(np.arange(len(people)) % 4 == 0, 3, 4)
    people.loc[people["true_switch"] == 3, "best_family"] = "cnn"
    why = diagnostics(people)
    tl1 = people[(people["condition"] == "time_limited") & (people["true_depth"] == 1)]
    assert f"depth 1: {tl1['gamma'].mean():.3f} (time_limited, n = {len(tl1)})" in why["gamma"]
    assert why["hybrid"] == ("the hybrid is the best family for 0 of 10 planted with switch point 3, "
                             "30 of 30 planted with switch point 4")
    found = evaluate(people, permutations=500)
    assert not found["gamma"]["holds"]
    table = pd.DataFrame([{"finding": f.name, "text": f.text, **{k: found[f.name][k] for k in ("statistic", "p", "holds")},
                           "expected": True, "rate": 0.5 if f.name in ("gamma", "hybrid") else 1.0,
                           "size_for_power": "", "paper": f.paper} for f in FINDINGS])
    sizes = {"time_limited": 20, "unconstrained": 20}
    text = report("dual_transition", table, Steps(Path("/nonexistent")), sizes, sizes, None, 10, True, [1, 2], 1.0,
                  why=why)
    not_found = next(line for line in text.splitlines() if line.startswith("- **Not found:**"))
    assert not_found.startswith("- **Not found:** gamma (Γ lower under time pressure: ") and "p " in not_found
    below = next(line for line in text.splitlines() if line.startswith("- **Below 0.8:**"))
    assert why["gamma"] in below and why["hybrid"] in below
    null = report("null", table.assign(holds=False), Steps(Path("/nonexistent")), sizes, sizes, None, 10, False,
                  [1, 2], 1.0)
    assert "- **As a null study should:** yes; none of the 6 effects the null cohort lacks appears at α = .05." in null
    assert "- **Kept by the null cohort** (its participants judge with a noisy IPE): both approximate" in null
    assert "Not found" not in null
    # the null cohort keeps approximate physics: the baseline appearing is not a false positive, a crossover is
    kept = table.assign(holds=table["finding"].isin(["stable", "baseline", "crossover"]))
    people["true_beta"] = np.linspace(2, 30, len(people))
    people["cnn_lead"] = -people["true_beta"] / 100 + np.random.default_rng(0).normal(0, 0.01, len(people))
    why = diagnostics(people)
    assert why["crossover"].startswith("each participant's late-minus-early CNN lead goes with the planted "
                                       "β (Spearman ρ = -") and why["crossover"].endswith(", p < .001)")
    null = report("null", kept, Steps(Path("/nonexistent")), sizes, sizes, None, 10, False, [1, 2], 1.0, why=why)
    assert "- **As a null study should:** no; 1 of 6 effects the null cohort lacks appear at α = .05 (crossover)." in null
    above = next(line for line in null.splitlines() if line.startswith("- **Above α = .05:**"))
    assert "gamma (50%" in above and why["crossover"] in above and "baseline" not in above
    rates = next(line for line in null.splitlines() if line.startswith("- **False-positive rate**"))
    assert "baseline" not in rates and "crossover 100%" in rates


def test_power_redraws_studies_of_the_given_size_from_the_participants():
    from overhang_framework.studies.power import replaced

    people = _people(True, n=30)
    people["who"] = people["participant"]
    drawn = resample(people, {"time_limited": 5, "unconstrained": 7}, np.random.default_rng(0))
    assert drawn["condition"].value_counts().to_dict() == {"time_limited": 5, "unconstrained": 7}
    assert drawn["participant"].is_unique and drawn["who"].is_unique  # without replacement from a larger pool
    assert not replaced(people, {"time_limited": 29, "unconstrained": 29})
    assert replaced(people, {"time_limited": 30, "unconstrained": 29})  # all of a condition: a bootstrap
    bigger = resample(people, {"time_limited": 60, "unconstrained": 60}, np.random.default_rng(0))
    assert len(bigger) == 120 and not bigger["who"].is_unique
    strong = power(people, {"time_limited": 30, "unconstrained": 30}, 10, 0)
    assert strong["overhang"] == 1.0 and strong["hybrid"] == 1.0
    weak = power(people, {"time_limited": 2, "unconstrained": 2}, 10, 0)
    assert weak["overhang"] < strong["overhang"]


def test_a_fit_of_one_family_leaves_the_family_finding_untested_and_says_so():
    from pathlib import Path

    from overhang_framework.studies.report import report
    from overhang_framework.studies.steps import Steps

    people = _people(True, n=20).drop(columns=["evidence_ipe", "evidence_cnn"])
    found = evaluate(people, permutations=500)
    assert not found["hybrid"]["tested"] and not found["hybrid"]["holds"]
    assert found["hybrid"]["statistic"] == "not tested: the fit has only the hybrid family"
    assert found["depth"]["holds"] and found["switch"]["holds"]  # what one family can show is still tested
    rates = power(people, {"time_limited": 20, "unconstrained": 20}, 5, 0)
    assert np.isnan(rates["hybrid"]) and rates["overhang"] == 1.0
    table = pd.DataFrame([{"finding": f.name, "text": f.text, **{k: found[f.name][k] for k in ("statistic", "p", "holds")},
                           "tested": found[f.name].get("tested", True), "expected": True, "rate": rates[f.name],
                           "size_for_power": "", "paper": f.paper} for f in FINDINGS])
    sizes = {"time_limited": 20, "unconstrained": 20}
    text = report("paper_calibrated", table, Steps(Path("/nonexistent")), sizes, sizes, None, 5, True, [1, 2], 1.0)
    lines = text.splitlines()
    assert next(x for x in lines if x.startswith("- **Found:**")).startswith("- **Found:** 7 of 7 effects")
    assert "- **Not tested:** hybrid (not tested: the fit has only the hybrid family)." in lines
    assert not any(x.startswith("- **Not found:**") for x in lines)
    row = next(x for x in lines if x.startswith("| the hybrid family wins"))
    assert "| not tested |" in row


# the planted study (124 s on a busy machine) and the null one (20 s idle) run with the slow tests; the default
# suite has the study of runs simulated already below, and the fit and its check in tests/test_fit*.py
@pytest.mark.parametrize("study", [pytest.param("dual_transition", marks=pytest.mark.slow),
                                   pytest.param("null", marks=pytest.mark.slow)])
def test_a_study_runs_end_to_end_at_a_small_size(tmp_path, study):
    out = tmp_path / study
    args = [sys.executable, "-m", "overhang_framework.study", study, "--out", str(out), "--scale", "0.05",
            "--tasks", "2", "--depths", "1", "--resamples", "5", "--replicas", "2", "--no-progress",
            "--world", "world.physics=static", "--fit", "models.ipe.sigma=[0.03]", "--fit", "models.ipe.K=10",
            "--fit", "+models.hybrid.early_params={K: 10}", "--fit", "models.hybrid.switch=[3,5]"]
    args += ["--participants", "+predictor.early_params.K=10"] if study == "dual_transition" else \
        ["--participants", "predictor.K=10"]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    findings = pd.read_csv(out / "findings.csv")
    assert list(findings["finding"]) == [f.name for f in FINDINGS]
    people = pd.read_csv(out / "participants.csv")  # the study's 2 + 2 and as many more to redraw from
    assert len(people) == 8 and set(people["condition"]) == {"time_limited", "unconstrained"}
    assert "(2 time_limited, 2 unconstrained)" in (out / "study.md").read_text()
    truth = pd.read_csv(out / "sim" / "participants.csv")
    assert ("switch" in truth.columns) == (study == "dual_transition")
    text = (out / "study.md").read_text()
    assert ("(planted)" in text) == (study == "dual_transition") and "**Found:**" in text
    assert ("**Power**" if study == "dual_transition" else "**False-positive rate**") in text
    assert (out / "fit" / "check" / "check.md").exists() and (out / "analysis" / "report.md").exists()
    # the check replays the study's own participants, not the rest of the pool, and study.md says what it found
    own = set(people.sort_values("participant").groupby("condition").head(2)["participant"].astype(str))
    checked = set(pd.read_csv(out / "fit" / "check" / "participants.csv")["participant"].astype(str))
    assert checked and checked <= own and "**Predictive check**" in text  # (a participant whose trials all timed
    assert not checked & (set(people["participant"].astype(str)) - own)  # out is left out of the check)
    # run again, in more processes: every step is current, nothing is computed twice
    again = subprocess.run([*args, "--jobs", "2"], capture_output=True, text=True, timeout=900)
    assert again.returncode == 0 and "fitting the models" not in again.stderr, again.stderr[-2000:]
    assert "checking the fits" not in again.stderr


def test_an_unknown_study_or_a_bad_size_is_refused_in_one_line(tmp_path):
    for extra, message in ((["nope"], "unknown study 'nope'; studies: dual_transition, null"),
                           (["null", "--scale", "0"], "--scale must be a number > 0"),
                           (["null", "--participants", "cohort.nope=1"], "--participants: ")):
        proc = subprocess.run([sys.executable, "-m", "overhang_framework.study", *extra, "--out", str(tmp_path)],
                              capture_output=True, text=True)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and message in proc.stderr, proc.stderr


def test_a_study_of_participants_simulated_already_without_a_fit(tmp_path):
    """Each condition simulated on its own (as a paper-size run is, sitting by sitting), then taken as one study:
    the findings of the behaviour tested, those of the fit said to be untested, power a bootstrap; and what the
    study cannot take is refused in one line, before any work."""
    from commands import run_each

    runs, argvs = {}, []
    for condition, counts, seed in (("tl", "{time_limited: 3, unconstrained: 0}", 1),
                                    ("un", "{time_limited: 0, unconstrained: 3}", 0)):
        runs[condition] = tmp_path / f"sim_{condition}"
        argvs.append([sys.executable, "-m", "overhang_framework.participants", "cohort=null_effect",
                      "predictor=ipe", "predictor.K=10", f"cohort.participants={counts}", "cohort.n_tasks=2",
                      f"seed={seed}", "world.physics=static", "progress=false", f"hydra.run.dir={runs[condition]}"])
    for proc in run_each(argvs, timeout=900):  # each condition simulated on its own, the two at once
        assert proc.returncode == 0, proc.stderr[-2000:]
    out = tmp_path / "study"
    base = [sys.executable, "-m", "overhang_framework.study", "null", "--out", str(out), "--no-progress"]
    args = [*base, "--sim", str(runs["tl"]), "--sim", str(runs["un"]), "--no-fit", "--resamples", "5",
            "--world", "world.physics=static"]
    proc = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "taking 6 participants (3 time_limited, 3 unconstrained) from 2 simulations" in proc.stderr
    findings = pd.read_csv(out / "findings.csv").set_index("finding")
    assert list(findings.index) == [f.name for f in FINDINGS]
    assert set(findings.index[~findings["tested"]]) == {"depth", "hybrid", "switch"}
    assert findings.loc["vertical", "tested"] and np.isfinite(findings.loc["vertical", "p"])
    people = pd.read_csv(out / "participants.csv")
    assert len(people) == 6 and people["abs_x_late"].notna().all() and people["fitted_depth"].isna().all()
    text = (out / "study.md").read_text()
    assert "2 tasks each, no fit;" in text
    assert "with replacement from the study's own participants" in text and not (out / "fit").exists()
    log = (out / "sim" / "log.jsonl").read_text()
    assert log == (runs["tl"] / "log.jsonl").read_text() + (runs["un"] / "log.jsonl").read_text()
    before = (out / "findings.csv").read_bytes()
    again = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0 and (out / "findings.csv").read_bytes() == before  # the same study, the same answer
    refusals = ((["--sim", str(runs["tl"]), "--sim", str(runs["tl"])], "is in"),
                (["--sim", str(runs["tl"])], "--sim: no unconstrained participants"),
                (["--sim", str(tmp_path / "nowhere")], "no finished simulation there"),
                (["--sim", str(runs["tl"]), "--sim", str(runs["un"]), "--scale", "0.5"],
                 "--sim takes participants already simulated"),
                (["--sim", str(runs["tl"]), "--sim", str(runs["un"]), "--world", "world.physics=tiered"],
                 "simulated under world.physics=static"))
    argvs = [[*base, *extra, "--no-fit"] + ([] if "--world" in extra else ["--world", "world.physics=static"])
             for extra, _ in refusals]
    argvs.append([*base[:3], "paper_people", *base[4:], "--sim", str(runs["tl"]), "--sim", str(runs["un"]),
                  "--no-fit", "--world", "world.physics=static"])
    *procs, other = run_each(argvs)
    for (_, message), proc in zip(refusals, procs):
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and message in proc.stderr, proc.stderr
    assert other.returncode == 2 and "a simulation of cohort 'null_effect', not this study's 'paper_people'" \
        in other.stderr, other.stderr


def _fake_run(where, cohort_words, conditions):
    """A finished participants run directory as --sim reads it: run.json's config composed from
    ``cohort_words``, a participant table with ``conditions`` ({condition: code}) and a log line each."""
    import json

    from omegaconf import OmegaConf

    from overhang_framework.behaviour.simulation import CONFIG_NAME
    from overhang_framework.studies.run import _compose

    from overhang_framework.results import readable

    config = OmegaConf.to_container(_compose(cohort_words, CONFIG_NAME, "--participants"), resolve=True)
    where.mkdir(parents=True)
    (where / "run.json").write_text(json.dumps({"config": readable(config)}))  # as a run keeps it (numbers rounded)
    ids = [f"sim-{code}-001" for code in conditions.values()]
    pd.DataFrame({"id": ids, "index": range(len(ids)), "condition": list(conditions)}).to_csv(
        where / "participants.csv", index=False)
    (where / "log.jsonl").write_text("".join(f'{{"participant": "{i}"}}\n' for i in ids))
    return config


def test_a_graded_study_takes_paper_people_runs_for_the_levels_whose_people_they_are(tmp_path):
    """The graded cohort's 5 s and no-limit levels are paper_people's two conditions (the two files must not
    drift apart), so a graded study takes paper_people's runs there; other people are refused, in one line
    that names what differs."""
    from omegaconf import OmegaConf

    from overhang_framework.config import compose_config
    from overhang_framework.errors import ConfigError
    from overhang_framework.behaviour.simulation import CONFIG_NAME
    from overhang_framework.studies.gather import _differences, gather, population

    graded = OmegaConf.to_container(compose_config(["cohort=graded_budgets"], config_name=CONFIG_NAME), resolve=True)
    people = OmegaConf.to_container(compose_config(["cohort=paper_people"], config_name=CONFIG_NAME), resolve=True)
    for level in ("time_limited", "unconstrained"):
        assert _differences(population(people, level), population(graded, level)) == []
    assert "parameters.risk.value" in _differences(population(people, "time_limited"), population(graded, "limit_10s"))

    levels = ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"]
    new = _fake_run(tmp_path / "new", ["cohort=graded_budgets", "seed=10"],
                    {"limit_2_5s": "limit_2_5s", "limit_10s": "limit_10s"})
    _fake_run(tmp_path / "pp", ["cohort=paper_people"], {"time_limited": "tl", "unconstrained": "un"})
    sizes = gather([tmp_path / "new", tmp_path / "pp"], tmp_path / "sim", "graded_budgets", levels,
                   "tiered", graded)
    assert sizes == dict.fromkeys(levels, 1)
    assert len(pd.read_csv(tmp_path / "sim" / "participants.csv")) == 4
    assert new["cohort"]["name"] == "graded_budgets"

    _fake_run(tmp_path / "bolder", ["cohort=paper_people", "cohort.by_condition.time_limited.parameters.risk.value=0.5",
                                    "seed=2"],
              {"time_limited": "tl"})
    with pytest.raises(ConfigError, match=r"a simulation of cohort 'paper_people', not this study's 'graded_budgets'; "
                                          r"its time_limited participants are other people \(they differ in "
                                          r"parameters.risk.value\)"):
        gather([tmp_path / "new", tmp_path / "bolder"], tmp_path / "sim2", "graded_budgets", levels, "tiered", graded)
    _fake_run(tmp_path / "null", ["cohort=null_effect"], {"time_limited": "tl"})
    with pytest.raises(ConfigError, match="its time_limited participants are other people"):
        gather([tmp_path / "null"], tmp_path / "sim3", "graded_budgets", levels, "tiered", graded)
    _fake_run(tmp_path / "fewer", ["cohort=paper_people", "cohort.n_tasks=5", "seed=3"], {"time_limited": "tl"})
    with pytest.raises(ConfigError, match=r"they differ in n_tasks\)"):
        gather([tmp_path / "new", tmp_path / "fewer"], tmp_path / "sim5", "graded_budgets", levels, "tiered", graded)
    # the same seed draws the same people: the 2.5 s level at seed 0 is paper_people's first time-limited ones
    _fake_run(tmp_path / "same", ["cohort=graded_budgets", "seed=0"], {"limit_2_5s": "limit_2_5s"})
    with pytest.raises(ConfigError, match=r"draw from the same random streams \(seed 0\) as .*pp's.*another seed="):
        gather([tmp_path / "pp", tmp_path / "same"], tmp_path / "sim6", "graded_budgets", levels, "tiered", graded)
    _fake_run(tmp_path / "other", ["cohort=dual_transition"], {"switching": "sw"})
    with pytest.raises(ConfigError, match="its switching participants are in none of the study's conditions"):
        gather([tmp_path / "other"], tmp_path / "sim4", "graded_budgets", levels, "tiered", graded)


def _people_like(sim, per_condition, seed):
    """A small null_effect cohort simulated into ``sim`` (static physics, two tasks each), whose log stands for an
    export of people."""
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.participants", "cohort=null_effect",
                           "predictor=ipe", "predictor.K=10",
                           f"cohort.participants={{time_limited: {per_condition}, unconstrained: {per_condition}}}",
                           "cohort.n_tasks=2", f"seed={seed}", "world.physics=static", "progress=false",
                           f"hydra.run.dir={sim}"], capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return sim


def test_a_graded_study_of_peoples_log_is_analysed_and_says_first_what_its_size_cannot_support(tmp_path):
    """``study graded_budgets --log``: an export of people, analysed as a simulation's participants are (Table 1, Γ,
    the flows per level, the trends, power by a bootstrap of them), its report opening with what its size cannot
    support; a log of a condition the study lacks, or --log with --sim, refused in one line."""
    from overhang_framework.behaviour.log import read_log, write_log

    sim = _people_like(tmp_path / "sim", 4, seed=3)
    df = read_log(sim / "log.jsonl")
    levels = ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"]
    ids = sorted(df["participant"].unique())
    df["condition"] = df["participant"].map({p: levels[i % 4] for i, p in enumerate(ids)})  # as an export has them
    write_log(df, tmp_path / "export.jsonl")
    out = tmp_path / "study"
    base = [sys.executable, "-m", "overhang_framework.study", "graded_budgets", "--out", str(out), "--no-progress",
            "--world", "world.physics=static"]
    proc = subprocess.run([*base, "--log", str(tmp_path / "export.jsonl"), "--no-fit", "--resamples", "5"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "taking 8 people (2 limit_2_5s, 2 time_limited, 2 limit_10s, 2 unconstrained) from 1 log" in proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == "# The graded-budget study: what people did"
    assert lines[2].startswith("**Nothing can be concluded from this study:** it has 2 participants in its level")
    assert "2 people" in proc.stdout and "simulated" not in proc.stdout
    people = pd.read_csv(out / "participants.csv")
    assert len(people) == 8 and sorted(set(people["condition"])) == sorted(levels)
    assert not [c for c in people.columns if c.startswith("true_")] and people["avg_overhang"].notna().all()
    assert (out / "people" / "log.jsonl").exists() and not (out / "sim").exists()
    trends = pd.read_csv(out / "trends.csv")
    assert {"overhang", "gamma", "lateral"} <= set(trends["measure"])
    # two a level: no bootstrap of them stands for a study's power, so none is computed, and the report says why
    assert "(power not estimated: a bootstrap of fewer than 4 people a level says nothing of a larger study)" in \
        (out / "study.md").read_text() and pd.read_csv(out / "power.csv").empty
    text = (out / "study.md").read_text()
    assert "these people do not show it" in text or "these people show it" in text
    df.loc[df["participant"] == ids[0], "condition"] = "limit_1s"
    write_log(df, tmp_path / "other.jsonl")
    for extra, words in ((["--log", str(tmp_path / "other.jsonl")], "--log: participants in condition 'limit_1s', "
                          "which the study graded_budgets does not have (its conditions: limit_2_5s, time_limited, "
                          "limit_10s, unconstrained)"),
                         (["--log", str(tmp_path / "export.jsonl"), "--sim", str(sim)],
                          "--log takes people's data and --sim simulated participants; give one of them")):
        proc = subprocess.run([*base[:5], str(tmp_path / "refused"), *extra], capture_output=True, text=True)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and words in proc.stderr, proc.stderr


def test_a_two_condition_study_of_peoples_log_reports_people_and_says_first_what_its_size_cannot_support(tmp_path):
    """``study paper_people --log``: the report is of people (no word of simulated participants), the paper's
    findings are what it tests, and with fewer people a condition than the study is designed for its first sentence
    says nothing can be concluded."""
    from overhang_framework.studies.report import shortfall

    sim = _people_like(tmp_path / "sim", 3, seed=5)
    out = tmp_path / "study"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.study", "paper_people", "--out", str(out),
                           "--no-progress", "--world", "world.physics=static", "--log", str(sim / "log.jsonl"),
                           "--resamples", "5", "--replicas", "0", "--depths", "1", "--fit", "~models.cnn",
                           "--fit", "~models.hybrid", "--fit", "models.ipe.K=5", "--fit", "models.ipe.sigma=[0.02]"],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert lines[0] == "# Study: paper_people: what people did"
    assert lines[2].startswith("**Nothing can be concluded from this study:** it has 3 participants in its condition "
                               "`time_limited`, fewer than the 43 the study is designed for"), lines[:4]
    assert "6 people (3 time_limited, 3 unconstrained)" in proc.stdout and "the paper predicts" in proc.stdout
    text = (out / "study.md").read_text()
    assert "simulated" not in text and "`people/`" in text and "`sim/`" not in text
    # people have no truth: their table is not a participants.csv beside the log, which the fit would read as one
    assert (out / "people" / "people.csv").is_file() and not (out / "people" / "participants.csv").exists()
    fits = pd.read_csv(out / "fit" / "fits.csv")
    fitted = {p for p in fits["participant"] if not p.startswith("pooled:")}  # and a pooled fit a condition
    assert fitted == set(pd.read_csv(out / "participants.csv")["participant"])
    assert not [c for c in pd.read_csv(out / "participants.csv").columns if c.startswith("true_")]
    # the sentence names the condition furthest below its plan, and none when every condition has its size
    assert "`time_limited`" in shortfall({"time_limited": 10, "unconstrained": 30}, {"time_limited": 43,
                                                                                    "unconstrained": 38})
    assert shortfall({"time_limited": 43, "unconstrained": 40}, {"time_limited": 43, "unconstrained": 38}) is None


def test_a_pilot_s_screened_out_participants_are_left_out_of_a_study_that_takes_its_folder(tmp_path):
    """A pilot's folder (``participants.csv`` with ``screened_out``) given to ``--sim``: those the practice screened
    out did no main trial and are no level's members; their number a condition is said."""
    from omegaconf import OmegaConf

    from overhang_framework.behaviour.simulation import CONFIG_NAME
    from overhang_framework.config import compose_config
    from overhang_framework.studies.gather import gather

    graded = OmegaConf.to_container(compose_config(["cohort=graded_budgets"], config_name=CONFIG_NAME), resolve=True)
    levels = ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"]
    where = tmp_path / "pilot"
    _fake_run(where, ["cohort=graded_budgets", "seed=7"], {lv: lv for lv in levels})
    table = pd.read_csv(where / "participants.csv")
    extra = table.assign(id=table["id"].str.replace("-001", "-002"), index=table["index"] + 4)
    both = pd.concat([table, extra], ignore_index=True)
    both["screened_out"] = [False, True, False, False, False, False, False, True]  # as the pilot writes it
    both.to_csv(where / "participants.csv", index=False)
    screened: dict = {}
    sizes = gather([where], tmp_path / "sim", "graded_budgets", levels, "tiered", graded, screened)
    assert sizes == {"limit_2_5s": 2, "time_limited": 1, "limit_10s": 2, "unconstrained": 1}
    assert screened == {"time_limited": 1, "unconstrained": 1}
    kept = pd.read_csv(tmp_path / "sim" / "participants.csv")
    assert len(kept) == 6 and not kept["screened_out"].any()

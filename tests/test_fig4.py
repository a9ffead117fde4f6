"""Fig. 4 (physical prediction by construction stage) on studies whose answer is known by construction.

The paper's two claims: both approximate models (the IPE, the CNN) fit people's executed placements
better than the veridical physics, and the CNN overtakes the IPE as the tower grows (the IPE ahead
early, the CNN later). The simulated studies here are built from the real predictors' answers on the
static physics, so that the truth is known before the analysis runs:

* every placement is either *neutral* (it stands, and the veridical physics, the IPE and the CNN all
  give it p >= 1 - ε, so their log-likelihoods are equal) or *decisive* (it falls, the IPE and the CNN
  both give it p >= 0.05, so both beat the veridical log ε on it, and one of them by at least 0.5 nats);
* in the ``crossover`` group every participant makes an IPE-favoured decisive placement at 3 blocks
  and CNN-favoured ones at 5 and 6 blocks, the rest neutral: LL_ipe − LL_cnn is above 0 at 3 blocks
  for every participant, below 0 at 5 and 6, and exactly 0 at 2 and 4 blocks;
* in the ``no_effect`` group half the participants make an IPE-favoured and half a CNN-favoured
  decisive placement at 5 blocks, and the other way round at 6 blocks, of nearly equal size: the
  stage means are not 0 and change sign (5 blocks above, 6 below), yet no stage has an effect.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from overhang_framework.analyze import main
from overhang_framework.behaviour import analysis, prediction
from overhang_framework.behaviour.log import write_log
from overhang_framework.geometry import Geometry, overhang
from overhang_framework.interfaces import Task

# The analysis and the pool use the same predictors: the static world, an IPE with 20 simulations.
WORLD = ["world.physics=static", "predictor.K=20"]
EPS = 1e-3
PATHS = 14          # block sequences (tasks) whose states give the candidate placements
PARTICIPANTS = 8    # per group
DECISIVE = 0.5      # nats: the least |LL_ipe − LL_cnn| of a decisive placement


def ll(p):
    return np.log(np.clip(p, EPS, 1 - EPS))


def legal_prefix_action(world, state, rng):
    """A near-centred placement on the top block (x within 0.1 of its centre)."""
    top = state.geometry.blocks[-1]
    aim = top.x + rng.choice([-0.1, 0.0, 0.0, 0.1])
    above = [a for a in world.legal_actions(state) if a.layer == top.layer + 1]
    return min(above, key=lambda a: (abs(a.x - aim), abs(a.x - top.x)))


@pytest.fixture(scope="module")
def pool():
    """Every state along near-centred towers of ``PATHS`` random sequences (the prefixes), with each
    predictor's answer for the prefix placement and, at 3, 5 and 6 blocks, for every legal placement."""
    world = analysis.build_world(["world.physics=static"])
    predictors = prediction.build_predictors(["veridical", "ipe", "cnn"], world, WORLD)
    rng = np.random.default_rng(5)
    rows = []
    for path in range(PATHS):
        sequence = [float(w) for w in rng.choice([0.6, 1.2, 1.8], 6)]
        state = world.initial_state(Task(f"path{path}", tuple(sequence)))
        for step in range(1, len(sequence)):
            before = [[b.width, b.x, b.layer] for b in state.geometry.blocks]
            chosen = legal_prefix_action(world, state, rng)
            wanted = world.legal_actions(state) if step + 1 in (3, 5, 6) else [chosen]
            for a in wanted:
                rows.append({"path": path, "sequence": sequence, "step": step, "n_blocks": step + 1,
                             "tower_before": before, "x": a.x, "layer": a.layer, "prefix": a == chosen})
            state = world.step(state, chosen)
    df = pd.DataFrame(rows)
    for name, p in prediction.probabilities(df, predictors, 0).items():
        df[name] = p
    df["d"] = ll(df["ipe"]) - ll(df["cnn"])
    df["neutral"] = (df["veridical"] == 1) & (df["ipe"] >= 1 - EPS) & (df["cnn"] >= 1 - EPS)
    df["decisive"] = (df["veridical"] == 0) & (df["ipe"] >= 0.05) & (df["cnn"] >= 0.05) & (df["d"].abs() >= DECISIVE)
    # a path's placements up to a stage can be used only while its prefix is neutral
    prefix = df[df["prefix"]].sort_values("step")
    neutral_to = {path: (int(g["n_blocks"][~g["neutral"]].min()) - 1 if (~g["neutral"]).any() else 6)
                  for path, g in prefix.groupby("path")}
    df["usable"] = [n - 1 <= neutral_to[path] for path, n in zip(df["path"], df["n_blocks"])]
    return df


def decisive(pool, n, sign):
    """Usable decisive placements at ``n`` blocks favouring the IPE (``sign`` +1) or the CNN (−1), largest first."""
    at = pool[pool["usable"] & pool["decisive"] & (pool["n_blocks"] == n) & (np.sign(pool["d"]) == sign)]
    assert len(at), f"no decisive placement at {n} blocks favouring the {'IPE' if sign > 0 else 'CNN'} in the pool"
    return at.sort_values("d", key=abs, ascending=False)


def trial_records(pool, participant, condition, number, final):
    """One trial: the neutral prefix of ``final``'s path up to its state, then ``final``."""
    path, n = final["path"], final["n_blocks"]
    steps = pool[(pool["path"] == path) & pool["prefix"] & (pool["n_blocks"] < n)].sort_values("step")
    placed = [(r["x"], r["layer"], True) for _, r in steps.iterrows()]
    placed.append((final["x"], final["layer"], bool(final["veridical"] == 1)))
    sequence = final["sequence"]
    tower = [[sequence[0], 0.0, 0]]
    records = []
    for k, (x, layer, stands) in enumerate(placed, 1):
        after = tower + [[sequence[k], float(x), int(layer)]]
        height = overhang(Geometry.from_tuples(after))
        ends = k == len(placed)
        assert stands or ends
        records.append({"log_version": 1, "participant": participant, "condition": condition,
                        "task_id": f"path{path}", "sequence": list(sequence), "trial": number, "step": k,
                        "width": sequence[k], "x": float(x), "layer": int(layer),
                        "tower_before": [list(b) for b in tower], "stable": stands, "overhang": height,
                        "reward": (height if stands else 0.0) if ends else None, "decision_time": 1.0,
                        "timed_out": False, "source": "simulated"})
        tower = after
    assert not stands or len(placed) == len(sequence) - 1, "a standing decisive placement must be the last block"
    return records


def distinct_paths(*choices):
    return len({c["path"] for c in choices}) == len(choices)


def crossover_study(pool):
    """Each participant: an IPE-favoured fall at 3 blocks, CNN-favoured falls at 5 and 6, on three tasks."""
    early, five, six = decisive(pool, 3, 1), decisive(pool, 5, -1), decisive(pool, 6, -1)
    combos = [(a, b, c) for _, a in early.iterrows() for _, b in five.iterrows() for _, c in six.iterrows()
              if distinct_paths(a, b, c)]
    assert combos, "no three decisive placements on three different tasks"
    records = []
    for i in range(PARTICIPANTS):
        for t, final in enumerate(combos[(i * 7) % len(combos)], 1):
            records += trial_records(pool, f"x{i}", "crossover", t, final)
    return records


def balanced_pair(pool, n, sign):
    """An IPE-favoured and a CNN-favoured decisive placement at ``n`` blocks whose differences nearly cancel,
    their sum of sign ``sign`` and about a quarter of the smaller one's size (a visible wobble of the stage
    mean, a quarter of the participants' spread)."""
    pairs = [(abs(u["d"] + v["d"]) / min(abs(u["d"]), abs(v["d"])), u, v)
             for _, u in decisive(pool, n, 1).iterrows() for _, v in decisive(pool, n, -1).iterrows()
             if np.sign(u["d"] + v["d"]) == sign]
    assert pairs, f"no IPE-favoured and CNN-favoured pair at {n} blocks with a sum of sign {sign}"
    best = min(pairs, key=lambda t: abs(t[0] - 0.25))
    assert best[0] <= 0.3, f"the closest pair at {n} blocks differs by {best[0]:.2f} of its size"
    return best[1], best[2]


def null_study(pool):
    """Half the participants IPE-favoured at 5 blocks and CNN-favoured at 6, half the other way round."""
    u5, v5 = balanced_pair(pool, 5, 1)
    u6, v6 = balanced_pair(pool, 6, -1)
    assert distinct_paths(u5, v6) and distinct_paths(v5, u6)
    records = []
    for i in range(PARTICIPANTS):
        first, second = (u5, v6) if i < PARTICIPANTS // 2 else (v5, u6)
        records += trial_records(pool, f"n{i}", "no_effect", 1, first)
        records += trial_records(pool, f"n{i}", "no_effect", 2, second)
    return records


@pytest.fixture(scope="module")
def study(pool, tmp_path_factory):
    root = tmp_path_factory.mktemp("fig4")
    records = crossover_study(pool) + null_study(pool)
    write_log(records, root / "log.jsonl")
    out = root / "analysis"
    args = [str(root / "log.jsonl"), "--out", str(out), "--only", "prediction", "--bootstrap", "400", "--quiet"]
    for o in WORLD:
        args += ["--world", o]
    assert main(args) == 0
    return out, pd.DataFrame(records)


def test_the_studies_are_what_they_claim(study, pool):
    """The constructed truth, checked on the analysis's own per-placement numbers."""
    out, log = study
    per = pd.read_csv(out / "fig4_placements.csv")
    assert len(per) == len(log)
    # the IPE's answers do not depend on the rest of the log: the pool asked the same states
    merged = per.merge(pool[["sequence", "step", "x", "layer", "ipe", "cnn"]].assign(
        task_id=[f"path{p}" for p in pool["path"]])[["task_id", "step", "x", "layer", "ipe", "cnn"]]
        .drop_duplicates(["task_id", "step", "x", "layer"]), on=["task_id", "step", "x", "layer"])
    assert len(merged) == len(per)
    np.testing.assert_allclose(merged["p_ipe"], merged["ipe"])
    np.testing.assert_allclose(merged["p_cnn"], merged["cnn"])
    # both approximate models beat the veridical log-likelihood on every placement that differs
    differs = per["ll_veridical"] != per["ll_ipe"]
    assert (per.loc[differs, "ll_ipe"] > per.loc[differs, "ll_veridical"] + 2).all()
    assert (per.loc[differs, "ll_cnn"] > per.loc[differs, "ll_veridical"] + 2).all()
    assert (per.loc[~differs, "ll_ipe"] == per.loc[~differs, "ll_cnn"]).all()


def test_the_paper_true_study_is_reported_as_the_papers_crossover(study):
    out, _ = study
    cross = pd.read_csv(out / "fig4_crossover.csv", dtype=str).set_index("group")
    row = cross.loc["crossover"]
    assert (row["ipe_ahead"], row["cnn_ahead"], row["not_credible"]) == ("3", "5 6", "2 4")
    assert row["verdict"] == "matches" and row["matches_paper"] == "True"
    total = pd.read_csv(out / "fig4_overall.csv").set_index(["group", "measure"])
    for model in ("ipe", "cnn"):
        assert total.loc[("crossover", f"{model}_minus_veridical"), "ci_low"] > 0
    report = (out / "report.md").read_text()
    line = next(x for x in report.splitlines() if x.startswith("- **crossover.**"))
    assert "credibly above 0 (the IPE fits better) at 3 blocks" in line
    assert "credibly below 0 (the CNN fits better) at 5–6 blocks" in line
    assert "its CI includes 0 at 2 and 4 blocks" in line
    assert "This matches the paper's direction (the IPE ahead early, the CNN later)" in line
    assert "Both approximate models fit credibly better than the veridical baseline, as in the paper" in line


def test_the_null_study_claims_no_effect_though_its_means_change_sign(study):
    out, _ = study
    stage = pd.read_csv(out / "fig4_loglik.csv")
    adv = stage[(stage["group"] == "no_effect") & (stage["measure"] == "ipe_minus_cnn")].set_index("n_blocks")
    assert adv.loc[5, "mean"] > 0 > adv.loc[6, "mean"]             # a sign change to be misread
    cross = pd.read_csv(out / "fig4_crossover.csv", dtype=str).fillna("").set_index("group").loc["no_effect"]
    assert (cross["ipe_ahead"], cross["cnn_ahead"], cross["verdict"]) == ("", "", "none")
    assert cross["matches_paper"] == "False"
    line = next(x for x in (out / "report.md").read_text().splitlines() if x.startswith("- **no_effect.**"))
    assert "not credibly different from 0 at any stage" in line and "its CI includes 0 at 2–6 blocks" in line
    assert "No credible crossover in either direction: this does not match the paper" in line
    assert "credibly above" not in line and "credibly below" not in line


def test_the_report_names_the_physics_and_labels_the_difference_plainly(study):
    out, _ = study
    report = (out / "report.md").read_text()
    assert "`ipe`: 20 noisy simulations per placement, σ = 0.03 (position, gravity, friction), on the `static` " \
           "physics" in report
    assert "`veridical`: the noise-free verdicts of the `static` physics (the world's)" in report
    assert "LL_ipe − LL_cnn [95% CI]" in report
    assert "(LL_ipe − LL_vrd) − (LL_cnn − LL_vrd)" in report          # said to be the same number, not plotted
    assert (out / "fig4_loglik.png").read_bytes()[:4] == b"\x89PNG"
    assert "fig4_crossover.csv" in report and "fig4_overall.csv" in report


# The verdicts on hand-made stage tables (no predictors).

def table(group, cells, participants=8):
    return pd.DataFrame([{"group": group, "n_blocks": n, "measure": "ipe_minus_cnn", "placements": 3 * participants,
                          "participants": participants, "mean": m, "ci_low": lo, "ci_high": hi}
                         for n, (m, lo, hi) in cells.items()])


def test_a_curve_whose_cis_include_0_is_no_crossover():
    # up, then back below 0, every CI including 0: no direction may be claimed
    stage = table("g", {2: (-0.01, -0.05, 0.03), 3: (0.27, -0.02, 0.55), 4: (-0.04, -0.3, 0.2)})
    c = prediction.crossover(stage, "g")
    assert (c.ipe_ahead, c.cnn_ahead, c.unclear, c.verdict) == ([], [], [2, 3, 4], "none")
    text = prediction.crossover_sentence(c, stage)
    assert "not credibly different from 0 at any stage; its CI includes 0 at 2–4 blocks" in text
    assert "does not match the paper" in text


@pytest.mark.parametrize("cells, verdict, phrase", [
    ({2: (0.2, 0.1, 0.3), 3: (0.0, -0.1, 0.1), 4: (-0.3, -0.4, -0.2)}, "matches", "This matches the paper's"),
    ({2: (-0.2, -0.3, -0.1), 3: (0.0, -0.1, 0.1), 4: (0.3, 0.2, 0.4)}, "reverse", "the reverse of the paper's"),
    ({2: (0.2, 0.1, 0.3), 3: (-0.2, -0.3, -0.1), 4: (0.3, 0.2, 0.4)}, "alternates", "alternate"),
    ({2: (0.0, -0.1, 0.1), 3: (-0.2, -0.3, -0.1)}, "cnn_only", "The IPE is credibly ahead at no stage"),
    ({2: (0.2, 0.1, 0.3), 3: (0.1, -0.1, 0.3)}, "ipe_only", "The CNN is credibly ahead at no stage"),
])
def test_each_direction_is_named(cells, verdict, phrase):
    stage = table("g", cells)
    c = prediction.crossover(stage, "g")
    assert c.verdict == verdict and c.matches_paper == (verdict == "matches")
    assert phrase in prediction.crossover_sentence(c, stage)


def test_too_few_participants_are_not_judged():
    few = prediction.MIN_PARTICIPANTS - 1
    stage = table("g", {2: (0.2, 0.1, 0.3), 3: (-0.3, -0.4, -0.2)}, participants=few)
    c = prediction.crossover(stage, "g")
    assert (c.too_few, c.verdict) == ([2, 3], "none")
    assert f"fewer than {prediction.MIN_PARTICIPANTS} participants at 2–3 blocks (not judged)" in \
        prediction.crossover_sentence(c, stage)


def test_the_veridical_baseline_sentence_says_which_model_beats_it():
    def total(ipe, cnn, participants=8):
        return pd.DataFrame([{"group": "g", "measure": f"{m}_minus_veridical", "participants": participants,
                              "placements": 40, "mean": (lo + hi) / 2, "ci_low": lo, "ci_high": hi}
                             for m, (lo, hi) in (("ipe", ipe), ("cnn", cnn))])

    assert "Both approximate models fit credibly better" in prediction.baseline_sentence("g", total((0.1, 0.3),
                                                                                                   (0.2, 0.4)))
    mixed = prediction.baseline_sentence("g", total((0.1, 0.3), (-0.1, 0.2)))
    assert "The IPE fits credibly better than the veridical baseline; the CNN is not credibly different" in mixed
    assert "unlike the paper" in mixed
    worse = prediction.baseline_sentence("g", total((-0.5, -0.3), (-0.4, -0.2)))
    assert "fits credibly worse" in worse and "unlike the paper" in worse
    assert "too few" in prediction.baseline_sentence("g", total((0.1, 0.3), (0.2, 0.4), participants=2))


def test_stages_text_joins_runs():
    assert prediction.stages_text([6, 2, 3, 4]) == "2–4 and 6 blocks"
    assert prediction.stages_text([3]) == "3 blocks"
    assert prediction.stages_text([2, 4, 6]) == "2, 4 and 6 blocks"


def test_predictor_overrides_go_to_the_predictors_that_have_them():
    configs = prediction.predictor_configs(["veridical", "ipe", "cnn"], ["world.physics=static", "predictor.K=7"])
    assert configs["ipe"]["K"] == 7 and "K" not in configs["veridical"] and "K" not in configs["cnn"]
    from overhang_framework.errors import OverhangError

    with pytest.raises(OverhangError, match=r"^--world predictor\.Kay=7: none of the predictors veridical, cnn "
                                            r"has that parameter$"):
        prediction.predictor_configs(["veridical", "cnn"], ["predictor.Kay=7"])

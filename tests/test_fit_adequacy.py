"""Does any model describe the participants? (fit.adequacy: the model against chance and the others' choices)."""

import math

import numpy as np
import pytest

from overhang_framework.fit import adequacy
from overhang_framework.fit.adequacy import assess, others_choices, sentence

LEGAL = [(k, 1) for k in range(10)]


def rows_of(choices, log_model):
    """Rows of participants p0.. making ``choices[p][s]`` (an action index) in shared states s, each given the
    model log-probability ``log_model(p, s, action)``."""
    rows = []
    for p, theirs in enumerate(choices):
        for s, a in enumerate(theirs):
            rows.append({"participant": f"p{p}", "condition": "c", "state": ((("w", s),), ()), "action": LEGAL[a],
                         "legal": LEGAL, "log_model": log_model(p, s, a)})
    return rows


def test_the_others_choices_leave_the_participant_out():
    rows = rows_of([[0], [0], [1]], lambda p, s, a: -1.0)
    logp, support = others_choices(rows, alpha=0.5)
    # p0 sees p1's 0 and p2's 1: (1 + 0.5) / (2 + 0.5 * 10)
    assert support.tolist() == [2, 2, 2]
    assert logp[0] == pytest.approx(math.log(1.5 / 7))
    # p2 chose 1, which neither other did
    assert logp[2] == pytest.approx(math.log(0.5 / 7))
    # another condition's choices in the same state are not the others'
    rows[1]["condition"] = "d"
    assert others_choices(rows, alpha=0.5)[1].tolist() == [1, 0, 1]


def test_with_a_motor_model_the_others_choices_are_placed_with_the_same_hand():
    rows = rows_of([[0], [0], [1]], lambda p, s, a: -1.0)
    w = np.zeros(len(LEGAL))
    w[0], w[1] = 0.2, 0.6  # the placement could have been planned as action 0 or 1
    rows[2]["weights"] = w
    logp, _ = others_choices(rows, alpha=0.5)
    shares = np.full(len(LEGAL), 0.5 / 7)
    shares[0] = 2.5 / 7  # p0's and p1's 0
    assert logp[2] == pytest.approx(math.log(shares @ w))


def shared_rule_cohort(n=12, states=8, seed=0):
    """Participants who all choose action 3 in every state but for a random one now and then."""
    rng = np.random.default_rng(seed)
    return [[3 if rng.random() < 0.85 else int(rng.integers(10)) for _ in range(states)] for _ in range(n)]


def test_a_model_that_misses_a_rule_the_people_share_is_said_to_describe_nobody():
    choices = shared_rule_cohort()
    # the model spreads its probability evenly: no better than chance, far worse than the others' choices
    people, summary = assess(rows_of(choices, lambda p, s, a: math.log(0.1)))
    assert summary["verdict"] == "not described"
    assert summary["vs_others"]["high"] < 0
    assert summary["participants_worse"] == 12
    assert "No model of the space describes these participants" in sentence(summary)


def test_the_rule_itself_describes_them():
    choices = shared_rule_cohort()
    truth = lambda p, s, a: math.log(0.85 * (a == 3) + 0.015)  # noqa: E731
    people, summary = assess(rows_of(choices, truth))
    assert summary["verdict"] == "described"
    # the others' choices estimate this shared rule well: the truth is within their reach, not below it
    assert summary["vs_others"]["high"] > 0 and abs(summary["vs_others"]["mean"]) < 0.1
    assert summary["vs_chance"]["low"] > 1.0
    assert len(people) == 12 and people["shared"].tolist() == [8] * 12
    assert "describe these participants as well as" in sentence(summary)


def test_too_few_shared_states_cannot_tell():
    rows = rows_of([[0, 1], [2, 3]], lambda p, s, a: -1.0)
    people, summary = assess(rows)
    assert summary["verdict"] == "cannot tell"
    assert "cannot be said" in sentence(summary)


def test_the_resampling_is_seeded():
    rows = rows_of(shared_rule_cohort(), lambda p, s, a: math.log(0.1))
    assert assess(rows, seed=3)[1] == assess(rows, seed=3)[1]


def test_a_directory_without_a_fit_is_one_line(tmp_path, capsys):
    assert adequacy.main([str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error:") and "fit.json" in err and "\n" not in err


def _cohort(root, name, overrides, parameters):
    from search_fixtures import fixed_cohort

    return fixed_cohort(root / name, parameters, 8, 6, "cohort.motor.sd=0", *overrides)


def _fit(root, log, out):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "overhang_framework.fit", str(log), "--out", str(out), "~models.cnn",
                           "~models.hybrid", "models.ipe.K=20", "models.ipe.sigma=[0.08]",
                           "+models.veridical={predictor: veridical}", "depths=[1]", "world.physics=static",
                           f"cache={root / 'scores.sqlite'}", "progress=false", "pooled=false"],
                          capture_output=True, text=True, timeout=600)


@pytest.fixture(scope="module")
def cohorts(tmp_path_factory):
    """Eight veridical myopic participants and eight who follow the edge heuristic (planner=edge), six tasks each,
    both fitted with the veridical and a noisy IPE at depth 1."""
    root = tmp_path_factory.mktemp("adequacy")
    fixed = lambda v: {"dist": "fixed", "value": v}  # noqa: E731
    logs = {"veridical": _cohort(root, "veridical", ["predictor=veridical"],
                                 {"depth": fixed(1), "beta": fixed(20.0), "lapse": fixed(0.02), "sigma": None}),
            "edge": _cohort(root, "edge", ["planner=edge"],
                            {"depth": None, "beta": fixed(30.0), "lapse": fixed(0.02), "sigma": None})}
    for name, log in logs.items():
        proc = _fit(root, log, root / f"fit-{name}")
        assert proc.returncode == 0, proc.stderr
    return root


def test_the_fit_opens_with_whether_any_model_describes_them(cohorts):
    import json

    right = json.loads((cohorts / "fit-veridical" / "adequacy.json").read_text())
    wrong = json.loads((cohorts / "fit-edge" / "adequacy.json").read_text())
    assert right["verdict"] == "described" and right["vs_others"]["mean"] > 0, right
    assert wrong["verdict"] == "not described" and wrong["vs_others"]["high"] < 0, wrong
    # both sets of participants have a best model; only the comparison's first sentence tells them apart
    for name, summary in (("veridical", right), ("edge", wrong)):
        text = (cohorts / f"fit-{name}" / "comparison.md").read_text()
        assert text.split("\n")[2] == summary["sentence"]
        assert "Each participant's best model" in text
    assert (cohorts / "fit-edge" / "comparison.md").read_text().split("\n")[2].startswith(
        "**No model of the space describes these participants**")


def test_the_summary_is_recomputed_from_the_kept_table(cohorts, tmp_path):
    import json

    fit = cohorts / "fit-edge"
    assert adequacy.main(["--table", str(fit / "adequacy.csv"), "--summary", str(tmp_path / "s.json")]) == 0
    again = json.loads((tmp_path / "s.json").read_text())
    kept = json.loads((fit / "adequacy.json").read_text())
    assert again["sentence"] == kept["sentence"] and again["vs_others"] == pytest.approx(kept["vs_others"])


def test_compare_reads_the_finding_only_for_the_fits_it_describes(cohorts, tmp_path):
    import shutil

    from overhang_framework.fit import compare

    fit = tmp_path / "fit"
    shutil.copytree(cohorts / "fit-edge", fit)
    assert compare.main([str(fit)]) == 0
    assert "No model of the space describes" in (fit / "comparison.md").read_text()
    # fits.csv changed after the check: its finding no longer describes them and is left out
    import pandas as pd

    fits = pd.read_csv(fit / "fits.csv")
    fits.loc[0, "bic"] += 1.0
    fits.to_csv(fit / "fits.csv", index=False)
    assert adequacy.read(fit) is None
    assert compare.main([str(fit)]) == 0
    assert "No model of the space describes" not in (fit / "comparison.md").read_text()


@pytest.mark.parametrize("text, message", [
    ("participant,condition\nx,y\n", "no column 'placements'"),
    ("participant,condition,placements,shared,model,chance,sum_vs_chance,sum_vs_others,model_shared,others_shared\n"
     "p,c,many,1,-1,-2,3,0.5,-1,-1.5\n", "column 'placements' must hold numbers"),
    ("participant,condition,placements,shared,model,chance,sum_vs_chance,sum_vs_others,model_shared,others_shared\n"
     "p,c,0,0,-1,-2,0,0,,\n", "placements must be counts >= 0, and some above 0"),
    ('a,"b\n1,2,3\n4\n', "cannot read a participant table"),
])
def test_a_bad_table_is_one_line(tmp_path, capsys, text, message):
    (tmp_path / "t.csv").write_text(text)
    assert adequacy.main(["--table", str(tmp_path / "t.csv")]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err, err

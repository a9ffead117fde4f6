"""The practice's expected screen-out (``overhang_framework.studies.screenout``): the design's participants do the
served study's practice as its server scores it, and the preregistration recruits by the share screened out."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pandas as pd
import pytest
from omegaconf import OmegaConf

from overhang_framework.studies import screenout

LEVELS = ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"]


def _practice(pass_rewards):
    return [SimpleNamespace(task=SimpleNamespace(id=f"practice{k}", sequence=(1.2, 0.6)), pass_reward=r)
            for k, r in enumerate(pass_rewards, 1)]


@pytest.mark.parametrize("rewards, max_attempts, expected", [
    # each task attempted until it passes: 2 failures then a pass, a pass, a timeout (None) then a pass
    ([0.5, 0.9, 1.5, 1.6, None, 1.4], 5, {"passed": True, "attempts": 6, "failed_task": None}),
    # the attempts are a task's, not the practice's: 4 failures on task 1 pass at the 5th; task 2 fails 5 times
    ([0.1] * 4 + [1.5] + [0.0] * 5, 5, {"passed": False, "attempts": 10, "failed_task": "practice2"}),
    ([0.1] * 2, 2, {"passed": False, "attempts": 2, "failed_task": "practice1"}),
    ([0.1] * 7 + [1.5, 1.5, 1.5], None, {"passed": True, "attempts": 10, "failed_task": None}),  # no limit
])
def test_a_participant_attempts_each_practice_task_until_it_passes_or_the_attempts_are_used_up(
        monkeypatch, rewards, max_attempts, expected):
    from overhang_framework.behaviour import participants

    given = iter(rewards)
    seen = []

    def trial(participant, spec, cohort, task, trial, *rest):
        seen.append((task.id, trial))
        return [{"reward": next(given)}]

    monkeypatch.setattr(participants, "simulate_trial", trial)
    who = SimpleNamespace(id="sim-x-001", condition="limit_10s", index=3)
    row = screenout.practise(who, None, None, _practice([1.35, 1.35, 1.35]), max_attempts, None, None, None, None,
                             seed=0)
    assert row == {"participant": "sim-x-001", "condition": "limit_10s", **expected}
    assert [t for _, t in seen] == sorted(t for _, t in seen)  # the tasks in order, each with its trial number


def test_recruits_keep_the_planned_size_after_the_screen_out():
    assert screenout.to_recruit(10, 0, 40) == 10
    assert screenout.to_recruit(10, 20, 40) == 20  # half screened out: twice as many
    assert screenout.to_recruit(10, 1, 4) == 14  # 10 / 0.75 = 13.3: rounded up
    assert screenout.to_recruit(10, 4, 4) is None  # everyone screened out: no number is enough
    table = pd.DataFrame({"participant": [f"p{i}" for i in range(8)], "condition": LEVELS * 2,
                          "passed": [True, False, True, True, False, False, True, True]})
    rows = {r["level"]: r for r in screenout.summary(table, LEVELS, 12)}
    assert (rows["limit_2_5s"]["screened_out"], rows["limit_2_5s"]["recruit"]) == (1, 24)
    assert (rows["time_limited"]["screened_out"], rows["time_limited"]["recruit"]) == (2, None)
    assert (rows["limit_10s"]["share"], rows["limit_10s"]["recruit"]) == (0.0, 12)


def test_the_preregistration_recruits_by_the_simulated_screen_out():
    import numpy as np

    from overhang_framework.studies import graded, prereg

    rng = np.random.default_rng(0)
    pool = pd.DataFrame([{"participant": f"{lv}-{i}", "condition": lv,
                          "avg_overhang": 1.3 + 0.06 * k + rng.normal(0, 0.04),
                          "gamma": 0.1 + 0.05 * k + rng.normal(0, 0.03),
                          "abs_x_late": 0.4 + 0.03 * k + rng.normal(0, 0.03)}
                         for k, lv in enumerate(LEVELS) for i in range(30)])
    levels = graded.levels_of({"limit_2_5s": 2.5, "time_limited": 5.0, "limit_10s": 10.0, "unconstrained": None})
    table = graded.power(pool, levels, [m for m in graded.MEASURES if m.name in ("overhang", "gamma", "lateral")],
                         sizes=(4, 8, 15), resamples=40)
    n, _ = prereg.planned_size(table)
    assert n is not None
    screen = pd.DataFrame({"participant": [f"p{i}" for i in range(16)], "condition": LEVELS * 4,
                           "passed": [True] * 4 + [False, True, True, True] * 3})
    limits = {"limit_2_5s": 2.5, "time_limited": 5.0, "limit_10s": 10.0, "unconstrained": None}
    args = (levels, limits, table, pd.DataFrame(), {lv: 13.4 for lv in levels}, dict.fromkeys(levels, 30), False,
            {"commit": "c", "version": "v", "settings_hash": "h", "seed": 0, "resamples": 40}, "cmd")
    text = prereg.document(*args, screen)
    need = screenout.to_recruit(n, 3, 4)
    assert f"| `limit_2_5s` | 3 of 4 (75%) | {need} |" in text and f"| `time_limited` | 0 of 4 (0%) | {n} |" in text
    # the server balances the levels over everyone it takes: each level gets what the worst one needs
    assert f"**Recruit {need} a level, {4 * need} in all.**" in text
    assert "'durations={limit_2_5s: 15, time_limited: 15, limit_10s: 15, unconstrained: 15}'" in text
    flat = table.assign(power=0.1)  # no size has the power: the document says so, whatever the screen-out
    for screened in (screen, "no towers", None):
        lacking = prereg.document(levels, limits, flat, *args[3:], screened)
        assert "**No size of the grid gives every primary hypothesis 80% power**" in lacking
        assert "participants per level**" not in lacking and "**Recruit" not in lacking
    why = prereg.document(*args, "practice task practice1 has no stored buildable tower")
    assert "could not be simulated (practice task practice1 has no stored buildable tower)" in why
    assert "recruit:" not in why


def test_the_design_s_participants_do_the_practice_as_the_server_scores_it_reproducibly():
    """A cohort that always lapses (a random legal placement each time) is screened out, at a task's fifth attempt; the same config gives the same table, in one process or two."""
    from overhang_framework.behaviour.simulation import CONFIG_NAME
    from overhang_framework.studies.run import _compose

    cfg = _compose(["cohort=null_effect", "predictor=ipe", "predictor.K=5", "seed=4", "progress=false",
                    "world.physics=static", "cohort.participants={time_limited: 2, unconstrained: 1}",
                    "~cohort.parameters.lapse", "+cohort.parameters.lapse={dist: fixed, value: 1.0}"], CONFIG_NAME, "--participants")
    config = OmegaConf.to_container(cfg, resolve=True)
    table = screenout.simulate_practice(config)
    assert list(table["condition"]) == ["time_limited", "time_limited", "unconstrained"]
    assert not table["passed"].any()
    k = table["failed_task"].str.removeprefix("practice").astype(int)  # the task each was screened out at
    assert ((table["attempts"] >= 5 + (k - 1)) & (table["attempts"] <= 5 * k)).all()
    assert table.equals(screenout.simulate_practice(config, jobs=2))
    steady = _compose(["cohort=null_effect", "predictor=ipe", "predictor.K=5", "seed=4", "progress=false",
                       "world.physics=static", "cohort.participants={time_limited: 2, unconstrained: 1}",
                       "~cohort.parameters.lapse", "+cohort.parameters.lapse={dist: fixed, value: 0.0}"], CONFIG_NAME, "--participants")
    again = screenout.simulate_practice(OmegaConf.to_container(steady, resolve=True))
    assert again["attempts"].sum() > 3 and json.loads(again.to_json()) == json.loads(
        screenout.simulate_practice(OmegaConf.to_container(steady, resolve=True)).to_json())


def test_the_practice_takes_the_first_participants_of_each_level():
    people = [SimpleNamespace(index=i, condition=c) for i, c in enumerate(["a", "a", "a", "b", "b", "c"])]
    assert screenout.chosen(people, 2) == [0, 1, 3, 4, 5]
    assert screenout.chosen(people, None) == [0, 1, 2, 3, 4, 5]

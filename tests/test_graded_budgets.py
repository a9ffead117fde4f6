"""The graded-budget study: conditions with time limits of their own, served to people (study=graded_budgets),
simulated (cohort=graded_budgets) and piloted through the server with each level's limit."""

from __future__ import annotations

import pytest

from overhang_framework.config import compose_config
from overhang_framework.errors import ConfigError

TOKEN = ["admin_token=abcdefghijklmnop"]


def test_the_study_serves_four_levels_each_with_its_own_limit(tmp_path):
    from overhang_framework.experiment.provenance import study_settings
    from overhang_framework.experiment.settings import load_settings

    s = load_settings(["study=graded_budgets", *TOKEN, f"run_dir={tmp_path}"])
    assert s.conditions == ["limit_2_5s", "time_limited", "limit_10s", "unconstrained"]
    assert [s.limit_of(c) for c in s.conditions] == [2.5, 5.0, 10.0, None]
    assert study_settings(s)["time_limits"] == {"limit_2_5s": 2.5, "limit_10s": 10.0}
    # the paper's two conditions: the study's settings, and so their hash, carry no time_limits
    plain = load_settings([*TOKEN, f"run_dir={tmp_path}"])
    assert plain.time_limits == {} and "time_limits" not in study_settings(plain)
    added = load_settings(["+time_limits.limit_3s=3.0", "conditions=[limit_3s,unconstrained]", *TOKEN,
                           f"run_dir={tmp_path}"])
    assert added.limit_of("limit_3s") == 3.0


@pytest.mark.parametrize("overrides, words", [
    (["conditions=[limit_3s]"], "another condition needs its entry in time_limits"),
    (["+time_limits.Fast=2", "conditions=[time_limited]"], "'Fast' is not a name for a condition"),
    (["+time_limits.fast=0", "conditions=[fast]"], "time_limits.fast must be a number of seconds > 0"),
    (["+time_limits.time_limited=3"], "'time_limited' is not a name for a condition"),
])
def test_a_bad_level_is_one_line(tmp_path, overrides, words):
    from overhang_framework.experiment.settings import load_settings

    with pytest.raises(ConfigError, match=words):
        load_settings([*overrides, *TOKEN, f"run_dir={tmp_path}"])


def test_a_participant_gets_their_levels_limit_from_the_server(tmp_path):
    from fastapi.testclient import TestClient

    from overhang_framework.experiment.api import create_app
    from overhang_framework.experiment.settings import load_settings

    settings = load_settings(["study=graded_budgets", *TOKEN, f"run_dir={tmp_path}"])
    seen = {}
    with TestClient(create_app(settings)) as client:
        for k in range(8):
            r = client.post("/api/sessions", json={"params": {"participant": f"p{k}"}})
            assert r.status_code == 201, r.text
            seen.setdefault(r.json()["condition"], set()).add(r.json()["time_limit"])
    assert seen == {"limit_2_5s": {2.5}, "time_limited": {5.0}, "limit_10s": {10.0}, "unconstrained": {None}}


def test_the_simulated_twin_has_each_levels_budget_and_the_pilot_passes_each_limit_to_its_server(tmp_path):
    from overhang_framework.experiment.pilot import plan, server_overrides
    from overhang_framework.behaviour.simulation import CONFIG_NAME, check_config

    checked = check_config(compose_config(["cohort=graded_budgets", "world.physics=static"],
                                          config_name=CONFIG_NAME))
    specs = {s.name: (s.time_limit, s.call_limit) for s in checked.cohort.conditions}
    assert specs == {"limit_2_5s": (2.5, 1), "time_limited": (5.0, 4), "limit_10s": (10.0, 11),
                     "unconstrained": (None, None)}
    assert checked.cohort.time_for("limit_2_5s").t0 < checked.cohort.time_for("time_limited").t0 \
        < checked.cohort.time_for("unconstrained").t0
    p = plan(["cohort=graded_budgets", "cohort.n_tasks=2",
              "cohort.participants={limit_2_5s: 1, time_limited: 1, limit_10s: 1, unconstrained: 1}"])
    words = server_overrides(p, 2.0, tmp_path, 8123)
    assert "conditions=[limit_2_5s,time_limited,limit_10s,unconstrained]" in words
    assert {"time_limit=10.0", "+time_limits.limit_2_5s=5.0", "+time_limits.limit_10s=20.0"} <= set(words)
    from overhang_framework.experiment.settings import load_settings

    served = load_settings([w for w in words if not w.startswith(("port=", "host="))] + TOKEN)
    assert [served.limit_of(c) for c in served.conditions] == [5.0, 10.0, 20.0, None]

"""Every config composes; every registered name has a config file and every config file a registered name."""

import pytest

from overhang_framework.cli import GROUPS
from overhang_framework.config import compose_config, group_options
from overhang_framework.plugins import KINDS, Registry
from overhang_framework.tasks import tasks_from_config


@pytest.mark.parametrize("kind", KINDS)
def test_registered_names_and_config_files_match(kind):
    assert set(group_options(kind)) == set(Registry().names(kind))


@pytest.mark.parametrize("group", GROUPS)
def test_every_option_composes_and_names_itself(group):
    options = group_options(group)
    assert options, f"group {group} is empty"
    for option in options:
        overrides = [f"{group}={option}"]
        if group == "tasks" and option == "custom":
            overrides.append("tasks.sequences=[[0.6,1.2]]")
        cfg = compose_config(overrides)
        assert cfg[group].name == option


def test_default_config_builds_every_model():
    from overhang_framework.plugins import build_models

    cfg = compose_config(["world.physics=pybullet"])
    models = build_models(cfg)
    assert set(models) == {"world", "predictor", "planner", "value"}
    assert len(tasks_from_config(cfg.tasks)) == 20

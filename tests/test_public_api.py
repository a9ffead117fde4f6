"""The declared public API (``overhang_framework.__all__``): every name there, documented, and every public name that
moved still found at its old place with a warning that names the new one."""

from __future__ import annotations

import importlib
import re
import sys
import warnings
from pathlib import Path

import pytest

import overhang_framework

ROOT = Path(__file__).resolve().parents[1]


def test_every_public_name_is_the_object_of_its_module_and_is_documented():
    documented = (ROOT / "docs" / "plugins.md").read_text().split("## The public Python API", 1)[1].split("\n## ")[0]
    listed = set(re.findall(r"`(\w+)`", documented))
    for name in overhang_framework.__all__:
        value = getattr(overhang_framework, name)
        if name != "__version__":
            assert value is getattr(importlib.import_module(overhang_framework.PUBLIC[name]), name)
        assert name in listed, f"{name} is public but docs/plugins.md's public API does not list it"
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        overhang_framework.nope  # noqa: B018


def test_the_documented_example_builds_the_models_of_a_config():
    from overhang_framework import Action, Geometry, Predictor, State, build_models, compose_config

    models = build_models(compose_config(["world.physics=static", "predictor=veridical"]))
    assert isinstance(models["predictor"], Predictor)
    state = models["world"].initial_state(overhang_framework.Task("t", (1.2, 0.6)))
    assert isinstance(state, State) and isinstance(state.geometry, Geometry)
    assert all(isinstance(a, Action) for a in models["world"].legal_actions(state))


MOVED = [
    ("overhang_framework.app", "build_models", "overhang_framework.plugins"),
    ("overhang_framework.study", "power", "overhang_framework.studies.findings"),
    ("overhang_framework.study", "resample", "overhang_framework.studies.power"),
    ("overhang_framework.study", "gather", "overhang_framework.studies.gather"),
    ("overhang_framework.study", "Steps", "overhang_framework.studies.steps"),
    ("overhang_framework.graded", "trend", "overhang_framework.studies.graded"),
    ("overhang_framework.participants", "run", "overhang_framework.behaviour.simulation"),
    ("overhang_framework.fidelity", "load_points", "overhang_framework.report.fidelity"),
    ("overhang_framework.docfigures", "load_registry", "overhang_framework.report.docfigures"),
]


@pytest.mark.parametrize("old, name, new", MOVED, ids=[f"{o}.{n}" for o, n, _ in MOVED])
def test_a_moved_name_is_found_at_its_old_place_with_a_warning_naming_the_new(old, name, new):
    module = importlib.import_module(old)
    with pytest.warns(DeprecationWarning, match=re.escape(f"{old}.{name} moved to {new}.{name}")):
        value = getattr(module, name)
    assert value is getattr(importlib.import_module(new), name)
    with pytest.raises(AttributeError, match="has no attribute 'nope'"):
        module.nope  # noqa: B018


def test_the_old_tower_module_warns_and_gives_the_same_towers():
    sys.modules.pop("overhang_framework.bench.towers", None)
    with pytest.warns(DeprecationWarning, match="overhang_framework.bench.towers moved to overhang_framework.physics.towers"):
        old = importlib.import_module("overhang_framework.bench.towers")
    from overhang_framework.physics import towers

    assert old.random_towers is towers.random_towers and old.episode_questions is towers.episode_questions


def test_the_package_itself_uses_no_moved_name():
    """Importing every module of the package warns of nothing: the code uses the names at their new places."""
    import pkgutil

    skip = {"overhang_framework.bench.towers"}
    with warnings.catch_warnings():
        warnings.simplefilter("error", DeprecationWarning)
        for info in pkgutil.walk_packages(overhang_framework.__path__, "overhang_framework."):
            if info.name not in skip and not info.name.endswith("__main__"):
                importlib.import_module(info.name)

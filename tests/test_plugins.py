"""The plugin system: registration, errors, listing, and plugin-contributed configs."""

import inspect
import subprocess
import sys
from pathlib import Path

import pytest

from overhang_framework import hookspecs
from overhang_framework.config import compose_config
from overhang_framework.errors import UnknownPluginError
from overhang_framework.hookspecs import hookimpl
from overhang_framework.plugins import KINDS, Registry, describe_plugins, get_plugin_manager

TESTS = Path(__file__).parent


def test_builtins_are_loaded_through_the_entry_point_group():
    pm = get_plugin_manager()
    dists = {pm.get_name(plugin): dist.project_name for plugin, dist in pm.list_plugin_distinfo()}
    assert dists.get("builtins") == "overhang-framework"
    reg = Registry()
    for kind in KINDS:
        assert reg.names(kind), f"no built-in {kind}"
    assert reg.get("world", "overhang").plugin == "builtins"


def test_unknown_name_lists_installed_names():
    with pytest.raises(UnknownPluginError) as err:
        Registry().create("planner", {"name": "nope"})
    message = str(err.value)
    assert "\n" not in message
    assert "unknown planner 'nope'" in message and "myopic" in message


def test_a_registered_plugin_adds_names_and_goes_away(register_plugin):
    class Plugin:
        @hookimpl
        def register_values(self, register):
            register("zero", lambda world=None: (lambda state: 0.0))

    before = Registry().names("value")
    plugin = register_plugin(Plugin(), name="zero-plugin")
    assert "zero" in Registry().names("value")
    assert Registry().create("value", {"name": "zero"})(None) == 0.0
    get_plugin_manager().unregister(plugin)
    assert Registry().names("value") == before
    get_plugin_manager().register(plugin, name="zero-plugin")  # the fixture unregisters it


def test_a_name_registered_twice_is_an_error(register_plugin):
    class Clash:
        @hookimpl
        def register_planners(self, register):
            register("myopic", object)

    register_plugin(Clash(), name="clash")
    with pytest.raises(ValueError, match="'myopic' is registered twice"):
        Registry()


def test_plugin_config_directory_joins_the_search_path(example_plugin):
    cfg = compose_config(["planner=random"])
    assert cfg.planner.name == "random" and cfg.planner.min_stability == 0.5
    planner = Registry().create("planner", cfg.planner, world=None)
    assert type(planner).__name__ == "RandomPlanner"


def test_listing_names_package_version_and_registrations(example_plugin):
    rows = {row["plugin"]: row for row in describe_plugins()}
    assert rows["builtins"]["package"] == "overhang-framework"
    assert rows["builtins"]["version"]
    assert rows["example"]["registers"] == {"planner": ["random"]}
    assert rows["example"]["config_paths"] == ["pkg://overhang_example_plugin.conf"]


def test_plugins_command_prints_listing():
    out = subprocess.run([sys.executable, "-m", "overhang_framework", "plugins"],
                         capture_output=True, text=True, check=True).stdout
    assert "builtins  (overhang-framework" in out
    assert "predictors" in out and "veridical" in out


def test_every_hook_is_documented_and_implemented_by_a_test_plugin():
    """Each hookspec has a docstring, and a test plugin in another test file implements it."""
    others = "\n".join(p.read_text() for p in TESTS.glob("test_*.py") if p.name != Path(__file__).name)
    hooks = [name for name, fn in inspect.getmembers(hookspecs, inspect.isfunction)
             if hasattr(fn, "overhang_framework_spec")]
    assert set(hooks) >= {"register_worlds", "register_predictors", "register_planners",
                          "register_values", "config_search_paths"}
    for name in hooks:
        assert (getattr(hookspecs, name).__doc__ or "").strip(), f"hook {name} has no docstring"
        assert f"def {name}(" in others, f"no test plugin implements {name}"

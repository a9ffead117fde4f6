import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_PLUGIN = ROOT / "examples" / "example_plugin"


@pytest.fixture
def register_plugin():
    """Register plugin objects with the process-wide plugin manager for one test."""
    from overhang_framework.plugins import get_plugin_manager

    pm = get_plugin_manager()
    added = []

    def register(plugin, name=None):
        pm.register(plugin, name=name)
        added.append(plugin)
        return plugin

    yield register
    for plugin in added:
        pm.unregister(plugin)


@pytest.fixture
def example_plugin(register_plugin, monkeypatch):
    """The example third-party plugin of ``examples/example_plugin``, registered for one test."""
    monkeypatch.syspath_prepend(str(EXAMPLE_PLUGIN))
    import overhang_example_plugin

    register_plugin(overhang_example_plugin, name="example")
    yield overhang_example_plugin
    sys.modules.pop("overhang_example_plugin", None)

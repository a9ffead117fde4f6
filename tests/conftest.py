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


SERVICE_USER = "overhang"


@pytest.fixture(scope="session")
def service_user():
    """The system user ``overhang`` the deployment's service runs as (docs/deploy.md), made when the tests run
    as root and it is missing; without it (and without root) the test is skipped."""
    import os
    import pwd
    import shutil
    import subprocess

    try:
        pwd.getpwnam(SERVICE_USER)
        return SERVICE_USER
    except KeyError:
        pass
    if os.geteuid() != 0 or shutil.which("useradd") is None:
        pytest.skip(f"needs the system user {SERVICE_USER!r} (sudo adduser --system --group {SERVICE_USER})")
    subprocess.run(["useradd", "--system", "--user-group", "--no-create-home", "--shell", "/usr/sbin/nologin",
                    SERVICE_USER], check=True, capture_output=True)
    return SERVICE_USER

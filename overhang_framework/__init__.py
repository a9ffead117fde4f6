"""overhang-framework: sequential physical planning on the Overhang Tower task.

The public Python API is what :data:`__all__` lists, importable from here (``from overhang_framework import
Geometry, build_models``); docs/plugins.md describes each name. Modules stay free to move below it: a public
name that moves keeps working at its old place for a release, with a ``DeprecationWarning`` naming the new
one. The names are loaded when first asked for, so importing the package stays cheap.
"""

from overhang_framework.version import __version__  # noqa: E402,F401

#: Each public name and the module it lives in.
PUBLIC = {
    # towers and tasks: plain immutable data
    "Action": "overhang_framework.geometry", "Block": "overhang_framework.geometry",
    "Geometry": "overhang_framework.geometry", "WIDTHS": "overhang_framework.geometry",
    "Task": "overhang_framework.interfaces", "State": "overhang_framework.interfaces",
    # the four interfaces a plugin implements, and what a planner reports
    "World": "overhang_framework.interfaces", "Predictor": "overhang_framework.interfaces",
    "Planner": "overhang_framework.interfaces", "Value": "overhang_framework.interfaces",
    "Budget": "overhang_framework.interfaces", "Decision": "overhang_framework.interfaces",
    "Spend": "overhang_framework.interfaces",
    # plugins: the hook marker, the registry, models built from a config
    "hookimpl": "overhang_framework.hookspecs", "Registry": "overhang_framework.plugins",
    "build_models": "overhang_framework.plugins", "compose_config": "overhang_framework.config",
    "tasks_from_config": "overhang_framework.tasks",
    # playing and reading
    "run_episode": "overhang_framework.episode", "read_log": "overhang_framework.behaviour.log",
    "write_log": "overhang_framework.behaviour.log",
    # the errors every refusal is
    "OverhangError": "overhang_framework.errors", "ConfigError": "overhang_framework.errors",
}

__all__ = ["__version__", *PUBLIC]


def __getattr__(name: str):
    module = PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'overhang_framework' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *PUBLIC})


from overhang_framework.envs import register as _register_envs  # noqa: E402

_register_envs()

"""Every hook of overhang-framework, declared once; each docstring is the hook's documentation.

A plugin is a module (or object) with functions marked ``@hookimpl`` and named
like the hooks below, exposed through an entry point in the
``overhang_framework`` group of its package::

    [project.entry-points.overhang_framework]
    my_plugin = "my_package.plugin"

The built-in implementations are loaded through this same group.
"""

from __future__ import annotations

from typing import Callable

import pluggy

PROJECT = "overhang_framework"

hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)

Register = Callable[[str, Callable], None]


@hookspec
def register_worlds(register: Register) -> None:
    """Add worlds: call ``register(name, factory)`` once per world.

    ``factory(**params)`` builds a :class:`~overhang_framework.interfaces.World`;
    ``params`` are the keys of ``conf/world/<name>.yaml`` other than ``name``.
    """


@hookspec
def register_predictors(register: Register) -> None:
    """Add predictors: call ``register(name, factory)`` once per predictor.

    ``factory(world=world, **params)`` builds a
    :class:`~overhang_framework.interfaces.Predictor`; ``params`` come from
    ``conf/predictor/<name>.yaml``.
    """


@hookspec
def register_planners(register: Register) -> None:
    """Add planners: call ``register(name, factory)`` once per planner.

    ``factory(world=world, **params)`` builds a
    :class:`~overhang_framework.interfaces.Planner`; ``params`` come from
    ``conf/planner/<name>.yaml``.
    """


@hookspec
def register_values(register: Register) -> None:
    """Add leaf values: call ``register(name, factory)`` once per value.

    ``factory(world=world, **params)`` builds a
    :class:`~overhang_framework.interfaces.Value`; ``params`` come from
    ``conf/value/<name>.yaml``.
    """


@hookspec
def config_search_paths() -> list[str]:
    """Return config directories to add to Hydra's search path.

    Each entry is a Hydra search-path string, ``pkg://my_package.conf`` for a
    directory shipped inside a package or ``file:///abs/path``. A directory
    holds ``<group>/<name>.yaml`` files for the groups ``world``,
    ``predictor``, ``planner``, ``value``, ``condition`` and ``tasks``.
    """

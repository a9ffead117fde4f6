"""Composing the project's Hydra config from Python, with every plugin's config directory."""

from __future__ import annotations

from typing import Sequence

from omegaconf import DictConfig

CONFIG_MODULE = "overhang_framework.conf"
CONFIG_PATH = f"pkg://{CONFIG_MODULE}"


def enable_plugin_configs() -> None:
    """Make Hydra add the config directories of installed plugins to its search path.

    Hydra finds the search-path plugin by scanning the ``hydra_plugins``
    namespace package; registering it here as well makes that independent of
    how the project was installed (an editable install hides it from the scan).
    """
    from hydra.core.plugins import Plugins
    from hydra_plugins.overhang_framework_searchpath import OverhangFrameworkSearchPathPlugin

    Plugins.instance().register(OverhangFrameworkSearchPathPlugin)


def compose_config(overrides: Sequence[str] = (), config_name: str = "config",
                   return_hydra_config: bool = False) -> DictConfig:
    """The composed run config for ``overrides``, as ``python -m overhang_framework`` would see it
    (with Hydra's own node when ``return_hydra_config``)."""
    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    enable_plugin_configs()
    GlobalHydra.instance().clear()
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return compose(config_name, overrides=list(overrides), return_hydra_config=return_hydra_config)


def group_options(group: str) -> list[str]:
    """Config names available in ``group`` on the full search path."""
    from hydra import initialize_config_module
    from hydra.core.global_hydra import GlobalHydra

    enable_plugin_configs()
    GlobalHydra.instance().clear()
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return sorted(GlobalHydra.instance().config_loader().get_group_options(group))


def in_sweep() -> bool:
    """Whether the running Hydra job is one job of a multirun (``-m``)."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.get().mode == RunMode.MULTIRUN

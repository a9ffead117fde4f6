"""The plugin manager, the registry of named implementations, and the models a config names built through it."""

from __future__ import annotations

import functools
import inspect
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Optional

import pluggy

from overhang_framework import hookspecs
from overhang_framework.errors import ConfigError, UnknownPluginError, closest

KINDS = ("world", "predictor", "planner", "value")
_HOOKS = {
    "world": "register_worlds",
    "predictor": "register_predictors",
    "planner": "register_planners",
    "value": "register_values",
}


@functools.lru_cache(maxsize=None)
def get_plugin_manager() -> pluggy.PluginManager:
    """The process-wide plugin manager, with every installed ``overhang_framework`` entry point loaded."""
    pm = pluggy.PluginManager(hookspecs.PROJECT)
    pm.add_hookspecs(hookspecs)
    pm.load_setuptools_entrypoints(hookspecs.PROJECT)
    return pm


@dataclass(frozen=True)
class Entry:
    kind: str
    name: str
    factory: Callable
    plugin: str


class Registry:
    """Names to factories, per kind, collected from the plugins' ``register_*`` hooks."""

    def __init__(self, pm: Optional[pluggy.PluginManager] = None):
        self.pm = pm or get_plugin_manager()
        self.entries: dict[str, dict[str, Entry]] = {kind: {} for kind in KINDS}
        for kind in KINDS:
            hook = getattr(self.pm.hook, _HOOKS[kind])
            for impl in hook.get_hookimpls():
                plugin_name = self.pm.get_name(impl.plugin) or repr(impl.plugin)

                def register(name: str, factory: Callable, _kind=kind, _plugin=plugin_name) -> None:
                    self._add(_kind, name, factory, _plugin)

                impl.function(register=register)

    def _add(self, kind: str, name: str, factory: Callable, plugin: str) -> None:
        if not isinstance(name, str) or not name:
            raise ValueError(f"plugin {plugin!r} registered a {kind} with an empty or non-string name")
        if name in self.entries[kind]:
            other = self.entries[kind][name].plugin
            raise ValueError(f"{kind} {name!r} is registered twice, by {other!r} and {plugin!r}")
        self.entries[kind][name] = Entry(kind, name, factory, plugin)

    def names(self, kind: str) -> list[str]:
        return sorted(self.entries[kind])

    def get(self, kind: str, name: str) -> Entry:
        try:
            return self.entries[kind][name]
        except KeyError:
            raise UnknownPluginError(kind, name, self.names(kind)) from None

    def create(self, kind: str, config: Mapping[str, Any], **deps: Any) -> Any:
        """Build the ``kind`` named by ``config['name']`` from the rest of ``config`` and ``deps``.

        A parameter the factory does not take, or a value it refuses with
        ``ValueError`` or ``TypeError``, raises :class:`ConfigError` naming the
        plugin and the parameter.
        """
        params = dict(config)
        name = params.pop("name", None)
        if name is None:
            raise UnknownPluginError(kind, "<missing name>", self.names(kind))
        factory = self.get(kind, name).factory
        allowed = accepted_parameters(factory)
        if allowed is not None:
            unknown = sorted(set(params) - allowed)
            if unknown:
                known = sorted(allowed - set(deps))
                hints = [c[0] for u in unknown if (c := closest(u, known))]
                hint = f" (did you mean {', '.join(hints)}?)" if hints else ""
                raise ConfigError(f"{kind} {name!r} has no parameter {', '.join(unknown)}{hint}; "
                                  f"its parameters: {', '.join(known) or '(none)'}")
        try:
            return factory(**deps, **params)
        except (ValueError, TypeError) as err:
            if isinstance(err, ConfigError):
                raise
            raise ConfigError(f"{kind} {name!r}: {err}") from err


def accepted_parameters(factory: Callable) -> Optional[set[str]]:
    """Keyword parameters ``factory`` takes, or ``None`` when it takes any (``**kwargs``)."""
    try:
        sig = inspect.signature(factory)
    except (TypeError, ValueError):
        return None
    names = set()
    for p in sig.parameters.values():
        if p.kind is p.VAR_KEYWORD:
            return None
        if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY):
            names.add(p.name)
    return names


def config_search_paths(pm: Optional[pluggy.PluginManager] = None) -> list[str]:
    """Every config directory the plugins contribute, in load order."""
    pm = pm or get_plugin_manager()
    paths: list[str] = []
    for result in pm.hook.config_search_paths():
        paths.extend(result or [])
    return paths


def describe_plugins(pm: Optional[pluggy.PluginManager] = None) -> list[dict]:
    """One row per loaded plugin: its name, package, version and what it registers."""
    pm = pm or get_plugin_manager()
    registry = Registry(pm)
    dists = {id(plugin): dist for plugin, dist in pm.list_plugin_distinfo()}
    rows = []
    for name, plugin in pm.list_name_plugin():
        dist = dists.get(id(plugin))
        registers = {
            kind: sorted(e.name for e in registry.entries[kind].values() if e.plugin == name)
            for kind in KINDS
        }
        hookimpls = {impl.function.__name__ for impl in _impls_of(pm, plugin)}
        rows.append(
            {
                "plugin": name,
                "package": dist.project_name if dist else "(not installed)",
                "version": dist.version if dist else "",
                "registers": {k: v for k, v in registers.items() if v},
                "config_paths": _paths_of(plugin) if "config_search_paths" in hookimpls else [],
            }
        )
    return rows


def _impls_of(pm: pluggy.PluginManager, plugin: object):
    for caller in pm.get_hookcallers(plugin) or []:
        for impl in caller.get_hookimpls():
            if impl.plugin is plugin:
                yield impl


def _paths_of(plugin: object) -> list[str]:
    fn = getattr(plugin, "config_search_paths", None)
    return list(fn() or []) if fn else []


def plain(cfg: Any) -> dict[str, Any]:
    """A config group (an OmegaConf node) as plain data, interpolations resolved; plain data as it is."""
    from omegaconf import DictConfig, OmegaConf

    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)  # type: ignore[return-value]


def build_models(cfg: Any, registry: Optional[Registry] = None) -> dict[str, Any]:
    """World, value, predictor and planner named by ``cfg`` (a composed config), built through the registry."""
    registry = registry or Registry()
    world = registry.create("world", plain(cfg.world))
    return {
        "world": world,
        "value": registry.create("value", plain(cfg.value), world=world),
        "predictor": registry.create("predictor", plain(cfg.predictor), world=world),
        "planner": registry.create("planner", plain(cfg.planner), world=world),
    }

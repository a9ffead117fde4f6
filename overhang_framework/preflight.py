"""Checks of a command line before Hydra runs it, each failure one line naming what is wrong.

Hydra reports a bad override with several lines, a hint and sometimes a
traceback; an appended key that nothing reads (``+planer=myopic``) it accepts
silently. :func:`check_command_line` composes the config the way the run will,
and turns every such mistake into one :class:`~overhang_framework.errors.OverhangError`:

* config-group choices that are not installed, all of them in one message;
* overrides that do not parse, keys that do not exist (with the closest
  existing key), appended keys that no part of the run reads, sweeps given
  without ``-m``;
* a run (or sweep) directory that cannot be written.
"""

from __future__ import annotations

import difflib
import os
import tempfile
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.errors import OverhangError, UnknownPluginError, UnknownPluginsError

#: Config groups the run selects by name.
GROUPS = ("world", "predictor", "planner", "value", "condition", "tasks")
#: Groups whose keys are the parameters of a registered factory; the registry checks those.
MODEL_GROUPS = ("world", "predictor", "planner", "value")

# Hydra's command-line flags that take the next word as their value.
_VALUE_FLAGS = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                "--config-dir", "-cd", "--experimental-rerun", "--shell-completion", "-sc"}
_INFO_TOPICS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}
# Flags after which Hydra prints something instead of running the job.
_INFO_FLAGS = {"--cfg", "-c", "--info", "-i", "--hydra-help", "--shell-completion", "-sc", "--resolve"}


def override_words(args: Sequence[str]) -> list[str]:
    """The config overrides among Hydra's command-line words (flags and their values removed)."""
    words, skip = [], False
    for i, arg in enumerate(args):
        if skip:
            skip = False
            continue
        if arg.startswith("-"):
            skip = arg in _VALUE_FLAGS or (
                arg in ("--info", "-i") and i + 1 < len(args) and args[i + 1] in _INFO_TOPICS)
            continue
        words.append(arg)
    return words


def is_multirun(args: Sequence[str]) -> bool:
    return any(a in ("-m", "--multirun") for a in args)


def runs_job(args: Sequence[str]) -> bool:
    """Whether Hydra would run the job (rather than print a config or help)."""
    return not any(a in _INFO_FLAGS for a in args)


def _parse(word: str):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    (override,) = OverridesParser.create().parse_overrides([word])
    return override


def check_group_choices(args: Sequence[str]) -> None:
    """Raise for every config-group choice that is not installed, all in one error.

    Overrides this cannot read (a glob sweep, a malformed word) are left for
    the later checks or for Hydra.
    """
    from overhang_framework.config import group_options

    known: dict[str, list[str]] = {}
    unknown: list[UnknownPluginError] = []
    for word in override_words(args):
        try:
            ov = _parse(word)
            if ov.key_or_group not in GROUPS or ov.is_delete() or ov.package:
                continue
            values = list(ov.sweep_string_iterator()) if ov.is_sweep_override() else [ov.value()]
        except Exception:
            continue
        group = ov.key_or_group
        for value in values:
            if not isinstance(value, str):
                continue
            if group not in known:
                known[group] = group_options(group)
            if value not in known[group] and all(e.name != value or e.kind != group for e in unknown):
                unknown.append(UnknownPluginError(group, value, known[group]))
    if len(unknown) == 1:
        raise unknown[0]
    if unknown:
        raise UnknownPluginsError(unknown)


def _variants(words: Sequence[str], multirun: bool) -> list[list[str]]:
    """Single-valued override lists that together use every value of every sweep (one compose each).

    Without ``-m`` the words are composed as given, so that Hydra's complaint
    about a sweep outside multirun surfaces. Sweeps that cannot be enumerated
    (globs, intervals for optimising sweepers) are dropped from the check.
    """
    if not multirun:
        return [list(words)]
    fixed: list[str] = []
    sweeps: list[tuple[int, list[str]]] = []
    for word in words:
        try:
            ov = _parse(word)
        except Exception:
            fixed.append(word)  # let the compose report it
            continue
        if not ov.is_sweep_override():
            fixed.append(word)
            continue
        try:
            values = [str(v) for v in ov.sweep_string_iterator()]
        except Exception:
            continue
        prefix = word.split("=", 1)[0]
        sweeps.append((len(fixed), [f"{prefix}={v}" for v in values]))
        fixed.append(sweeps[-1][1][0] if values else word)
    variants = [fixed]
    for pos, options in sweeps:
        for option in options[1:]:
            variant = list(fixed)
            variant[pos] = option
            variants.append(variant)
    return variants


def _key_error(full_key: str, cfg, problem: str = "unknown config key") -> str:
    """One line for a key that is not in ``cfg``: the closest existing key and the keys there."""
    from omegaconf import OmegaConf

    parent_path, _, leaf = full_key.rpartition(".")
    node = OmegaConf.select(cfg, parent_path) if parent_path else cfg
    where = f"keys of {parent_path}" if parent_path else "top-level keys"
    if parent_path in GROUPS and node is not None and node.get("name"):
        where = f"keys of {parent_path} {node.get('name')!r}"
    keys = sorted(str(k) for k in node.keys() if k != "hydra") if hasattr(node, "keys") else []
    close = difflib.get_close_matches(leaf, keys, n=1)
    hint = f" (did you mean '{(parent_path + '.') if parent_path else ''}{close[0]}'?)" if close else ""
    return f"{problem} '{full_key}'{hint}; {where}: {', '.join(keys) if keys else '(none)'}"


def _choices(words: Sequence[str]) -> list[str]:
    """The plain config-group choices among ``words`` (what decides which keys exist)."""
    out = []
    for word in words:
        try:
            ov = _parse(word)
        except Exception:
            continue
        if ov.key_or_group in GROUPS and not ov.is_sweep_override() and not ov.is_delete() \
                and not ov.is_add() and not ov.package:
            out.append(word)
    return out


def _one_line(text: str) -> str:
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith("See https://")]
    return "; ".join(lines)


def _compose(words: Sequence[str]):
    """Compose ``words`` and translate Hydra's errors into :class:`OverhangError`."""
    from hydra.errors import (
        ConfigCompositionException,
        HydraException,
        MissingConfigException,
        OverrideParseException,
    )
    from omegaconf.errors import OmegaConfBaseException

    from overhang_framework.config import compose_config

    try:
        return compose_config(words, return_hydra_config=True)
    except OverrideParseException as err:
        bad = next((w for w in words if not _parses(w)), None)
        what = f"cannot read the override '{bad}'" if bad else "cannot read an override"
        raise OverhangError(f"{what}: {_one_line(err)}; overrides are key=value, "
                            "+key=value (add), ~key (remove); see --help") from None
    except MissingConfigException as err:
        missing = err.missing_cfg_file or ""
        group, _, name = missing.rpartition("/")
        if group and err.options is not None:
            raise OverhangError(f"unknown {group} {name!r}; available: {', '.join(err.options) or '(none)'}") from None
        raise OverhangError(_one_line(err).split("; Config search path:")[0]) from None
    except ConfigCompositionException as err:
        cause = err.__cause__
        if isinstance(cause, OmegaConfBaseException) and getattr(cause, "full_key", None):
            raise OverhangError(_key_error(cause.full_key, compose_config(_choices(words)))) from None
        message = _one_line(err)
        if message.startswith("Ambiguous value for argument"):
            word = message.split("'")[1] if "'" in message else "?"
            key = word.split("=", 1)[0]
            raise OverhangError(f"'{word}' gives several values: add -m (--multirun) to sweep over "
                                f"them, or write {key}=[...] for a list") from None
        raise OverhangError(message) from None
    except HydraException as err:
        raise OverhangError(_one_line(err)) from None


def _parses(word: str) -> bool:
    try:
        _parse(word)
        return True
    except Exception:
        return False


def _check_appended(words: Sequence[str]) -> None:
    """An appended (``+key=value``) key that the run never reads is an error, not a silent no-op.

    Keys under a model group are checked later against the factory's
    parameters; an appended config group (``+experiment=x``) is fine.
    """
    from overhang_framework.config import group_options

    for word in words:
        if not word.startswith("+") or word.startswith("++"):
            continue
        key = word[1:].split("=", 1)[0].split("@", 1)[0]
        root = key.split(".")[0]
        if root == "hydra" or root in MODEL_GROUPS:
            continue
        if "." not in key and group_options(key):
            continue
        from overhang_framework.config import compose_config

        raise OverhangError(_key_error(key, compose_config(_choices(words)),
                                       problem="nothing reads the added config key"))


def check_writable(directory: str | os.PathLike) -> None:
    """Raise unless ``directory`` exists as a writable directory or can be created.

    Nothing is left behind: the check writes into the nearest existing
    ancestor and removes what it wrote.
    """
    path = Path(directory).expanduser().absolute()
    probe = path
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    try:
        if not probe.is_dir():
            raise NotADirectoryError(f"{probe} is not a directory")
        tmp = tempfile.mkdtemp(dir=probe, prefix=".overhang-write-check-")
        os.rmdir(tmp)
    except OSError as err:
        reason = err.strerror or str(err)
        raise OverhangError(f"cannot write the output directory '{path}' ({reason}); "
                            "choose another with hydra.run.dir=DIR (hydra.sweep.dir=DIR with -m)") from None


def check_command_line(args: Sequence[str]) -> None:
    """Everything that can be checked about a command line before Hydra starts the run."""
    check_group_choices(args)
    words = override_words(args)
    multirun = is_multirun(args)
    cfg = None
    for variant in _variants(words, multirun):
        cfg = _compose(variant)
    _check_appended(words)
    if cfg is not None:
        _check_groups_present(cfg)
    if cfg is not None and runs_job(args):
        _check_output_dir(cfg, multirun)


def _check_groups_present(cfg) -> None:
    from overhang_framework.config import group_options

    for group in GROUPS:
        if cfg.get(group) is None:
            raise OverhangError(f"the run needs a {group}; choose one with {group}=NAME "
                                f"(installed: {', '.join(group_options(group)) or '(none)'})")


def _check_output_dir(cfg, multirun: bool) -> None:
    from omegaconf import OmegaConf

    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    try:
        directory: Optional[str] = OmegaConf.select(cfg, key)
    except Exception:  # an interpolation only Hydra's runtime can resolve
        return
    if directory:
        check_writable(directory)

"""Checks of a command line before Hydra runs it, each failure one line naming what is wrong.

Hydra reports a bad override with several lines, a hint and sometimes a
traceback; an appended key that nothing reads (``+planer=myopic``) it accepts
silently; and by the time a run could refuse a value, Hydra has already made
its output directory. :func:`check_command_line` therefore composes the config
the way the run will, for every job of a sweep, and turns every mistake into
one :class:`~overhang_framework.errors.OverhangError` before anything is written:

* flags Hydra does not know, words that are not overrides;
* config-group choices that are not installed, all of them in one message;
* overrides that do not parse, keys that do not exist (all of them, each with
  the closest existing key), values of the wrong type, appended keys that no
  part of the run reads, sweeps given without ``-m``;
* values a model refuses (every job of a sweep is built once, not run);
* an output directory that is empty, cannot be written, holds another
  config's results or is being written by another run.

The other commands that take overrides (``participants``, ``fit``,
``fit.recovery``, ``experiment``, ``check``, ...) compose their own configs
through :func:`compose_checked`, which gives the same one line.
"""

from __future__ import annotations

import difflib
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Optional, Sequence

from overhang_framework.errors import OverhangError, UnknownPluginError, UnknownPluginsError, closest

#: Config groups the run selects by name.
GROUPS = ("world", "predictor", "planner", "value", "condition", "tasks")
#: Groups that choose several of the groups above at once (conf/model, conf/experiment).
PRESET_GROUPS = ("model", "experiment")
#: Groups whose keys are the parameters of a registered factory; the registry checks those.
MODEL_GROUPS = ("world", "predictor", "planner", "value")

# Hydra's command-line flags: those that take the next word as their value, and the rest.
_VALUE_FLAGS = {"--cfg", "-c", "--package", "-p", "--config-path", "-cp", "--config-name", "-cn",
                "--config-dir", "-cd", "--experimental-rerun", "--shell-completion", "-sc"}
_PLAIN_FLAGS = {"--multirun", "-m", "--run", "-r", "--resolve", "--hydra-help", "--version", "--help", "-h",
                "--info", "-i"}
_INFO_TOPICS = {"all", "config", "defaults", "defaults-tree", "plugins", "searchpath"}
_CFG_VALUES = ("job", "hydra", "all")
# Flags after which Hydra prints something instead of running the job.
_INFO_FLAGS = {"--cfg", "-c", "--info", "-i", "--hydra-help", "--shell-completion", "-sc", "--resolve",
               "--version"}
COMMANDS = ("plugins",)
#: Launcher configs of Hydra plugins that are optional extras: (package, extra).
OPTIONAL_LAUNCHERS = {"ray": ("hydra-ray-launcher", "ray"), "ray_aws": ("hydra-ray-launcher", "ray")}


def split_flags(args: Sequence[str]) -> tuple[list[str], list[str]]:
    """Hydra's flags (with their values) and the overrides, in their orders.

    Hydra wants its flags before the overrides; a user may write them anywhere.
    """
    flags, words, i = [], [], 0
    while i < len(args):
        arg = args[i]
        if arg.startswith("-"):
            flags.append(arg)
            takes = arg in _VALUE_FLAGS or (
                arg in ("--info", "-i") and i + 1 < len(args) and args[i + 1] in _INFO_TOPICS)
            if takes and i + 1 < len(args):
                flags.append(args[i + 1])
                i += 1
        else:
            words.append(arg)
        i += 1
    return flags, words


def override_words(args: Sequence[str]) -> list[str]:
    """The config overrides among Hydra's command-line words (flags and their values removed)."""
    return split_flags(args)[1]


def is_multirun(args: Sequence[str]) -> bool:
    return any(a in ("-m", "--multirun") for a in args)


def runs_job(args: Sequence[str]) -> bool:
    """Whether Hydra would run the job (rather than print a config or help)."""
    return not any(a in _INFO_FLAGS for a in args)


def check_flags(args: Sequence[str]) -> None:
    """Raise for a flag Hydra does not know, or a ``--cfg`` without one of its values."""
    flags, _ = split_flags(args)
    known = sorted(_VALUE_FLAGS | _PLAIN_FLAGS)
    i = 0
    while i < len(flags):
        flag = flags[i]
        if flag not in _VALUE_FLAGS and flag not in _PLAIN_FLAGS:
            close = difflib.get_close_matches(flag, known, n=1)
            hint = f" (did you mean {close[0]}?)" if close else ""
            raise OverhangError(f"unknown option {flag!r}{hint}; options: -m (--multirun), --cfg job|hydra|all, "
                                "--help, --hydra-help, --info, --version; anything else is key=value")
        if flag in ("--cfg", "-c"):
            value = flags[i + 1] if i + 1 < len(flags) else None
            if value not in _CFG_VALUES:
                raise OverhangError(f"{flag} takes one of {', '.join(_CFG_VALUES)}, got {value!r}")
        if flag in _VALUE_FLAGS or (flag in ("--info", "-i") and i + 1 < len(flags)
                                    and flags[i + 1] in _INFO_TOPICS):
            i += 1
        i += 1


def _parse(word: str):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    (override,) = OverridesParser.create().parse_overrides([word])
    return override


def _parses(word: str) -> bool:
    try:
        _parse(word)
        return True
    except Exception:
        return False


def check_words(words: Sequence[str], commands: Sequence[str] = COMMANDS) -> None:
    """Raise for a word that is not an override at all (``plugin``, ``=3``); ``commands`` are the words
    the command also takes, offered when one is close."""
    for word in words:
        if "=" not in word and not word.startswith("~"):
            close = difflib.get_close_matches(word, list(commands), n=1)
            hint = f"; did you mean the command '{close[0]}'?" if close else ""
            raise OverhangError(f"cannot read {word!r}: overrides are key=value, +key=value (add) or ~key "
                                f"(remove){hint} (see --help)")
        key = word.lstrip("+~").split("=", 1)[0]
        if not key:
            raise OverhangError(f"cannot read {word!r}: the override names no key; overrides are key=value "
                                "(see --help)")


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


def sweep_variants(words: Sequence[str], multirun: bool) -> list[list[str]]:
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


class Source:
    """Where a command's config comes from: the config ``name`` of the config directory ``directory``
    (None: the project's ``conf``, with the installed plugins' configs)."""

    def __init__(self, name: str = "config", directory: Optional[str] = None):
        self.name, self.directory = name, directory

    def _initialize(self):
        from hydra import initialize_config_dir
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()
        return initialize_config_dir(str(Path(self.directory).absolute()), version_base="1.3")

    def compose(self, words: Sequence[str] = (), hydra: bool = True):
        """The config composed with ``words`` (with Hydra's own node when ``hydra``); Hydra's exceptions as
        they come."""
        if self.directory is None:
            from overhang_framework.config import compose_config

            return compose_config(list(words), config_name=self.name, return_hydra_config=hydra)
        from hydra import compose

        with self._initialize():
            return compose(self.name, overrides=list(words), return_hydra_config=hydra)

    def is_group(self, key: str) -> bool:
        if self.directory is None:
            if key in GROUPS + PRESET_GROUPS:
                return True
            from overhang_framework.config import group_options

            return bool(group_options(key))
        from hydra.core.global_hydra import GlobalHydra

        with self._initialize():
            return bool(GlobalHydra.instance().config_loader().get_group_options(key))


MAIN = Source()


def _choices(words: Sequence[str], source: Source = MAIN) -> list[str]:
    """The plain config-group choices among ``words``, Hydra's own included (they decide which keys exist)."""
    out = []
    for word in words:
        try:
            ov = _parse(word)
        except Exception:
            continue
        key = ov.key_or_group
        if ov.is_sweep_override() or ov.is_delete() or ov.is_add() or ov.package or "." in key:
            continue
        if "/" in key or source.is_group(key):
            out.append(word)
    return out


def _base(words: Sequence[str], source: Source = MAIN):
    try:
        return source.compose(_choices(words, source))
    except Exception:
        return source.compose()


def _key_error(full_key: str, cfg, problem: str = "unknown config key") -> str:
    """One line for a key that is not in ``cfg``: the closest existing key and the keys there."""
    from omegaconf import OmegaConf

    parent_path, _, leaf = full_key.rpartition(".")
    node = OmegaConf.select(cfg, parent_path) if parent_path else cfg
    where = f"keys of {parent_path}" if parent_path else "top-level keys"
    if parent_path in GROUPS and node is not None and node.get("name"):
        where = f"keys of {parent_path} {node.get('name')!r}"
    hidden = {"hydra"} if not parent_path else set()
    keys = sorted(str(k) for k in node.keys() if k not in hidden) if hasattr(node, "keys") else []
    close = [k for k in closest(leaf, keys) if k != leaf]
    hint = f" (did you mean '{(parent_path + '.') if parent_path else ''}{close[0]}'?)" if close else ""
    return f"{problem} '{full_key}'{hint}; {where}: {', '.join(keys) if keys else '(none)'}"


def one_line(text, drop: tuple[str, ...] = ()) -> str:
    """``text`` (or an exception's message) on one line, without Hydra's and OmegaConf's pointer lines and
    without lines starting with any of ``drop``."""
    lines = [line.strip() for line in str(text).splitlines() if line.strip()]
    skip = ("See https://", "full_key:", "object_type=", *drop)
    return "; ".join(line for line in lines if not line.startswith(skip))


def _compose_error(words: Sequence[str], err: Exception, source: Source = MAIN) -> str:
    """The one line for a failed compose of ``words``."""
    from hydra.errors import ConfigCompositionException, MissingConfigException, OverrideParseException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    if isinstance(err, OverrideParseException):
        bad = next((w for w in words if not _parses(w)), None)
        what = f"cannot read the override '{bad}'" if bad else "cannot read an override"
        return (f"{what}: {one_line(err)}; overrides are key=value, +key=value (add), ~key (remove); "
                "see --help")
    if isinstance(err, MissingConfigException):
        group, _, name = (err.missing_cfg_file or "").rpartition("/")
        if group == "hydra/launcher" and name in OPTIONAL_LAUNCHERS:
            chosen = next((w.split("=", 1)[1] for w in words if w.startswith("hydra/launcher=")), name)
            package, extra = OPTIONAL_LAUNCHERS[name]
            return (f"hydra/launcher={chosen} needs {package}, which is not installed; it is the optional "
                    f"extra '{extra}': pip install -e '.[{extra}]'")
        if group and err.options is not None:
            return f"unknown {group} {name!r}; available: {', '.join(err.options) or '(none)'}"
        return one_line(err).split("; Config search path:")[0]
    if isinstance(err, ConfigCompositionException):
        cause = err.__cause__
        full_key = getattr(cause, "full_key", None)
        if isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and full_key:
            return _key_error(full_key, _base(words, source))
        if isinstance(cause, OmegaConfBaseException) and full_key:
            message = str(cause).splitlines()[0]
            return f"bad value for '{full_key}': {message}"
        message = one_line(err)
        if message.startswith("Could not override '") and "No match in the defaults list" in message:
            # a config group that this config does not use (Hydra advises appending it with +)
            return _key_error(message.split("'")[1], _base(words, source))
        if message.startswith("Ambiguous value for argument"):
            word = message.split("'")[1] if "'" in message else "?"
            key = word.split("=", 1)[0]
            return (f"'{word}' gives several values: add -m (--multirun) to sweep over them, or write "
                    f"{key}=[...] for a list")
        return message
    return one_line(err) or type(err).__name__


def _compose(words: Sequence[str], source: Source = MAIN):
    """Compose ``words``; on failure raise one :class:`OverhangError` naming every bad override."""
    try:
        return source.compose(words)
    except Exception as err:  # Hydra raises several kinds, some of them plain ValueErrors
        first = _compose_error(words, err, source)
    # report every bad override, not only the first Hydra stopped at
    choices = _choices(words, source)
    messages = [first]
    for word in words:
        if word in choices:
            continue
        try:
            source.compose([*choices, word])
        except Exception as err:
            message = _compose_error([*choices, word], err, source)
            if message not in messages:
                messages.append(message)
    raise OverhangError(" | ".join(messages))


def compose_checked(words: Sequence[str], config_name: str = "config", config_dir: Optional[str] = None,
                    return_hydra_config: bool = False, commands: Sequence[str] = ()):
    """The config ``config_name`` (of the directory ``config_dir``; None: the project's) composed with the override
    ``words`` as a command's Hydra app will compose it; otherwise one :class:`OverhangError` naming every bad
    override as the main command does: an unknown key with the closest existing one and the keys there, a
    word that does not parse, a group option that does not exist. ``commands``: the bare words the command
    also takes (offered when a word that is not an override is close to one). The error is a
    :class:`~overhang_framework.errors.ConfigError`."""
    from overhang_framework.errors import ConfigError

    source = Source(config_name, config_dir)
    try:
        check_words(words, commands)
        cfg = _compose(words, source)
    except ConfigError:
        raise
    except OverhangError as err:
        raise ConfigError(str(err)) from None
    return cfg if return_hydra_config else source.compose(words, hydra=False)


def _check_appended(words: Sequence[str]) -> None:
    """An added (``+key=value``, ``++key=value``) key that the run never reads is an error.

    Keys under a model group are checked later against the factory's
    parameters; an appended config group (``+experiment=x``) is fine.
    """
    from overhang_framework.config import group_options

    for word in words:
        if not word.startswith("+"):
            continue
        key = word.lstrip("+").split("=", 1)[0].split("@", 1)[0]
        root = key.split(".")[0]
        if root == "hydra" or root in MODEL_GROUPS:
            continue
        if "." not in key and group_options(key):
            continue
        if word.startswith("++") and _exists(key, words):
            continue
        raise OverhangError(_key_error(key, _base(words), problem="nothing reads the added config key"))


def _exists(key: str, words: Sequence[str]) -> bool:
    from omegaconf import OmegaConf

    return OmegaConf.select(_base(words), key, default=None) is not None


def check_writable(directory: str | os.PathLike,
                   choose: str = "hydra.run.dir=DIR (hydra.sweep.dir=DIR with -m)") -> None:
    """Raise unless ``directory`` exists as a writable directory or can be created.

    Nothing is left behind: the check writes into the nearest existing
    ancestor and removes what it wrote. ``choose`` says how the command
    takes another directory.
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
                            f"choose another with {choose}") from None


def check_command_line(args: Sequence[str], check_config: Optional[Callable] = None) -> None:
    """Everything that can be checked about a command line before Hydra starts the run.

    ``check_config``, when given, is called with every job's composed config
    to check its values (the main job builds its models, without running them).
    """
    check_flags(args)
    words = override_words(args)
    check_words(words)
    check_group_choices(args)
    from_config, config_sweeps = _config_sweep(words)
    multirun = is_multirun(args) or from_config  # an experiment config may sweep (hydra.mode: MULTIRUN)
    if multirun:
        words = [*words, *config_sweeps]
    configs = [_compose(variant) for variant in sweep_variants(words, multirun)]
    _check_appended(words)
    for cfg in configs:
        _check_groups_present(cfg)
    if not runs_job(args):
        return
    if multirun:
        _check_launcher(configs[0])
    if check_config is not None:
        for cfg in configs:
            check_config(cfg)
    _check_output_dir(configs[0], multirun)


def overrides_problem(overrides: Sequence[str]) -> Optional[str]:
    """What is wrong with the config ``overrides`` of a command that composes a run config but runs no
    Hydra job (a benchmark, an analysis), in one line; ``None`` when nothing is."""
    from overhang_framework.errors import OverhangError

    try:
        check_command_line([*overrides, "--cfg", "job"])
    except OverhangError as err:
        return str(err)
    return None


def _config_sweep(words: Sequence[str]) -> tuple[bool, list[str]]:
    """Whether the chosen configs make the command a multirun (``hydra.mode: MULTIRUN``), and the
    sweeps their ``hydra.sweeper.params`` add (as override words; a key the command line sets wins)."""
    from omegaconf import OmegaConf

    try:
        cfg = _base(words)
        mode = str(OmegaConf.select(cfg, "hydra.mode", default="") or "")
        params = OmegaConf.select(cfg, "hydra.sweeper.params", default=None) or {}
    except Exception:
        return False, []
    given = set()
    for word in words:
        try:
            given.add(_parse(word).key_or_group)
        except Exception:
            continue
    extra = [f"{key}={value}" for key, value in params.items() if key.lstrip("+") not in given]
    return mode.endswith("MULTIRUN"), extra


def _check_launcher(cfg) -> None:
    """Launcher settings Hydra would only refuse with a traceback once the sweep has started."""
    from omegaconf import OmegaConf

    n_jobs = OmegaConf.select(cfg, "hydra.launcher.n_jobs", default=None)
    if n_jobs is not None and (isinstance(n_jobs, bool) or not isinstance(n_jobs, int) or n_jobs == 0):
        raise OverhangError(f"hydra.launcher.n_jobs must be a whole number other than 0 (-1: one job per "
                            f"core), got {n_jobs!r}")
    # hydra-ray-launcher asks ray.init() for a 75 MB object store unless the key is there (even as null),
    # and Ray refuses any object-store size when it joins a running cluster: say so before the sweep starts.
    target = str(OmegaConf.select(cfg, "hydra.launcher._target_", default="") or "")
    init = OmegaConf.select(cfg, "hydra.launcher.ray.init", default=None)
    if target.endswith(".RayLauncher") and init is not None and init.get("address") not in (None, "local") \
            and "object_store_memory" not in init:
        raise OverhangError("joining a running Ray cluster (hydra.launcher.ray.init.address) also needs "
                            "+hydra.launcher.ray.init.object_store_memory=null: the Ray launcher otherwise asks "
                            "for an object store of its own size, which Ray refuses for a running cluster")


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
    if directory is None or not str(directory).strip():
        raise OverhangError(f"{key} is empty; give the directory the results go to, e.g. {key}=runs/mine")
    check_writable(directory)
    if not multirun:
        from overhang_framework.rundir import RunDir, result_config

        plain = OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]),
                                       resolve=True)
        rundir = RunDir(directory)
        rundir.check_free()
        rundir.check_config(result_config(plain), overwrite=bool(plain.get("overwrite") is True))


def check_app_command(args: Sequence[str], config_name: str, check_config: Callable,
                      check_output: Optional[Callable] = None) -> None:
    """The checks of a Hydra command with its own primary config (``config_name``) before Hydra runs it:
    its flags, its overrides, every job's composed config (``check_config``, when a job runs); and, for a
    single run, ``check_output(cfg, run_dir)`` before Hydra writes anything into its run directory."""
    check_flags(args)
    words = override_words(args)
    check_group_choices(args)
    multirun = is_multirun(args)
    configs = [compose_checked(v, config_name=config_name) for v in sweep_variants(words, multirun)]
    if not runs_job(args):
        return
    for cfg in configs:
        check_config(cfg)
    if check_output is not None and not multirun:
        from omegaconf import OmegaConf

        full = compose_checked(words, config_name=config_name, return_hydra_config=True)
        try:
            directory = OmegaConf.select(full, "hydra.run.dir")
        except Exception:  # an interpolation only Hydra's runtime can resolve: a new directory
            return
        if directory:
            check_output(configs[0], Path(str(directory)))


def run_app_command(argv: Optional[Sequence[str]], app: Callable, config_name: Optional[str],
                    check_config: Optional[Callable], doc: str, check_output: Optional[Callable] = None,
                    check: Optional[Callable[[list], None]] = None,
                    words: Callable[[list], list] = list, interrupted: Optional[str] = None) -> None:
    """A Hydra command's ``main``: ``--help`` prints ``doc``; a mistake on the command line (or, with
    ``check_output``, a run directory the run must not write into) is one line and exit status 2 before
    Hydra starts; otherwise Hydra runs ``app`` with its flags put first. ``words`` turns the command line into
    Hydra's words (a command's own options into overrides); ``check`` checks them in place of
    :func:`check_app_command` of ``config_name`` and ``check_config``; ``interrupted``, when given, is said on a
    Ctrl-C during the check (exit status 130)."""
    import sys

    args = list(sys.argv[1:] if argv is None else argv)
    if "--help" in args or "-h" in args:
        print(doc)
        return
    try:
        args = list(words(args))
        if check is not None:
            check(args)
        else:
            check_app_command(args, config_name, check_config, check_output)
    except (OverhangError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        if interrupted is None:
            raise
        print(interrupted, file=sys.stderr)
        sys.exit(130)
    flags, rest = split_flags(args)
    sys.argv = [sys.argv[0]] + flags + rest
    app()


def job_result(run: Callable, interrupted: Callable[[], str], log) -> Any:
    """``run()`` inside a Hydra job: a user's mistake is one line (exit status 2, or ``None`` in a sweep, so
    the sweep's other jobs go on); Ctrl-C says what was kept (``interrupted()``) and exits 130."""
    import sys

    from overhang_framework.config import in_sweep

    try:
        return run()
    except OverhangError as err:
        log.error("%s", err)
        print(f"error: {err}", file=sys.stderr)
        if in_sweep():
            return None
        sys.exit(2)
    except KeyboardInterrupt:
        print(interrupted(), file=sys.stderr)
        sys.exit(130)

"""Command-line entry: the help page, the ``plugins`` listing, the pre-run checks, then the Hydra app."""

from __future__ import annotations

import json
import os
import sys
from typing import Optional, Sequence

from overhang_framework.errors import OverhangError
from overhang_framework.preflight import (
    GROUPS,
    PRESET_GROUPS,
    check_command_line,
    check_group_choices,
    override_words,
    split_flags,
)

__all__ = ["GROUPS", "check_overrides", "help_text", "list_plugins", "main", "override_words"]

PROG = "python -m overhang_framework"


def list_plugins(as_json: bool = False) -> str:
    from overhang_framework.plugins import describe_plugins

    rows = describe_plugins()
    if as_json:
        return json.dumps(rows, indent=2)
    lines = []
    for row in rows:
        lines.append(f"{row['plugin']}  ({row['package']} {row['version']})".rstrip())
        for kind, names in row["registers"].items():
            lines.append(f"  {kind + 's':<12}{', '.join(names)}")
        for path in row["config_paths"]:
            lines.append(f"  {'configs':<12}{path}")
    return "\n".join(lines)


def check_overrides(args: Sequence[str]) -> None:
    """Raise for config-group choices that are not installed (all of them in one error)."""
    check_group_choices(args)


def help_text() -> str:
    """The ``--help`` page: what the program does, the groups with their installed names, examples, outputs."""
    from overhang_framework.config import compose_config, group_options

    defaults = compose_config()
    width = max(len(g) for g in GROUPS) + 2
    groups = []
    for group in GROUPS:
        names = group_options(group)
        default = defaults[group].get("name")
        listed = ", ".join(f"{n} (default)" if n == default else n for n in names)
        groups.append(f"  {group:<{width}}{listed}")
    presets = [f"  {group:<{width}}{', '.join(group_options(group))}" for group in PRESET_GROUPS]
    settings = ", ".join(f"{k}={json.dumps(defaults[k])}" for k in defaults if k not in GROUPS)
    return f"""\
overhang-framework: run the Overhang Tower task with pluggable physics predictors and planners.

An agent places a known sequence of blocks to maximise the tower's overhang while
it stays stable after every placement. Each run plays every task of a task set,
with the world, predictor, planner and value chosen by name, and writes one
record per episode plus a summary.

usage:
  {PROG} [key=value ...]          run once (console script: overhang-framework)
  {PROG} -m key=a,b ...           sweep: one run per combination (Hydra multirun)
  {PROG} plugins [--json]         list installed plugins and what they register
  {PROG} --cfg job [key=value]    print the composed config without running

config groups (group=name; installed names):
{chr(10).join(groups)}

presets (a paper model: planner and settings; an experiment: a whole paper result, e.g. Table 2):
{chr(10).join(presets)}

other settings: {settings}
  any key can be set: world.resolution=0.05, predictor.K=100, world.pybullet.threshold=0.1

examples:
  {PROG} tasks=example seed=1 hydra.run.dir=runs/example
  {PROG} predictor=ipe 'tasks.only=[paper00,paper07]' repeats=5
  {PROG} tasks=custom 'tasks.sequences=[[0.6,1.8,1.2],[1.2,1.2,0.6,1.8]]'
  {PROG} -m predictor=veridical,ipe condition=unconstrained,time_limited hydra/launcher=joblib
  {PROG} experiment=table2_quick

outputs (in hydra.run.dir, by default outputs/<date>/<time>):
  episodes.jsonl   one JSON object per episode, every placement with its timing and spend
  metrics.json     mean and SEM of reward, stability, overhang and decision time (and its median, max)
  run.json         the config the episodes belong to (rerunning into the directory resumes)
  run.log          one line per episode, and how the run ended
  .hydra/          the composed config and the overrides
  .run.lock        exists while a run writes the directory

An interrupted run keeps every finished episode: rerun the same command with the
same hydra.run.dir to continue; overwrite=true starts the directory afresh.
Hydra's own flags: --hydra-help. Version: --version."""


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    import hydra

    try:
        ours = version("overhang-framework")
    except PackageNotFoundError:
        ours = "(not installed)"
    return f"overhang-framework {ours} (Hydra {hydra.__version__})"


def _plugins_command(args: Sequence[str]) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog=f"{PROG} plugins", add_help=True,
                                     description="List installed plugins and what they register.")
    parser.add_argument("--json", action="store_true", help="print JSON")
    options, extra = parser.parse_known_args(list(args))
    if extra:
        raise OverhangError(f"plugins takes only --json, got {' '.join(extra)}")
    print(list_plugins(as_json=options.json))


def main(argv: Optional[Sequence[str]] = None) -> None:
    args = list(sys.argv[1:] if argv is None else argv)
    try:
        if argv is None:  # the process's own command line: a Ctrl-C that Python drops still stops the run
            from overhang_framework.interrupts import remember_ctrl_c

            with remember_ctrl_c():
                _main(args)
        else:
            _main(args)
    except KeyboardInterrupt:
        print("interrupted before the first episode; nothing was written", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:
        # the reader went away (``... | head``): stop quietly, as command-line tools do
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(1)


def _runs_here(cfg) -> bool:
    """Whether Hydra runs this config's job in this process (a single run or the basic launcher's
    sweep), so that the models its check built can be handed to it; other launchers' jobs build their own."""
    from omegaconf import OmegaConf

    target = str(OmegaConf.select(cfg, "hydra.launcher._target_", default="") or "")
    return target.endswith(".BasicLauncher")


def _main(args: list[str]) -> None:
    try:
        if args and args[0] == "plugins":
            _plugins_command(args[1:])
            return
        if "--help" in args or "-h" in args:
            print(help_text())
            return
        if "--version" in args:
            print(_version())
            return
        from overhang_framework.app import check_config, forget_kept_models

        forget_kept_models()
        check_command_line(args, check_config=lambda cfg: check_config(cfg, keep=_runs_here(cfg)))
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    from overhang_framework.app import main as app_main

    flags, words = split_flags(args)
    sys.argv = [sys.argv[0]] + flags + words  # Hydra wants its flags first
    app_main()

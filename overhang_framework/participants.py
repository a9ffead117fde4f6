"""Simulated participants: ``python -m overhang_framework.participants [OVERRIDES...]``.

A cohort of model agents (config ``conf/participants.yaml``, cohorts in
``conf/cohort/``) does the experiment; the run directory (``hydra.run.dir``)
gets ``log.jsonl``, the behaviour log, and ``participants.csv``, each
participant's true parameters, both written atomically. Overrides, ``-m``
sweeps and launchers work as for the main job; a bad config stops the command
before anything runs with one ``error: ...`` line and exit status 2. The
science is in :mod:`overhang_framework.behaviour.participants`; the model and
every key: ``docs/participants.md``.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional, Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from overhang_framework.behaviour.log import write_log
from overhang_framework.behaviour.participants import (
    Agents,
    Cohort,
    cohort_from_config,
    condition_summary,
    format_summary,
    participants_csv,
    simulate,
)
from overhang_framework.config import CONFIG_PATH, enable_plugin_configs, in_sweep
from overhang_framework.errors import ConfigError, OverhangError
from overhang_framework.plugins import Registry
from overhang_framework.progress import progress_bar
from overhang_framework.results import atomic_write_text
from overhang_framework.tasks import tasks_from_config

enable_plugin_configs()
log = logging.getLogger("overhang_framework.participants")
PROG = "python -m overhang_framework.participants"
CONFIG_NAME = "participants"


@dataclass
class Checked:
    """A participants config with every value checked and the shared models built."""

    seed: int
    progress: bool
    cohort: Cohort
    tasks: list
    models: dict
    agents: Agents


def _plain(node) -> Any:
    return OmegaConf.to_container(node, resolve=True) if node is not None else None


def check_config(cfg: DictConfig) -> Checked:
    """Check every value of ``cfg`` and build what the run shares (nothing runs); :class:`OverhangError` otherwise."""
    top = ("world", "predictor", "planner", "value", "tasks", "conditions", "cohort", "seed", "progress")
    extra = [k for k in cfg if k not in top and k != "hydra"]
    if extra:
        raise ConfigError(f"unknown config key '{extra[0]}'; top-level keys: {', '.join(sorted(top))}")
    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a whole number >= 0, got {seed!r}")
    if not isinstance(cfg.get("progress"), bool):
        raise ConfigError(f"progress must be true or false, got {cfg.get('progress')!r}")
    cohort = cohort_from_config(_plain(cfg.cohort), _plain(cfg.conditions) or {})
    tasks = tasks_from_config(cfg.tasks)
    registry = Registry()
    world = registry.create("world", _plain(cfg.world))
    models = {"world": world, "value": registry.create("value", _plain(cfg.value), world=world)}
    agents = Agents(registry, world, _plain(cfg.predictor), _plain(cfg.planner), cohort)
    # build the first participant's agent, so that a value the models refuse stops the command here
    from overhang_framework.behaviour.participants import draw_participants

    agents.build(draw_participants(cohort, seed)[0])
    return Checked(seed, cfg.progress, cohort, tasks, models, agents)


def run(cfg: DictConfig, out_dir: Path) -> dict:
    """Simulate the cohort of ``cfg``; write ``log.jsonl`` and ``participants.csv`` into ``out_dir``."""
    checked = check_config(cfg)
    cohort = checked.cohort
    n_tasks = len(checked.tasks[: cohort.n_tasks] if cohort.n_tasks else checked.tasks)
    bar = progress_bar(total=cohort.size * n_tasks, desc="trials", unit="trial", disable=not checked.progress,
                       miniters=1, mininterval=0.5, dynamic_ncols=True)

    def on_trial(participant, task) -> None:
        bar.set_postfix_str(f"{participant.id} {task.id}")
        bar.update(1)

    try:
        sim = simulate(cohort, checked.tasks, checked.models, checked.agents, checked.seed, on_trial=on_trial)
    finally:
        bar.close()
    out_dir.mkdir(parents=True, exist_ok=True)
    write_log(sim.records, out_dir / "log.jsonl")
    atomic_write_text(out_dir / "participants.csv", participants_csv(sim.participants))
    rows = condition_summary(sim.records)
    log.info("wrote %d records of %d participants to %s", len(sim.records), len(sim.participants), out_dir)
    return {"records": len(sim.records), "participants": len(sim.participants), "conditions": rows}


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name=CONFIG_NAME)
def app(cfg: DictConfig) -> Optional[dict]:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        summary = run(cfg, out_dir)
    except OverhangError as err:
        log.error("%s", err)
        print(f"error: {err}", file=sys.stderr)
        if in_sweep():
            return None
        sys.exit(2)
    except KeyboardInterrupt:
        print(f"interrupted: nothing was written to {out_dir} (the log is written when every trial is done)",
              file=sys.stderr)
        sys.exit(130)
    print(format_summary(summary["conditions"]))
    print(f"{summary['records']} records of {summary['participants']} participants: {out_dir}")
    return summary


def _one_line(err: BaseException) -> str:
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    lines = [line for line in lines if not line.startswith(("See https://", "full_key:", "object_type=",
                                                           "Config search path", "Available options"))]
    return "; ".join(lines) or type(err).__name__


def _compose_error(err: BaseException) -> str:
    """One line for a failed compose: an unknown key with the closest existing one, else Hydra's words."""
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError

    from overhang_framework.config import compose_config
    from overhang_framework.errors import closest

    cause = err.__cause__
    full_key = getattr(cause, "full_key", None)
    if not (isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and full_key):
        return _one_line(err)
    parent, _, leaf = str(full_key).rpartition(".")
    base = compose_config(config_name=CONFIG_NAME)
    node = OmegaConf.select(base, parent) if parent else base
    keys = sorted(str(k) for k in node.keys()) if hasattr(node, "keys") else []
    close = closest(leaf, keys)
    hint = f" (did you mean '{(parent + '.') if parent else ''}{close[0]}'?)" if close else ""
    return f"unknown config key '{full_key}'{hint}; {f'keys of {parent}' if parent else 'top-level keys'}: " \
           f"{', '.join(keys) or '(none)'}"


def preflight(args: Sequence[str]) -> None:
    """Compose every job's config and check its values before Hydra runs (one :class:`OverhangError` otherwise)."""
    from overhang_framework.config import compose_config
    from overhang_framework.preflight import (check_flags, check_group_choices, check_writable, is_multirun,
                                              override_words, runs_job)

    check_flags(args)
    words = override_words(args)
    check_group_choices(args)
    variants = _sweep_variants(words) if is_multirun(args) else [list(words)]
    configs = []
    for variant in variants:
        try:
            configs.append(compose_config(variant, config_name=CONFIG_NAME, return_hydra_config=True))
        except Exception as err:  # Hydra raises several kinds
            raise OverhangError(_compose_error(err)) from None
    if not runs_job(args):
        return
    for cfg in configs:
        check_config(cfg)
    key = "hydra.sweep.dir" if is_multirun(args) else "hydra.run.dir"
    try:
        directory = OmegaConf.select(configs[0], key)
    except Exception:  # an interpolation only Hydra's runtime resolves (${now:...})
        return
    if directory is not None:
        check_writable(directory)


def _sweep_variants(words: Sequence[str]) -> list[list[str]]:
    """Single-valued override lists that together use every value of every simple sweep (``key=a,b``)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parser = OverridesParser.create()
    variants: list[list[str]] = [[]]
    for word in words:
        try:
            (ov,) = parser.parse_overrides([word])
            values = [str(v) for v in ov.sweep_string_iterator()] if ov.is_sweep_override() else None
        except Exception:
            values = None
        if values is None:
            variants = [v + [word] for v in variants]
        else:
            prefix = word.split("=", 1)[0]
            variants = [v + [f"{prefix}={value}"] for v in variants for value in values]
    return variants


def main(argv: Optional[Sequence[str]] = None) -> None:
    from overhang_framework.preflight import split_flags

    args = list(sys.argv[1:] if argv is None else argv)
    if "--help" in args or "-h" in args:
        print(__doc__)
        return
    try:
        preflight(args)
    except OverhangError as err:
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted before the first trial; nothing was written", file=sys.stderr)
        sys.exit(130)
    flags, words = split_flags(args)
    sys.argv = [sys.argv[0]] + flags + words  # Hydra wants its flags first
    app()


if __name__ == "__main__":
    main()

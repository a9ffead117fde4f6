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

import json
import logging
import shutil
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
    Participant,
    cohort_from_config,
    cohort_tasks,
    condition_summary,
    draw_participants,
    format_summary,
    participants_csv,
    simulate_participant,
)
from overhang_framework.config import CONFIG_PATH, enable_plugin_configs
from overhang_framework.errors import ConfigError
from overhang_framework.plugins import Registry
from overhang_framework.progress import progress_bar
from overhang_framework.results import atomic_write_text
from overhang_framework.rundir import RunDir, result_config
from overhang_framework.tasks import tasks_from_config

enable_plugin_configs()
log = logging.getLogger("overhang_framework.participants")
PROG = "python -m overhang_framework.participants"
CONFIG_NAME = "participants"
#: What the run directory gets: the log, the participants' parameters, and (while running) finished participants.
LOG, CSV, PARTS = "log.jsonl", "participants.csv", "parts"


@dataclass
class Checked:
    """A participants config with every value checked and the shared models built."""

    seed: int
    progress: bool
    jobs: int
    cohort: Cohort
    tasks: list
    models: dict
    agents: Agents


def _plain(node) -> Any:
    return OmegaConf.to_container(node, resolve=True) if node is not None else None


def check_config(cfg: DictConfig) -> Checked:
    """Check every value of ``cfg`` and build what the run shares (nothing runs); :class:`OverhangError` otherwise."""
    top = ("world", "predictor", "planner", "value", "tasks", "conditions", "cohort", "seed", "progress", "jobs",
           "overwrite")
    extra = [k for k in cfg if k not in top and k != "hydra"]
    if extra:
        raise ConfigError(f"unknown config key '{extra[0]}'; top-level keys: {', '.join(sorted(top))}")
    seed = cfg.get("seed")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"seed must be a whole number >= 0, got {seed!r}")
    for key in ("progress", "overwrite"):
        if not isinstance(cfg.get(key), bool):
            raise ConfigError(f"{key} must be true or false, got {cfg.get(key)!r}")
    jobs = cfg.get("jobs")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ConfigError(f"jobs must be a whole number >= 1 (worker processes), got {jobs!r}")
    cohort = cohort_from_config(_plain(cfg.cohort), _plain(cfg.conditions) or {})
    tasks = tasks_from_config(cfg.tasks)
    registry = Registry()
    world = registry.create("world", _plain(cfg.world))
    models = {"world": world, "value": registry.create("value", _plain(cfg.value), world=world)}
    agents = Agents(registry, world, _plain(cfg.predictor), _plain(cfg.planner), cohort)
    # build the first participant's agent, so that a value the models refuse stops the command here
    agents.build(draw_participants(cohort, seed)[0])
    return Checked(seed, cfg.progress, jobs, cohort, tasks, models, agents)


def _worker_setup(config: dict) -> Checked:
    return check_config(OmegaConf.create(config))


def _worker_simulate(checked: Checked, index: int) -> list[dict]:
    from overhang_framework.parallel import tick

    participant = draw_participants(checked.cohort, checked.seed)[index]
    tasks = cohort_tasks(checked.cohort, checked.tasks)
    return simulate_participant(participant, checked.cohort, tasks, checked.models, checked.agents, checked.seed,
                                on_trial=lambda *_: tick())


def _read_part(path: Path) -> Optional[list[dict]]:
    """A finished participant's records from ``path``, or None when the file is not whole."""
    try:
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    except (OSError, ValueError):
        return None


def run(cfg: DictConfig, out_dir: Path) -> dict:
    """Simulate the cohort of ``cfg``; write ``log.jsonl`` and ``participants.csv`` into ``out_dir``.

    Each participant's records are kept in ``out_dir/parts/`` as it finishes, so
    a run that stops (Ctrl-C, a crash, a time limit) continues where it was
    when run again into the same directory with the same config; the parts are
    removed once the log is written.
    """
    checked = check_config(cfg)
    cohort = checked.cohort
    tasks = cohort_tasks(cohort, checked.tasks)
    participants = draw_participants(cohort, checked.seed)
    config = result_config({k: v for k, v in _plain(cfg).items() if k != "hydra"})
    rundir = RunDir(out_dir)
    parts = out_dir / PARTS
    with rundir.lock():
        rundir.prepare(config, overwrite=cfg.overwrite)
        if cfg.overwrite:
            shutil.rmtree(parts, ignore_errors=True)
            for name in (LOG, CSV):
                (out_dir / name).unlink(missing_ok=True)
        done: dict[int, list[dict]] = {}
        if parts.is_dir():
            for p in participants:
                records = _read_part(parts / f"{p.id}.jsonl")
                if records is not None:
                    done[p.index] = records
        if (out_dir / LOG).exists() and not done:
            records = _read_part(out_dir / LOG)
            if records is not None:
                log.info("%s is already complete for this config", out_dir / LOG)
                return {"records": len(records), "participants": len(participants),
                        "conditions": condition_summary(records), "resumed": len(participants)}
        if done:
            log.info("continuing: %d of %d participants already simulated in %s", len(done), len(participants), parts)
        todo = [p for p in participants if p.index not in done]
        bar = progress_bar(total=len(participants) * len(tasks), initial=len(done) * len(tasks), desc="trials",
                           unit="trial", disable=not checked.progress, miniters=1, mininterval=0.5,
                           dynamic_ncols=True)

        def keep(participant: Participant, records: list[dict]) -> None:
            parts.mkdir(parents=True, exist_ok=True)
            atomic_write_text(parts / f"{participant.id}.jsonl",
                              "".join(json.dumps(r) + "\n" for r in records))
            done[participant.index] = records

        try:
            if checked.jobs > 1 and len(todo) > 1:
                from overhang_framework.parallel import pool_map

                by_index = {p.index: p for p in todo}
                for index, records, _ in pool_map(_worker_setup, (_plain(cfg),), _worker_simulate,
                                                  [p.index for p in todo], min(checked.jobs, len(todo)),
                                                  on_tick=lambda: bar.update(1)):
                    keep(by_index[index], records)
                    bar.set_postfix_str(f"{len(done)}/{len(participants)} participants")
            else:
                def on_trial(participant, task) -> None:
                    bar.set_postfix_str(f"{participant.id} {task.id}")
                    bar.update(1)

                for p in todo:
                    keep(p, simulate_participant(p, cohort, tasks, checked.models, checked.agents, checked.seed,
                                                 on_trial))
        finally:
            bar.close()
        records = [r for p in participants for r in done[p.index]]
        write_log(records, out_dir / LOG)
        atomic_write_text(out_dir / CSV, participants_csv(participants))
        shutil.rmtree(parts, ignore_errors=True)
    log.info("wrote %d records of %d participants to %s", len(records), len(participants), out_dir)
    return {"records": len(records), "participants": len(participants), "conditions": condition_summary(records)}


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name=CONFIG_NAME)
def app(cfg: DictConfig) -> Optional[dict]:
    from overhang_framework.preflight import job_result

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    summary = job_result(lambda: run(cfg, out_dir), lambda: f"interrupted: the participants already simulated are "
                         f"kept in {out_dir / PARTS}; run the same command into {out_dir} to continue", log)
    if summary is None:
        return None
    print(format_summary(summary["conditions"]))
    print(f"{summary['records']} records of {summary['participants']} participants: {out_dir}")
    return summary


def preflight(args: Sequence[str]) -> None:
    """Compose every job's config and check its values before Hydra runs (one :class:`OverhangError` otherwise)."""
    from overhang_framework.preflight import (check_flags, check_group_choices, check_writable, compose_checked,
                                              is_multirun, override_words, runs_job, sweep_variants)

    check_flags(args)
    words = override_words(args)
    check_group_choices(args)
    variants = sweep_variants(words, is_multirun(args))
    configs = [compose_checked(variant, config_name=CONFIG_NAME, return_hydra_config=True) for variant in variants]
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


def main(argv: Optional[Sequence[str]] = None) -> None:
    from overhang_framework.preflight import run_app_command

    run_app_command(argv, app, None, None, __doc__, check=preflight,
                    interrupted="interrupted before the first trial; nothing was written")


if __name__ == "__main__":
    main()

"""The main job: compose the models from config, run every episode, write the results."""

from __future__ import annotations

import json
import logging
import signal
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Optional

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from overhang_framework.advice import run_notes
from overhang_framework.config import CONFIG_PATH, enable_plugin_configs, in_sweep
from overhang_framework.episode import play_run_episode
from overhang_framework.errors import ConfigError, OverhangError, first_line
from overhang_framework.interrupts import raising, stop_if_ctrl_c
from overhang_framework.parallel import merge_stats
from overhang_framework.episode import play_episodes
from overhang_framework.physics.pool import PoolCrashed
from overhang_framework import plugins
from overhang_framework.moved import forwarder
from overhang_framework.progress import progress_bar
from overhang_framework.results import EpisodeLog, atomic_write_json, readable, summarize
from overhang_framework.rundir import RunDir, finished_jobs, result_config
from overhang_framework.tasks import tasks_from_config

enable_plugin_configs()
log = logging.getLogger("overhang_framework")


_params = plugins.plain


__getattr__ = forwarder(__name__, [plugins], only=("build_models",))


def _whole(cfg: DictConfig, key: str, minimum: int) -> int:
    value = cfg.get(key)
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{key} must be a whole number >= {minimum}, got {value!r}")
    return value


def _time_limit(cfg: DictConfig) -> float | None:
    value = cfg.condition.get("time_limit")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)) or value <= 0:
        raise ConfigError(f"condition.time_limit must be a number of seconds > 0 or null, got {value!r}")
    return float(value)


def _flag(cfg: DictConfig, key: str, default: bool) -> bool:
    value = cfg.get(key, default)
    if not isinstance(value, bool):
        raise ConfigError(f"{key} must be true or false, got {value!r}")
    return value


def tasks_label(cfg: DictConfig, tasks: list) -> str:
    """The task set's name, with the ids picked when ``tasks.only`` narrowed it."""
    name = str(cfg.tasks.get("name"))
    return f"{name}[{','.join(t.id for t in tasks)}]" if cfg.tasks.get("only") else name


class Interrupted(Exception):
    """The run stopped (Ctrl-C, SIGTERM) after ``finished`` of ``expected`` episodes."""

    def __init__(self, finished: int, expected: int, kept: Path, how: str = "interrupted",
                 overwrite: bool = False):
        self.finished, self.expected, self.kept, self.how, self.overwrite = finished, expected, kept, how, overwrite
        super().__init__(f"{finished} of {expected} episodes finished")


class Stopped(Exception):
    """The run stopped on ``error`` after ``finished`` of ``expected`` episodes."""

    def __init__(self, error: BaseException, finished: int, expected: int, kept: Path):
        self.error, self.finished, self.expected, self.kept = error, finished, expected, kept
        super().__init__(str(error))


def run(cfg: DictConfig, out_dir: Path) -> dict:
    """Run every (task, repeat) episode of ``cfg`` into ``out_dir``; return the summary (see :func:`run_unlocked`).

    A second run into the same directory at the same time is refused.
    """
    with RunDir(out_dir).lock():
        return run_unlocked(cfg, out_dir)


def _call_limit(cfg: DictConfig) -> int | None:
    value = cfg.condition.get("call_limit")
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ConfigError(f"condition.call_limit must be a whole number of predictor calls >= 1 or null, "
                          f"got {value!r}")
    return value


@dataclass
class Checked:
    """A run config whose every value was checked: the settings, the tasks and the built models."""

    seed: int
    repeats: int
    time_limit: Optional[float]
    call_limit: Optional[int]
    progress: bool
    overwrite: bool
    jobs: int
    tasks: list
    models: dict


#: Models that the command-line check built, by the config that names them; a run of an equal config
#: in the same process takes one set instead of building its own again (see :func:`check_config`).
_kept_models: dict[str, list[dict[str, Any]]] = {}


def _models_key(cfg: DictConfig) -> str:
    return json.dumps([_params(cfg[group]) for group in ("world", "value", "predictor", "planner")],
                      sort_keys=True, default=str)


def forget_kept_models() -> None:
    """Drop the models kept by earlier checks (a new command starts from none)."""
    _kept_models.clear()


def check_config(cfg: DictConfig, keep: bool = False) -> Checked:
    """Check every value of ``cfg`` and build its models (nothing runs, nothing is written).

    With ``keep``, the built models are kept for the run of an equal config
    that follows in this process: loading a CNN checkpoint or starting a
    physics client then happens once per job, not twice. Without it, models
    kept for an equal config are taken (each set once) instead of built.

    Raises :class:`~overhang_framework.errors.OverhangError` with a one-line
    message for the first value refused.
    """
    checked = dict(
        seed=_whole(cfg, "seed", 0), repeats=_whole(cfg, "repeats", 1), time_limit=_time_limit(cfg),
        call_limit=_call_limit(cfg), progress=_flag(cfg, "progress", True),
        overwrite=_flag(cfg, "overwrite", False), jobs=_whole(cfg, "jobs", 1) if "jobs" in cfg else 1,
        tasks=tasks_from_config(cfg.tasks))
    key = _models_key(cfg)
    kept = _kept_models.get(key)
    models = kept.pop() if kept and not keep else plugins.build_models(cfg)
    if keep:
        _kept_models.setdefault(key, []).append(models)
    return Checked(**checked, models=models)


class DecisionWatch:
    """Shows a decision's progress on the run's bar while it is under way.

    ``charged`` is the decisions' budget observer: at most every ``seconds``
    it puts the decision's predictor calls and time so far beside ``label``
    (on a terminal the bar redraws; off one, the bar writes a line now and
    then). ``placed`` moves the bar by one placement.
    """

    def __init__(self, bar, label: str, seconds: float = 0.5):
        self.bar, self.label, self.seconds = bar, label, seconds
        self.placement = 1
        self.shown = time.monotonic()

    def charged(self, budget) -> None:
        now = time.monotonic()
        if now - self.shown >= self.seconds:
            self.shown = now
            self.bar.set_postfix_str(f"{self.label}, placement {self.placement}: "
                                     f"{budget.calls_used:,} predictor calls, {budget.elapsed():.0f} s")

    def placed(self, step: dict) -> None:
        self.placement += 1
        self.bar.set_postfix_str(self.label)
        self.bar.update(1)


def _earlier_session(metrics_file: Path) -> dict:
    """What the earlier sessions of a resumed run counted (``wall_time``, ``world_stats``,
    ``predictor_stats``), from the metrics.json they left; nothing when it is missing or unreadable."""
    try:
        earlier = json.loads(metrics_file.read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(earlier, dict):
        return {}
    wall = earlier.get("wall_time")
    kept = {k: earlier[k] for k in ("world_stats", "predictor_stats") if isinstance(earlier.get(k), dict)}
    if isinstance(wall, (int, float)) and not isinstance(wall, bool) and wall >= 0:
        kept["wall_time"] = float(wall)
    return kept


class Terminated(BaseException):
    """The process was asked to stop (SIGTERM, as a cluster scheduler does at a time limit).

    Like :class:`KeyboardInterrupt`, it is not an :class:`Exception`, so that code which handles
    errors broadly does not take it for one and carry on."""


def _stop_if_asked(sigterm: list) -> None:
    """Raise the stop that a signal asked for, if a finaliser dropped the handler's own exception."""
    if sigterm:
        raise Terminated()
    stop_if_ctrl_c()


def _sigterm_stops_the_run():
    """Turn SIGTERM into :class:`Terminated` for the duration (main thread only); yields a list that holds
    the signal once it came, which the caller also checks between episodes (:func:`overhang_framework.interrupts.raising`)."""
    return raising(signal.SIGTERM, Terminated, [])


def run_unlocked(cfg: DictConfig, out_dir: Path) -> dict:
    """Run every (task, repeat) episode of ``cfg`` into ``out_dir``; return the summary.

    Everything the config says is checked before the first episode starts.
    Episodes already finished in ``out_dir`` for the same config are kept and
    not run again (see :mod:`overhang_framework.rundir`). If the run stops
    early (Ctrl-C, SIGTERM, a crashed worker), ``metrics.json`` is written for
    the finished episodes, marked ``complete: false``, and :class:`Interrupted`
    or :class:`Stopped` is raised.
    """
    checked = check_config(cfg)
    seed, repeats, time_limit, call_limit = checked.seed, checked.repeats, checked.time_limit, checked.call_limit
    tasks, models = checked.tasks, checked.models
    for note in run_notes(cfg, tasks, models):
        log.warning("note: %s", note)
        print(f"note: {note}", file=sys.stderr)
    rundir = RunDir(out_dir)
    done = finished_jobs(rundir.prepare(result_config(_params(cfg)), overwrite=checked.overwrite))
    for note in rundir.notes:
        log.warning("note: %s", note)
        print(f"note: {note}", file=sys.stderr)
    resumed = len(done)
    jobs = [(i, task, rep) for i, task in enumerate(tasks) for rep in range(repeats)]
    header = {g: cfg[g].get("name") for g in ("world", "predictor", "planner", "value", "condition")}
    header["tasks"] = tasks_label(cfg, tasks)
    started = time.perf_counter()
    log.info("run %s: %d episodes, %d already finished", out_dir, len(jobs), len(done))
    metrics_file = out_dir / "metrics.json"
    if resumed == len(jobs) and metrics_file.exists():
        try:
            summary = json.loads(metrics_file.read_text())
        except ValueError:
            summary = None
        if summary and summary.get("complete"):
            log.info("every episode was already finished; results unchanged")
            summary["episodes_resumed"] = resumed
            return summary
    earlier = _earlier_session(metrics_file) if resumed else {}
    rundir.reopen()

    worker_counters: dict = {}

    def run_stats() -> dict:
        """The models' counters: this process's, or the sum of the workers' when they played, plus
        those of the earlier sessions that finished episodes in this directory."""
        if worker_counters:
            parts = list(worker_counters.values())
            world, predictor = (merge_stats([c["world"] for c in parts]),
                                merge_stats([c["predictor"] for c in parts]))
        else:
            world, predictor = models["world"].stats(), getattr(models["predictor"], "stats", dict)()
        return {"world_stats": merge_stats([world, earlier.get("world_stats")]),
                "predictor_stats": merge_stats([predictor, earlier.get("predictor_stats")])}

    def summary_of(complete: bool, error: Optional[BaseException] = None) -> dict:
        episodes = [done[(i, rep)] for i, _, rep in jobs if (i, rep) in done]
        session = time.perf_counter() - started
        summary = summarize(episodes)
        summary.update({
            "complete": complete,
            "status": "complete" if complete else ("failed" if error is not None else "incomplete"),
            "error": "" if error is None else first_line(error),
            "episodes_expected": len(jobs),
            "episodes_resumed": resumed,
            "wall_time": earlier.get("wall_time", 0.0) + session,
            "wall_time_session": session,
            "config": header,
            "seed": seed,
            "time_limit": time_limit,
            **run_stats(),
        })
        atomic_write_json(metrics_file, summary)
        return summary

    placements = [len(task.sequence) - 1 for _, task, _ in jobs]
    bar = progress_bar(total=sum(placements), desc="placements", unit="pl", disable=not checked.progress,
                   miniters=1, mininterval=0.5, dynamic_ncols=True,
                   initial=sum(n for (i, _, rep), n in zip(jobs, placements) if (i, rep) in done))
    length = {(i, rep): n for (i, _, rep), n in zip(jobs, placements)}
    todo = [(i, rep) for i, _, rep in jobs if (i, rep) not in done]

    def serial() -> Iterator[dict]:
        for i, rep in todo:
            label = f"episode {len(done) + 1}/{len(jobs)} {tasks[i].id}"
            bar.set_postfix_str(label)
            watch = DecisionWatch(bar, label)
            yield play_run_episode(models, tasks[i], i, rep, seed, time_limit, call_limit,
                                   on_step=watch.placed, on_charge=watch.charged)

    if checked.jobs > 1 and len(todo) > 1:
        bar.set_postfix_str(f"{min(checked.jobs, len(todo))} processes")
        records = play_episodes(_params(cfg), todo, seed, time_limit, call_limit, checked.jobs,
                                on_step=lambda: bar.update(1), counters=worker_counters)
    else:
        records = serial()
    try:
        with _sigterm_stops_the_run() as sigterm, EpisodeLog(rundir.episodes, append=True) as episode_log:
            _stop_if_asked(sigterm)
            for record in records:
                key = (record["task_index"], record["repeat"])
                bar.update(length[key] - len(record["steps"]))  # placements a collapse cut short
                episode_log.write(record)
                done[key] = readable(record)
                log.info("episode %s repeat %d: reward %.3f, %d placements, %s", record["task_id"], key[1],
                         record["reward"], len(record["steps"]),
                         "stood throughout" if record["stable_throughout"] else "collapsed")
                _stop_if_asked(sigterm)
    except (KeyboardInterrupt, Terminated) as stop:
        bar.close()
        summary_of(complete=False)
        how = "terminated (SIGTERM)" if isinstance(stop, Terminated) else "interrupted"
        raise Interrupted(len(done), len(jobs), rundir.partial, how, checked.overwrite) from None
    except Exception as err:  # a crashed worker, or a fault in a model: keep what finished
        bar.close()
        log.exception("the run stopped on an error")
        summary_of(complete=False, error=err)
        raise Stopped(err, len(done), len(jobs), rundir.partial) from None
    bar.close()
    summary = summary_of(complete=True)
    log.info("finished: reward %.3f +- %.3f over %d episodes", summary["reward_mean"],
             summary["reward_sem"], summary["episodes"])
    return summary


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _number(value) -> str:
    """Three decimals, or '-' for a value that does not exist (the SEM of one number, a mean of none)."""
    if value is None or (isinstance(value, float) and value != value):
        return "-"
    return f"{value:.3f}"


def _job_failed(out_dir: Path, error: BaseException) -> None:
    """In a sweep, a job that fails records why in its metrics.json and lets the other jobs run."""
    metrics = out_dir / "metrics.json"
    try:
        summary = json.loads(metrics.read_text()) if metrics.exists() else {}
    except ValueError:
        summary = {}
    summary.update({"complete": False, "status": "failed", "error": first_line(error)})
    atomic_write_json(metrics, summary)


def _overwrite(cfg: DictConfig) -> bool:
    return cfg.get("overwrite") is True


def format_summary(summary: dict) -> str:
    rows = [
        ("terminal reward", "reward"),
        ("stable placements", "stable_placement"),
        ("successful episodes", "success"),
        ("overhang (successful)", "overhang_successful"),
        ("decision time (s)", "decision_time"),
    ]
    cfg = summary.get("config", {})
    lines = [
        " ".join(f"{k}={v}" for k, v in cfg.items()),
        f"{_count(summary['episodes'], 'episode')}, {_count(summary['placements'], 'placement')}, "
        f"{summary.get('wall_time', 0):.1f} s"
        + (f" ({summary['episodes_resumed']} finished earlier in this directory)"
           if summary.get("episodes_resumed") else ""),
        f"{'metric':<24}{'mean':>10}{'sem':>10}",
    ]
    for label, key in rows:
        lines.append(f"{label:<24}{_number(summary[key + '_mean']):>10}{_number(summary[key + '_sem']):>10}")
    if "decision_time_median" in summary:
        lines.append(f"{'decision time median':<24}{_number(summary['decision_time_median']):>10}"
                     f"   (max {_number(summary['decision_time_max'])})")
    if summary.get("time_limit") is not None:
        lines.append(f"over the time limit of {summary['time_limit']:g} s: {summary['over_time_limit']} of "
                     f"{_count(summary['placements'], 'decision')} (each played its best action so far)")
    cache = summary.get("world_stats", {}).get("cache")
    if cache:
        lines.append(f"physics cache: {cache['hits']} hits, {cache['misses']} misses "
                     f"(hit rate {cache['hit_rate']:.2f})")
    return "\n".join(lines)


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name="config")
def main(cfg: DictConfig) -> dict:
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        summary = run(cfg, out_dir)
    except OverhangError as err:
        log.error("%s", err)
        print(f"error: {err}", file=sys.stderr)
        if in_sweep():
            _job_failed(out_dir, err)
            return {}
        sys.exit(2)
    except Interrupted as stop:
        again = "the same command without overwrite=true" if stop.overwrite else "the same command"
        message = (f"{stop.how}: {stop.finished} of {stop.expected} episodes finished, kept in {stop.kept} "
                   f"(metrics.json covers them, marked incomplete); to resume, rerun {again} "
                   f"with hydra.run.dir={out_dir}")
        log.warning("%s", message)
        print(message, file=sys.stderr)
        sys.exit(143 if stop.how.startswith("terminated") else 130)
    except Stopped as stop:
        what = str(stop.error) if isinstance(stop.error, PoolCrashed) else \
            f"{type(stop.error).__name__}: {stop.error} (traceback in {out_dir / 'run.log'})"
        message = (f"error: {what}; {stop.finished} of {stop.expected} episodes finished, kept in "
                   f"{stop.kept}; to resume, rerun the same command{' without overwrite=true' if _overwrite(cfg) else ''} "
                   f"with hydra.run.dir={out_dir}")
        log.error("%s", message)
        print(message, file=sys.stderr)
        if in_sweep():
            return {}  # metrics.json says failed; the sweep goes on and reports it
        sys.exit(1)
    except KeyboardInterrupt:
        print("interrupted before the first episode; no episode was written", file=sys.stderr)
        sys.exit(130)
    print(format_summary(summary))
    print(f"results: {out_dir}")
    return summary

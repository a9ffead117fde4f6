"""The main job: compose the models from config, run every episode, write the results."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from overhang_framework.config import CONFIG_PATH, enable_plugin_configs
from overhang_framework.episode import episode_rng, run_episode
from overhang_framework.errors import ConfigError, OverhangError
from overhang_framework.physics.pool import PoolCrashed
from overhang_framework.plugins import Registry
from overhang_framework.results import EpisodeLog, atomic_write_json, summarize
from overhang_framework.tasks import tasks_from_config

enable_plugin_configs()


def _params(cfg: DictConfig) -> dict[str, Any]:
    return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]


def build_models(cfg: DictConfig, registry: Registry | None = None) -> dict[str, Any]:
    """World, value, predictor and planner named by ``cfg``, built through the registry."""
    registry = registry or Registry()
    world = registry.create("world", _params(cfg.world))
    return {
        "world": world,
        "value": registry.create("value", _params(cfg.value), world=world),
        "predictor": registry.create("predictor", _params(cfg.predictor), world=world),
        "planner": registry.create("planner", _params(cfg.planner), world=world),
    }


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


def run(cfg: DictConfig, out_dir: Path) -> dict:
    """Run every (task, repeat) episode of ``cfg`` into ``out_dir``; return the summary.

    Everything the config says is checked before the first episode starts.
    """
    seed, repeats, time_limit = _whole(cfg, "seed", 0), _whole(cfg, "repeats", 1), _time_limit(cfg)
    tasks = tasks_from_config(cfg.tasks)
    models = build_models(cfg)
    episodes = []
    started = time.perf_counter()
    jobs = [(i, task, rep) for i, task in enumerate(tasks) for rep in range(repeats)]
    with EpisodeLog(out_dir / "episodes.jsonl") as log:
        bar = tqdm(jobs, desc="episodes", unit="ep", disable=not cfg.get("progress", True),
                   file=sys.stderr, dynamic_ncols=True)
        for i, task, rep in bar:
            record = run_episode(task, models["world"], models["predictor"], models["planner"],
                                 models["value"], episode_rng(seed, i, rep), time_limit)
            record.update({"seed": seed, "repeat": rep, "task_index": i})
            log.write(record)
            episodes.append(record)
            bar.set_postfix(reward=f"{record['reward']:.2f}")
    summary = summarize(episodes)
    summary.update({
        "wall_time": time.perf_counter() - started,
        "config": {g: cfg[g].get("name") for g in ("world", "predictor", "planner", "value", "condition", "tasks")},
        "seed": seed,
        "world_stats": models["world"].stats(),
    })
    atomic_write_json(out_dir / "metrics.json", summary)
    return summary


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
        f"{summary['episodes']} episodes, {summary['placements']} placements, {summary.get('wall_time', 0):.1f} s",
        f"{'metric':<24}{'mean':>10}{'sem':>10}",
    ]
    for label, key in rows:
        lines.append(f"{label:<24}{summary[key + '_mean']:>10.3f}{summary[key + '_sem']:>10.3f}")
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
        print(f"error: {err}", file=sys.stderr)
        sys.exit(2)
    except PoolCrashed as err:
        kept = out_dir / "episodes.jsonl.partial"
        print(f"error: {err}; the episodes finished before it are in {kept}", file=sys.stderr)
        sys.exit(1)
    print(format_summary(summary))
    print(f"results: {out_dir}")
    return summary

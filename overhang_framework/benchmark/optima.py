"""The proven optimum of every scored benchmark task, its path replayed under the reference.

``python -m overhang_framework.benchmark.optima split=test`` searches the optimum of each task of a
split under the world's physics (the default: the tiered physics, whose verdicts are the full-window
reference's) with :class:`~overhang_framework.optimum.OptimumSearch`: exhaustive branch and bound over
every placement on the grid, with the veridical predictor. It then replays the path it found under
``world.physics=pybullet`` itself and keeps, with the optimum, what the reference said of every
placement. Rows go to the project's optima file (keyed by sequence, physics parameters and resolution,
as ``python -m overhang_framework.optimum`` keys them), where ``planner=optimal``, the reports and the
benchmark's scoring find them.

It is resumable and spreads over any launcher:

    python -m overhang_framework.benchmark.optima split=test jobs=2
    python -m overhang_framework.benchmark.optima -m split=test shard=0,1,2,3 shards=4 hydra/launcher=slurm

With ``carry=true``, a task whose optimum the file holds under a tiered physics that grants at least what
the world's grants (the world's "stands for sure" stage only stricter: ``stable_tilt`` and ``stable_margin``
no smaller, ``frictionless_stable`` kept on, every other parameter the same) is not searched again if its
stored path still stands, placement by placement, under the world: the world calls a subset of those
towers standing, so an optimum still reached is still the optimum. Only the paths that fall are searched.

Each worker keeps one world for all its tasks, so the verdicts of towers that several tasks build are
decided once, and every worker and job shares the reference's verdicts in one SQLite file
(``verdicts=``). A solved task is written at once to ``<optima file>.parts/`` and merged into the optima
file under a lock at once; a stopped run loses at most the tasks being solved.
"""

from __future__ import annotations

import contextlib
import json
import logging
import sys
import time
from pathlib import Path
from typing import Iterator, Optional, Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from overhang_framework.config import CONFIG_PATH, enable_plugin_configs, in_sweep
from overhang_framework.errors import ConfigError, OverhangError

enable_plugin_configs()
log = logging.getLogger("overhang_framework.benchmark.optima")
CONFIG_NAME = "benchmark_optima"
_WORLDS: dict = {}


def optima_file(cfg: DictConfig) -> Path:
    from overhang_framework.optimum import DATA_FILE

    return Path(cfg.out).expanduser() if cfg.get("out") else DATA_FILE


def parts_dir(out: Path) -> Path:
    return out.with_name(out.name + ".parts")


def config_ids(cfg: DictConfig) -> list[str]:
    """The task ids a config names (``ids``, or ``split`` with ``fold``), checked."""
    from overhang_framework.benchmark import splits

    if cfg.get("ids"):
        ids = [str(t) for t in cfg.ids] if not isinstance(cfg.ids, str) else [cfg.ids]
        for t in ids:
            splits.sequence_of(t)
        return ids
    if cfg.split not in splits.SPLITS:
        raise ConfigError(f"unknown split {cfg.split!r}; splits: {', '.join(splits.SPLITS)} (or ids=[w123123,...])")
    return splits.split_ids(cfg.split, cfg.get("fold"))


def shard_of(ids: Sequence[str], shard: int, shards: int) -> list[str]:
    """The ids of job ``shard`` of ``shards``: every ``shards``-th, from ``shard``."""
    return [t for k, t in enumerate(ids) if k % shards == shard]


def world_config(cfg: DictConfig) -> dict:
    return OmegaConf.to_container(cfg.world, resolve=True)  # type: ignore[return-value]


def _world(world_cfg: dict, verdicts: Optional[str]):
    """This process's world for ``world_cfg`` (one per process, kept across tasks)."""
    key = json.dumps([world_cfg, verdicts], sort_keys=True, default=str)
    world = _WORLDS.get(key)
    if world is None:
        from overhang_framework.plugins import Registry

        params = dict(world_cfg)
        if verdicts:
            params["verdict_file"] = str(Path(verdicts).expanduser())
        world = _WORLDS[key] = Registry().create("world", params)
    return world


def replay(row: dict, world_cfg: dict) -> dict:
    """The path of ``row`` placed step by step under the full-window reference (``physics=pybullet``,
    ``early_stop`` off, no verdict file): whether each placement stands, and the final overhang."""
    from overhang_framework.geometry import Action
    from overhang_framework.interfaces import Task
    from overhang_framework.plugins import Registry

    params = {k: v for k, v in world_cfg.items() if k not in ("verdict_file", "tiered", "static")}
    params["physics"] = "pybullet"
    params["pybullet"] = {**dict(world_cfg.get("pybullet") or {}), "early_stop": False}
    reference = Registry().create("world", params)
    state = reference.initial_state(Task(row["task_id"], tuple(row["sequence"])))
    stands = []
    for x, layer in row["actions"]:
        action = Action(float(x), int(layer))
        if reference.illegal_reason(state, action) is not None:
            stands.append(False)
            break
        state = reference.successor(state, action)
        stands.append(bool(reference.is_stable(state.geometry)))
        if not stands[-1]:
            break
    whole = len(stands) == len(row["actions"]) and all(stands)
    return {"physics": "pybullet", "stands": stands, "stood": whole,
            "overhang": float(reference.overhang(state.geometry)) if whole else 0.0}


#: The tiered physics' "stands for sure" parameters, and the direction in which each makes the stage stricter.
STRICTER = {"stable_tilt": "up", "stable_margin": "up", "frictionless_stable": "on"}


def carry_refusal(stored: dict, ident: dict) -> Optional[str]:
    """Why the optimum row ``stored`` cannot be carried to the physics ``ident`` (``physics_id`` of a world), or
    None when ``ident``'s physics grants a subset of what ``stored``'s granted: both tiered, the same resolution, the
    "stands for sure" stage only stricter, every other parameter the same."""
    if stored.get("physics") != "tiered" or ident["physics"] != "tiered":
        return f"only tiered optima carry to a tiered physics ({stored.get('physics')} -> {ident['physics']})"
    if stored.get("resolution") != ident["resolution"]:
        return f"the resolution differs ({stored.get('resolution')} -> {ident['resolution']})"
    old, new = stored.get("params") or {}, ident["params"]
    for name in sorted(set(old) | set(new)):
        a, b = old.get(name), new.get(name)
        if a == b:
            continue
        way = STRICTER.get(name)
        if way == "up" and a is not None and b is not None and b > a:
            continue
        if way == "on" and b is True and a is False:
            continue
        return (f"{name} {a!r} -> {b!r} is not known to grant fewer towers (only {', '.join(STRICTER)} may change, "
                "and only to a stricter stage)")
    return None


def carry(stored: dict, world) -> Optional[dict]:
    """``stored``'s row for the physics of ``world`` if its path stands under ``world`` placement by placement and
    reaches the stored optimum; None if not."""
    from overhang_framework.geometry import Action
    from overhang_framework.interfaces import Task
    from overhang_framework.optimum import physics_id

    started = time.perf_counter()
    state = world.initial_state(Task(stored["task_id"], tuple(stored["sequence"])))
    for x, layer in stored["actions"]:
        action = Action(float(x), int(layer))
        if world.illegal_reason(state, action) is not None:
            return None
        state = world.successor(state, action)
        if not world.is_stable(state.geometry):
            return None
    if abs(float(world.overhang(state.geometry)) - float(stored["optimum"])) > 1e-9:
        return None
    return {**stored, **physics_id(world), "carried": {"params": stored["params"],
                                                       "seconds": time.perf_counter() - started}}


def carry_sources(tid: str, ident: dict, known: dict) -> list[dict]:
    """The stored rows of task ``tid``'s sequence that may be carried to the physics ``ident`` (``physics_id``)."""
    from overhang_framework.benchmark.splits import sequence_of

    sequence = [round(w, 6) for w in sequence_of(tid)]
    return [r for r in known.values() if [round(w, 6) for w in r.get("sequence", [])] == sequence
            and carry_refusal(r, ident) is None]


def solve(tid: str, world_cfg: dict, verdicts: Optional[str], do_replay: bool,
          sources: Sequence[dict] = ()) -> tuple[str, dict]:
    """Worker: the optimum row of task ``tid`` and its key in the optima file (carried from one of ``sources`` if
    its path stands under the world, searched otherwise)."""
    from overhang_framework.benchmark.splits import task
    from overhang_framework.optimum import optimum_key, task_optimum

    world = _world(world_cfg, verdicts)
    t = task(tid)
    row = next((r for r in (carry(stored, world) for stored in sources) if r is not None), None)
    if row is None:
        row = task_optimum(t, world, path=None)
    if do_replay and not row.get("reference"):  # a carried path keeps its replay: the reference is the same
        started = time.perf_counter()
        row["reference"] = replay(row, world_cfg)
        row["reference"]["seconds"] = time.perf_counter() - started
    return optimum_key(t, world), row


def _worker_solve(state: tuple, job: tuple) -> tuple[str, dict]:
    """Worker of :func:`~overhang_framework.parallel.pool_map`: :func:`solve` of ``(task id, carry sources)``."""
    world_cfg, verdicts, do_replay = state
    tid, sources = job
    return solve(tid, world_cfg, verdicts, do_replay, sources)


@contextlib.contextmanager
def locked(path: Path) -> Iterator[None]:
    """An exclusive lock on ``<path>.lock`` (every job merging into one optima file takes it)."""
    import fcntl

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path.with_name(path.name + ".lock"), "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def keep_part(out: Path, key: str, row: dict) -> None:
    from overhang_framework.results import atomic_write_json

    atomic_write_json(parts_dir(out) / f"{key}.json", row)


def read_parts(out: Path) -> dict:
    """The rows kept in ``<out>.parts/``, by key."""
    rows = {}
    for f in sorted(parts_dir(out).glob("*.json")):
        try:
            rows[f.stem] = json.loads(f.read_text())
        except ValueError as err:
            raise OverhangError(f"{f} is not a JSON optimum row ({err}); delete it to solve its task again") from None
    return rows


def merge(out: Path) -> int:
    """Move the rows of ``<out>.parts/`` into the optima file ``out`` (under its lock); how many were new."""
    from overhang_framework.optimum import load_optima
    from overhang_framework.results import atomic_write_json

    with locked(out):
        parts = read_parts(out)
        if not parts:
            return 0
        optima = load_optima(out)
        new = [k for k in parts if k not in optima]
        optima.update({k: parts[k] for k in new})
        atomic_write_json(out, {"optima": optima})
        for key in parts:
            (parts_dir(out) / f"{key}.json").unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            parts_dir(out).rmdir()
    return len(new)


def check_config(cfg: DictConfig) -> None:
    for key, low in (("jobs", 1), ("shards", 1), ("shard", 0)):
        value = cfg.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            raise ConfigError(f"{key} must be a whole number >= {low}, got {value!r}")
    if cfg.shard >= cfg.shards:
        raise ConfigError(f"shard must be below shards ({cfg.shards}), got {cfg.shard}")
    for key in ("replay", "progress", "carry"):
        if not isinstance(cfg.get(key), bool):
            raise ConfigError(f"{key} must be true or false, got {cfg.get(key)!r}")
    config_ids(cfg)
    from overhang_framework.plugins import Registry

    world = Registry().create("world", world_config(cfg))
    if cfg.carry and getattr(world, "physics_name", None) != "tiered":
        raise ConfigError(f"carry=true carries optima to a stricter tiered physics; world.physics is "
                          f"{getattr(world, 'physics_name', None)}")


def run(cfg: DictConfig, out_dir: Path) -> dict:
    """Solve this job's share of the tasks that the optima file does not hold yet."""
    from overhang_framework.benchmark.splits import task
    from overhang_framework.optimum import load_optima, optimum_key, physics_id
    from overhang_framework.progress import progress_bar

    check_config(cfg)
    out = optima_file(cfg)
    world_cfg = world_config(cfg)
    verdicts = str(Path(cfg.verdicts).expanduser()) if cfg.get("verdicts") else None
    world = _world(world_cfg, verdicts)  # the world a one-process run solves with
    mine = shard_of(config_ids(cfg), cfg.shard, cfg.shards)
    merge(out)  # a stopped run's finished tasks
    known = {**load_optima(out), **read_parts(out)}
    keys = {tid: optimum_key(task(tid), world) for tid in mine}
    todo = [tid for tid in mine if keys[tid] not in known]
    ident = physics_id(world)
    sources = {tid: carry_sources(tid, ident, known) if cfg.carry else [] for tid in todo}
    log.info("%d tasks, %d with an optimum already, %d to solve in %s (%d with a stored optimum to carry)", len(mine),
             len(mine) - len(todo), len(todo), out, sum(bool(v) for v in sources.values()))
    bar = progress_bar(total=len(mine), initial=len(mine) - len(todo), desc="optima", unit="task",
                       disable=not cfg.progress)
    started = time.perf_counter()
    rows: dict = {}

    def done(key: str, row: dict) -> None:
        keep_part(out, key, row)
        merge(out)  # the optima file holds every finished task at once
        rows[key] = row
        how = f"carried in {row['carried']['seconds']:.1f} s" if row.get("carried") else f"in {row['seconds']:.0f} s"
        bar.set_postfix_str(f"{row['task_id']} {row['optimum']:.1f} {how}")
        bar.update(1)
        log.info("%s optimum %.3f %s, reference %s", row["task_id"], row["optimum"], how,
                 row.get("reference", {}).get("stood"))

    try:
        if cfg.jobs == 1 or len(todo) <= 1:
            for tid in todo:
                done(*solve(tid, world_cfg, verdicts, cfg.replay, sources[tid]))
        else:
            from overhang_framework.parallel import given, pool_map

            for _, result, _ in pool_map(given, (world_cfg, verdicts, cfg.replay), _worker_solve,
                                         [(tid, sources[tid]) for tid in todo], cfg.jobs, on_tick=lambda: None):
                done(*result)
    finally:
        bar.close()
        merge(out)
    optima = load_optima(out)
    table = [optima[keys[tid]] | {"benchmark_id": tid} for tid in mine]
    write_table(out_dir / "optima.csv", table)
    falls = [r["benchmark_id"] for r in table if r.get("reference") and not r["reference"]["stood"]]
    searched = [r for r in rows.values() if not r.get("carried")]
    return {"tasks": len(mine), "solved": len(searched), "carried": len(rows) - len(searched),
            "seconds": time.perf_counter() - started,
            "search_seconds": sum(r["seconds"] for r in searched), "file": str(out), "falls": falls,
            "table": str(out_dir / "optima.csv")}


def write_table(path: Path, rows: Sequence[dict]) -> None:
    """One line per task: id, sequence, optimum, search seconds, nodes, what the reference said."""
    import pandas as pd

    from overhang_framework.results import atomic_write_text

    frame = pd.DataFrame([{
        "task_id": r["benchmark_id"], "sequence": " ".join(f"{w:.1f}" for w in r["sequence"]),
        "optimum": r["optimum"], "seconds": r["seconds"], "nodes_expanded": r.get("nodes_expanded"),
        "reference_stood": (r.get("reference") or {}).get("stood"), "physics": r["physics"]} for r in rows])
    atomic_write_text(path, frame.to_csv(index=False))


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name=CONFIG_NAME)
def app(cfg: DictConfig) -> Optional[dict]:
    from overhang_framework.preflight import job_result

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    summary = job_result(lambda: run(cfg, out_dir), lambda: f"interrupted: every finished optimum is kept in "
                         f"{optima_file(cfg)}; run the same command to solve the rest", log)
    if summary is None:
        return None
    carried = f", {summary['carried']} carried from a physics that grants more" if summary["carried"] else ""
    print(f"{summary['tasks']} tasks: {summary['solved']} solved now{carried} in {summary['seconds']:.0f} s "
          f"({summary['search_seconds']:.0f} s of search), the rest already in {summary['file']}; table: {summary['table']}")
    if summary["falls"]:
        print(f"error: under the reference the optimal paths of {', '.join(summary['falls'])} fall", file=sys.stderr)
        if not in_sweep():
            sys.exit(1)
    return summary


def main(argv: Optional[Sequence[str]] = None) -> None:
    from overhang_framework.preflight import run_app_command

    run_app_command(argv, app, CONFIG_NAME, check_config, __doc__)


if __name__ == "__main__":
    main()

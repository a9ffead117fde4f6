"""Scoring one agent on one split: ``python -m overhang_framework.benchmark``.

Every task of the split is played once per seed (and per rung of a budget ladder), by the agent the
config names; each finished episode is appended to ``episodes.jsonl`` at once. Then ``scores.csv``
(one row per task, seed and budget), ``summary.json`` (score, 95% bootstrap interval over tasks,
share stood, mean raw reward; with a ladder, the curve and its area) and ``score.png`` are written,
atomically. The same command into the same run directory continues a stopped run; a directory of
another config is refused with the differences listed. ``python -m overhang_framework.benchmark.rescore DIR``
writes the scores again from the episodes (with the optima file as it is now) in seconds.
"""

from __future__ import annotations

import contextlib
import json
import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any, Optional, Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from overhang_framework.config import CONFIG_PATH, enable_plugin_configs
from overhang_framework.errors import ConfigError

enable_plugin_configs()
log = logging.getLogger("overhang_framework.benchmark")
CONFIG_NAME = "benchmark"
EPISODES = "episodes.jsonl"
SCORES = "scores.csv"
SUMMARY = "summary.json"
FIGURE = "score.png"
RUN = "run.json"
COLUMNS = ("task_id", "seed", "budget", "reward", "optimum", "normalised", "stood", "calls", "seconds", "reason",
           "steps", "snapped")
AGENT_TYPES = ("planner", "random", "command")
#: What changes no result: left out of the run directory's identity.
NOT_RESULTS = ("jobs", "progress", "figure", "overwrite", "verdicts")
_AGENTS: dict = {}


def _container(node) -> Any:
    return OmegaConf.to_container(node, resolve=True)


def identity(cfg: DictConfig) -> dict:
    """What a run's results depend on: the config less how it is run (jobs, progress, files)."""
    data = {k: v for k, v in _container(cfg).items() if k not in NOT_RESULTS}
    data.get("world", {}).pop("verdict_file", None)
    if cfg.agent.type != "planner":
        for key in ("planner", "predictor", "value"):
            data.pop(key, None)
    return data


def label(cfg: DictConfig) -> str:
    """A short name of the agent: ``lookahead D=2 + ipe``, ``random``, ``command: node centre.js``."""
    kind = cfg.agent.type
    if kind == "random":
        return "random"
    if kind == "command":
        return "command: " + " ".join(Path(w).name if "/" in w else w for w in cfg.agent.command)
    planner = cfg.planner.name
    if planner == "lookahead":
        planner = f"lookahead D={cfg.planner.depth}"
    elif planner == "mcts":
        planner = f"mcts {cfg.planner.get('iterations')} it."
    elif planner == "policy":  # a policy asks no predictor
        return f"policy {Path(str(cfg.planner.get('path'))).name}"
    return f"{planner} + {cfg.predictor.name}"


def task_ids(cfg: DictConfig) -> list[str]:
    from overhang_framework.benchmark import splits

    if cfg.get("ids"):
        ids = [cfg.ids] if isinstance(cfg.ids, str) else [str(t) for t in cfg.ids]
        for t in ids:
            splits.sequence_of(t)
        return ids
    if cfg.split not in splits.SPLITS:
        raise ConfigError(f"unknown split {cfg.split!r}; splits: {', '.join(splits.SPLITS)} (or ids=[w123123,...])")
    return splits.split_ids(cfg.split, cfg.get("fold"))


def world_params(cfg: DictConfig) -> dict:
    params = _container(cfg.world)
    if cfg.get("verdicts"):
        params["verdict_file"] = str(Path(cfg.verdicts).expanduser())
    return params


def build_agent(cfg_data: dict, workdir: Path):
    """The world and the agent a config (as plain data) names."""
    from overhang_framework.benchmark.agents import PlannerAgent, RandomAgent
    from overhang_framework.plugins import Registry

    cfg = OmegaConf.create(cfg_data)
    registry = Registry()
    kind = cfg.agent.type
    if kind == "planner":
        world = registry.create("world", world_params(cfg))
        models = {"world": world,
                  "value": registry.create("value", _container(cfg.value), world=world),
                  "predictor": registry.create("predictor", _container(cfg.predictor), world=world),
                  "planner": registry.create("planner", _container(cfg.planner), world=world)}
        return world, PlannerAgent(models, cfg.budget_kind)
    world = registry.create("world", world_params(cfg))
    if kind == "random":
        return world, RandomAgent(world)
    if kind == "command":
        from overhang_framework.benchmark.external import CommandAgent

        return world, CommandAgent(world, list(cfg.agent.command), timeout=cfg.agent.timeout,
                                   render=bool(cfg.agent.get("render", False)), workdir=workdir,
                                   cwd=cfg.agent.get("cwd"))
    raise ConfigError(f"unknown agent type {kind!r}; allowed: {', '.join(AGENT_TYPES)}")


def check_config(cfg: DictConfig, start: bool = True) -> None:
    """Every value of a benchmark config that can be checked before the first episode: every problem found,
    in one :class:`ConfigError` (problems joined by ``|``); ``start``: also start an external program once to
    see that it does not exit at once."""
    problems = config_problems(cfg, start)
    if problems:
        raise ConfigError(" | ".join(problems))


def config_problems(cfg: DictConfig, start: bool = True) -> list[str]:
    """What is wrong with a benchmark config, each problem one sentence (empty when nothing is)."""
    problems: list[str] = []
    kind = cfg.agent.get("type")
    if kind not in AGENT_TYPES:
        problems.append(f"unknown agent type {kind!r}; allowed: {', '.join(AGENT_TYPES)}")
    for key, low in (("seeds", 1), ("jobs", 1), ("seed", 0)):
        value = cfg.get(key)
        if isinstance(value, bool) or not isinstance(value, int) or value < low:
            problems.append(f"{key} must be a whole number >= {low}, got {value!r}")
    if cfg.budget_kind not in ("calls", "seconds"):
        problems.append(f"budget_kind must be calls or seconds, got {cfg.budget_kind!r}")
    budgets = cfg.get("budgets")
    if budgets is not None:
        values = list(budgets) if not isinstance(budgets, (int, float, str)) else [budgets]
        bad = [b for b in values if isinstance(b, bool) or not isinstance(b, (int, float)) or b <= 0]
        if bad or not values or len(set(values)) != len(values):
            problems.append(f"budgets must be a list of distinct numbers > 0 (e.g. [1,4,16,64,256]), got {values!r}")
        elif cfg.budget_kind == "calls" and any(float(b) != int(b) for b in values):
            problems.append(f"budgets of predictor calls must be whole numbers, got {values!r}")
        if kind in ("random", "command"):
            problems.append(f"agent={kind} takes no budget; leave budgets=null (it gets one point, at the compute "
                            "it spent)")
    for key in ("figure", "progress", "overwrite"):
        if not isinstance(cfg.get(key), bool):
            problems.append(f"{key} must be true or false, got {cfg.get(key)!r}")
    if kind == "command":
        problems += _command_problems(cfg.agent)
    try:
        task_ids(cfg)
    except (ConfigError, ValueError) as err:
        problems.append(str(err))
    if problems:
        return problems
    from overhang_framework.plugins import Registry

    registry = Registry()
    try:
        world = registry.create("world", _container(cfg.world))
        if kind == "planner":
            for group in ("value", "predictor", "planner"):
                registry.create(group, _container(cfg[group]), world=world)
    except (ConfigError, ValueError) as err:
        problems.append(str(err))
    if not problems and kind == "command" and start:
        from overhang_framework.benchmark.external import check_starts

        why = check_starts(list(cfg.agent.command), cfg.agent.get("cwd"))
        if why:
            problems.append(why)
    return problems


def _command_problems(agent: DictConfig) -> list[str]:
    """What is wrong with ``agent=command``'s options: the program, its timeout, render and cwd."""
    import shutil

    problems = []
    command = None if OmegaConf.is_missing(agent, "command") else agent.get("command")
    if isinstance(command, str):
        problems.append(f"agent.command must be a list of words, got the string {command!r}; write "
                        f"'agent.command=[{','.join(command.split())}]'")
    elif not command or not all(isinstance(w, str) and w for w in command):
        problems.append("agent=command needs agent.command, the program as a list of words, e.g. "
                        "'agent.command=[node,examples/agents/centre.js]'" +
                        (f"; got {list(command)!r}" if command else ""))
    timeout = agent.get("timeout")
    if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not timeout > 0 or timeout == float("inf"):
        problems.append(f"agent.timeout must be a number of seconds > 0 (the default is 30), got {timeout!r}")
    if not isinstance(agent.get("render"), bool):
        problems.append(f"agent.render must be true or false, got {agent.get('render')!r}")
    cwd = agent.get("cwd")
    if cwd is not None and (not isinstance(cwd, str) or not Path(cwd).expanduser().is_dir()):
        problems.append(f"agent.cwd must be an existing directory (or null: the current one), got {cwd!r}")
    elif command and not isinstance(command, str) and not problems:
        program = str(command[0])
        where = Path(cwd).expanduser() if cwd else Path.cwd()
        found = shutil.which(program) if "/" not in program else (
            str(where / program) if (where / program).is_file() else None)
        if found is None:
            problems.append(f"agent.command's program {program!r} is not found" +
                            (" on the PATH" if "/" not in program else f" in {where}"))
    return problems


def check_output_dir(cfg: DictConfig, out_dir: Path) -> None:
    """Refuse, before anything is written, a run into a directory that holds another config's results."""
    run_file = Path(out_dir) / RUN
    if cfg.overwrite is True or not run_file.exists():
        return
    from overhang_framework.results import readable

    try:
        old = json.loads(run_file.read_text()).get("identity")
    except (OSError, ValueError, AttributeError):
        raise ConfigError(f"{run_file} cannot be read as a benchmark run's record; use another hydra.run.dir, "
                          "or overwrite=true to replace it") from None
    ident = json.loads(json.dumps(readable(identity(cfg)), default=str))  # as run.json keeps it
    if old != ident:
        raise ConfigError(f"{out_dir} holds results of a different config ({_differences(old, ident)}); use "
                          "another hydra.run.dir, or overwrite=true to replace them")


def plan(cfg: DictConfig) -> list[tuple[str, int, Optional[float]]]:
    """Every episode of the run: (task id, seed, budget), in order."""
    budgets = cfg.get("budgets")
    rungs: list = [None] if budgets is None else sorted(float(b) for b in budgets)
    return [(t, cfg.seed + s, b) for b in rungs for t in task_ids(cfg) for s in range(cfg.seeds)]


def _episode_key(record: dict) -> tuple:
    budget = record.get("budget")
    return (record["task_id"], int(record["seed"]), None if budget is None else float(budget))


def play_one(cfg_data: dict, workdir: str, tid: str, seed: int, budget: Optional[float]) -> dict:
    """Worker: one episode, with this process's agent for the config."""
    from overhang_framework.benchmark.agents import play
    from overhang_framework.benchmark.splits import task

    key = json.dumps(cfg_data, sort_keys=True, default=str)
    if key not in _AGENTS:
        _AGENTS[key] = build_agent(cfg_data, Path(workdir))
    world, agent = _AGENTS[key]
    if cfg_data.get("budget_kind") == "calls" and budget is not None:
        budget = int(budget)
    return play(agent, world, task(tid), seed, budget)


def _worker_play(state: tuple[dict, str], episode: tuple) -> dict:
    """Worker of :func:`~overhang_framework.parallel.pool_map`: one episode ``(task id, seed, budget)``."""
    return play_one(*state, *episode)


def close_agents() -> None:
    for world, agent in _AGENTS.values():
        agent.close()
    _AGENTS.clear()


def read_episodes(path: Path) -> list[dict]:
    """The episodes of ``episodes.jsonl`` (a last line cut short by a crash is dropped)."""
    if not path.exists():
        return []
    records = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except ValueError:
            log.warning("%s: line %d is cut short; its episode is played again", path, n)
    return records


def score_rows(records: Sequence[dict], world, optima_path: Optional[str]) -> list[dict]:
    """One ``scores.csv`` row per episode, with its task's optimum under ``world``'s physics."""
    from overhang_framework.benchmark.score import normalised
    from overhang_framework.benchmark.splits import task
    from overhang_framework.optimum import load_optima, optimum_key

    optima = load_optima(optima_path)
    rows = []
    for r in sorted(records, key=lambda r: (r["task_id"], -1 if r.get("budget") is None else r["budget"], r["seed"])):
        row = optima.get(optimum_key(task(r["task_id"]), world))
        optimum = None if row is None else float(row["optimum"])
        rows.append({"task_id": r["task_id"], "seed": r["seed"], "budget": r.get("budget"), "reward": r["reward"],
                     "optimum": optimum, "normalised": normalised(r["reward"], optimum), "stood": r["stood"],
                     "calls": r.get("calls"), "seconds": r["seconds"], "reason": r["reason"],
                     "steps": len(r["steps"]), "snapped": r.get("snapped", 0)})
    return rows


def write_results(out_dir: Path, cfg_data: dict, records: Sequence[dict], world, figure: bool = True) -> dict:
    """``scores.csv``, ``summary.json`` and the figure from the episodes (atomically); the summary."""
    import pandas as pd

    from overhang_framework.benchmark.score import summary
    from overhang_framework.results import atomic_write_json, atomic_write_text

    cfg = OmegaConf.create(cfg_data)
    rows = score_rows(records, world, cfg.get("optima"))
    frame = pd.DataFrame(rows, columns=list(COLUMNS))
    atomic_write_text(out_dir / SCORES, frame.to_csv(index=False, float_format="%.10g"))
    result = summary(rows, draws=10_000)
    missing = sorted({r["task_id"] for r in rows if r["optimum"] is None})
    result.update({"agent": label(cfg), "split": cfg.split if not cfg.get("ids") else "ids", "fold": cfg.get("fold"),
                   "budget_kind": cfg.budget_kind if cfg.get("budgets") is not None else None,
                   "physics": cfg.world.physics, "missing_optima": missing, "config": identity(cfg)})
    atomic_write_json(out_dir / SUMMARY, result)
    if figure and result["n_scored"]:
        from overhang_framework.benchmark.figures import run_figure

        run_figure(result, out_dir / FIGURE)
    elif figure:
        log.warning("no task of the run has an optimum under this physics: no score and no figure")
    return result


def run(cfg: DictConfig, out_dir: Path) -> dict:
    from overhang_framework.progress import progress_bar
    from overhang_framework.results import atomic_write_json

    check_config(cfg, start=False)  # the command line's check started the program already
    check_output_dir(cfg, out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg_data = _container(cfg)
    from overhang_framework.results import readable

    ident = json.loads(json.dumps(readable(identity(cfg)), default=str))  # as run.json keeps it
    run_file = out_dir / RUN
    episodes = out_dir / EPISODES
    if cfg.overwrite:
        for name in (EPISODES, SCORES, SUMMARY, FIGURE):
            (out_dir / name).unlink(missing_ok=True)
    atomic_write_json(run_file, {"identity": ident})
    done = {_episode_key(r): r for r in read_episodes(episodes)}
    wanted = plan(cfg)
    todo = [e for e in wanted if (e[0], e[1], e[2]) not in done]
    if done:
        # rewrite without lines cut short or left by another plan
        keep = [done[k] for k in sorted(done, key=str) if k in set(wanted)]
        from overhang_framework.results import atomic_write_text

        atomic_write_text(episodes, "".join(json.dumps(r, sort_keys=True) + "\n" for r in keep))
    log.info("%s on %d episodes, %d already played", label(cfg), len(wanted), len(wanted) - len(todo))
    bar = progress_bar(total=len(wanted), initial=len(wanted) - len(todo), desc=label(cfg)[:30], unit="episode",
                       disable=not cfg.progress)
    with open(episodes, "a") as fh:
        def keep_record(record: dict) -> None:
            fh.write(json.dumps(record, sort_keys=True) + "\n")
            fh.flush()
            done[_episode_key(record)] = record
            bar.set_postfix_str(f"{record['task_id']} {record['reward']:.1f}")
            bar.update(1)

        try:
            if cfg.jobs == 1 or len(todo) <= 1:
                for tid, seed, budget in todo:
                    keep_record(play_one(cfg_data, str(out_dir), tid, seed, budget))
            else:  # a Ctrl-C stops the workers at once; the episodes they were playing are played again next time
                from overhang_framework.parallel import given, pool_map

                for _, record, _ in pool_map(given, (cfg_data, str(out_dir)), _worker_play, todo, cfg.jobs,
                                             on_tick=lambda: None):
                    keep_record(record)
        finally:
            bar.close()
            close_agents()
    with _interrupt_deferred():  # every episode is played: a Ctrl-C now waits for the results to be written
        world, _ = build_agent({**cfg_data, "agent": {"type": "random"}}, out_dir)
        records = [done[(t, s, b)] for t, s, b in wanted]
        return write_results(out_dir, cfg_data, records, world, figure=cfg.figure)


@contextlib.contextmanager
def _interrupt_deferred():
    """Hold a Ctrl-C (SIGINT) until the block is done, then raise it (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    received: list = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: received.append(signum))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
    if received:
        raise KeyboardInterrupt


def played(out_dir: Path) -> int:
    """How many episodes ``episodes.jsonl`` in ``out_dir`` holds."""
    return len(read_episodes(Path(out_dir) / EPISODES))


def agent_faults(result: dict) -> int:
    """How many of the run's episodes ended in a fault of the agent (not a fall)."""
    from overhang_framework.benchmark.score import AGENT_FAULTS

    return sum(n for kind, n in (result.get("failures") or {}).items() if kind in AGENT_FAULTS)


def _differences(old: Optional[dict], new: dict) -> str:
    def flat(d, prefix=""):
        out = {}
        for k, v in (d or {}).items():
            if isinstance(v, dict):
                out.update(flat(v, f"{prefix}{k}."))
            else:
                out[f"{prefix}{k}"] = v
        return out

    a, b = flat(old), flat(new)
    diffs = [f"{k}: {a.get(k)!r} -> {b.get(k)!r}" for k in sorted(set(a) | set(b)) if a.get(k) != b.get(k)]
    return "; ".join(diffs[:5]) + ("; ..." if len(diffs) > 5 else "")


def format_summary(result: dict) -> str:
    line = (f"{result['agent']} on {result['split']}: score {result['score']:.3f} "
            f"[{result['ci_low']:.3f}, {result['ci_high']:.3f}] (reward / optimum, 95% bootstrap over "
            f"{result['n_scored']} tasks x {result['seeds']} seeds); stood {100 * result['stood']:.1f}%, "
            f"mean reward {result['reward']:.3f}")
    if result.get("area") is not None:
        line += f"; area under score-against-{result['budget_kind']} {result['area']:.3f}"
    if result["missing_optima"]:
        line += f"; {len(result['missing_optima'])} tasks without an optimum under this physics are not scored"
    return line


@hydra.main(version_base="1.3", config_path=CONFIG_PATH, config_name=CONFIG_NAME)
def app(cfg: DictConfig) -> Optional[dict]:
    from overhang_framework.preflight import job_result

    out_dir = Path(HydraConfig.get().runtime.output_dir)
    result = job_result(lambda: run(cfg, out_dir), lambda: f"interrupted: {played(out_dir)} of {len(plan(cfg))} "
                        f"episodes are kept in {out_dir / EPISODES}; to resume, rerun the same command with "
                        f"hydra.run.dir={out_dir}", log)
    if result is None:
        return None
    print(format_summary(result))
    faults = agent_faults(result)
    if faults and faults == result["episodes"]:
        first = next((r for r in read_episodes(out_dir / EPISODES) if r.get("reason")), {}).get("reason", "")
        print(f"warning: every episode ended in a fault of the agent, e.g. {first!r}; see {out_dir / 'agent.log'} "
              f"and {out_dir / SCORES}", file=sys.stderr)
    if result["above_optimum"]:
        print(f"error: {', '.join(result['above_optimum'])} scored above its optimum: that optimum is wrong",
              file=sys.stderr)
    print(f"wrote {out_dir / SCORES}, {out_dir / SUMMARY}" + (f" and {out_dir / FIGURE}" if cfg.figure and
                                                              result["n_scored"] else ""))
    return {k: result[k] for k in ("score", "ci_low", "ci_high", "stood", "reward", "n_tasks")}


def main(argv: Optional[Sequence[str]] = None) -> None:
    from overhang_framework.preflight import run_app_command

    run_app_command(argv, app, CONFIG_NAME, check_config, __doc__, check_output=check_output_dir)

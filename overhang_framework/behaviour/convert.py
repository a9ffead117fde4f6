"""Model runs as behaviour logs: each repeat of a run is one simulated participant.

    python -m overhang_framework.behaviour.convert RUN_DIR [RUN_DIR...] --out log.jsonl

A RUN_DIR is a run directory of the main job (``episodes.jsonl`` with
``run.json`` or ``.hydra/config.yaml``) or a sweep directory, whose every job
is converted. Each episode becomes one trial, each of its steps one record:

* ``participant``: ``{label}/{repeat}``, the label naming predictor and planner
  (``veridical-myopic``, ``hybrid-lookahead3``: the planner's depth follows its
  name). When several runs converted together share a label, each label gets
  the config values that tell those runs apart, ``hybrid-lookahead3[condition=time_limited]``
  (a setting that follows from a differing name, such as the condition's
  ``time_limit``, left out), or the run's directory when their configs are the
  same, so participants stay distinct;
* ``condition``: the name of the run's condition; ``trial``: ``task_index + 1``;
* ``tower_before``: rebuilt by replaying the episode's steps from the ground block;
* ``reward``: the episode's reward, on its last step;
* ``timed_out``: always false. A model's condition never ends a trial on a
  timeout: a planner out of budget plays its best action so far and the
  episode goes on. Whether a decision went over the time limit is kept in
  the extra field ``over_time_limit``;
* ``source``: ``model``; extra fields ``seed``, and from each step
  ``predicted_stability``, ``choice_probability``, ``choice_rank``,
  ``over_time_limit`` and ``spend``, where the run recorded them.

Records are ordered by run, participant, trial and step. The log is checked
before it is written; any mistake stops the command with one line and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

from overhang_framework.behaviour.log import LOG_VERSION, describe, to_csv, to_frame, write_log
from overhang_framework.errors import OverhangError
from overhang_framework.report.aggregate import job_dirs
from overhang_framework.rundir import EPISODES, RUN_FILE, flatten, result_config

#: Fields of an episode's steps that each record keeps as extra fields, where the run has them.
STEP_EXTRAS = ("predicted_stability", "choice_probability", "choice_rank", "over_time_limit", "spend")


class ConvertError(OverhangError):
    """A directory that holds no finished run to convert, or a run's files that cannot be read."""


def config_of(run_dir: Path) -> dict:
    """The config a run's results belong to: ``run.json``, else Hydra's ``.hydra/config.yaml``."""
    run_file, hydra_file = run_dir / RUN_FILE, run_dir / ".hydra" / "config.yaml"
    try:
        if run_file.exists():
            return result_config(json.loads(run_file.read_text())["config"])
        if hydra_file.exists():
            import yaml

            return result_config(yaml.safe_load(hydra_file.read_text()) or {})
    except (ValueError, KeyError, TypeError) as exc:
        raise ConvertError(f"{run_file if run_file.exists() else hydra_file} is not a run's config ({exc})") from None
    raise ConvertError(f"{run_dir} has neither {RUN_FILE} nor .hydra/config.yaml: no config to name its model by")


def episodes_of(run_dir: Path) -> list[tuple[int, dict]]:
    """The finished episodes of a run with their line numbers; a run without ``episodes.jsonl`` is refused."""
    path = run_dir / EPISODES
    if not path.exists():
        unfinished = (run_dir / (EPISODES + ".partial")).exists()
        raise ConvertError(f"{run_dir} has no {EPISODES}" + (
            " (the run did not finish: rerun its command into the same directory to finish it)" if unfinished else ""))
    episodes = []
    with open(path, encoding="utf-8") as fh:
        for number, text in enumerate(fh, 1):
            if text.strip():
                try:
                    episodes.append((number, json.loads(text)))
                except ValueError as exc:
                    raise ConvertError(f"{path} line {number}: not JSON ({exc})") from None
    return episodes


def model_label(config: Mapping[str, Any]) -> str:
    """``{predictor}-{planner}{depth}``: ``veridical-myopic``, ``hybrid-lookahead3``."""
    predictor = (config.get("predictor") or {}).get("name", "unknown")
    planner = config.get("planner") or {}
    depth = planner.get("depth")
    return f"{predictor}-{planner.get('name', 'unknown')}{'' if depth is None else depth}"


def _flatten(data: Any) -> dict[str, str]:
    """The config as dotted keys, each value as text (strings as they are, the rest as compact JSON)."""
    return {k: v if isinstance(v, str) else json.dumps(v, separators=(",", ":")) for k, v in flatten(data).items()}


def _follows_from_name(key: str, flat: Sequence[Mapping[str, str]], differ: Sequence[str]) -> bool:
    """Whether ``key`` (``condition.time_limit``) varies only with its group's differing name (``condition.name``)."""
    name = key.split(".")[0] + ".name"
    if key == name or name not in differ:
        return False
    values: dict[str, set] = {}
    for f in flat:
        values.setdefault(f.get(name, "(unset)"), set()).add(f.get(key, "(unset)"))
    return all(len(v) == 1 for v in values.values())


def participant_labels(run_dirs: Sequence[Path], configs: Sequence[Mapping[str, Any]]) -> list[str]:
    """The label of each run's participants: :func:`model_label`, told apart where runs share it."""
    labels = [model_label(c) for c in configs]
    out = list(labels)
    for label in dict.fromkeys(labels):
        group = [i for i, other in enumerate(labels) if other == label]
        if len(group) < 2:
            continue
        flat = [_flatten(configs[i]) for i in group]
        keys = sorted({k for f in flat for k in f})
        differ = [k for k in keys if len({f.get(k, "(unset)") for f in flat}) > 1]
        differ = [k for k in differ if not _follows_from_name(k, flat, differ)]
        names = [",".join(f"{k.removesuffix('.name')}={f.get(k, '(unset)')}" for k in differ) for f in flat]
        if len(set(names)) < len(group):
            names = [str(run_dirs[i]) for i in group]
        for i, name in zip(group, names):
            out[i] = f"{label}[{name}]"
    return out


def episode_records(episode: Mapping[str, Any], participant: str, condition: str) -> list[dict]:
    """The records of one episode: one per step, ``tower_before`` rebuilt by replaying the steps."""
    sequence = [float(w) for w in episode["sequence"]]
    tower: list[list] = [[sequence[0], 0.0, 0]]
    steps = episode["steps"]
    records = []
    for number, step in enumerate(steps, 1):
        records.append({
            "log_version": LOG_VERSION, "participant": participant, "condition": condition,
            "task_id": str(episode["task_id"]), "sequence": sequence, "trial": int(episode["task_index"]) + 1,
            "step": number, "width": step["width"], "x": step["x"], "layer": step["layer"],
            "tower_before": [list(block) for block in tower], "stable": step["stable"],
            "overhang": step["overhang"], "reward": episode["reward"] if number == len(steps) else None,
            "decision_time": step["decision_time"], "timed_out": False, "source": "model",
            "seed": episode.get("seed"), **{k: step[k] for k in STEP_EXTRAS if k in step},
        })
        tower.append([step["width"], step["x"], step["layer"]])
    return records


def from_runs(dirs: Sequence[Path | str]) -> list[dict]:
    """The behaviour-log records of every run in ``dirs`` (run or sweep directories), in order:
    run, participant (repeat), trial (task order), step. Raises :class:`ConvertError`."""
    runs: list[Path] = []
    for d in dirs:
        found = job_dirs(d) if Path(d).is_dir() else []
        if not found:
            raise ConvertError(f"{d} holds no run (no {RUN_FILE} or .hydra/overrides.yaml in it or below it)")
        runs.extend(r for r in found if r not in runs)
    configs = [config_of(r) for r in runs]
    records: list[dict] = []
    for run_dir, config, label in zip(runs, configs, participant_labels(runs, configs)):
        condition = str((config.get("condition") or {}).get("name", "unknown"))
        episodes = episodes_of(run_dir)
        for number, episode in sorted(episodes, key=lambda e: (e[1].get("repeat", 0), e[1].get("task_index", 0))):
            try:
                records.extend(episode_records(episode, f"{label}/{episode.get('repeat', 0)}", condition))
            except (KeyError, TypeError, ValueError, IndexError) as exc:
                raise ConvertError(f"{run_dir / EPISODES} line {number}: not an episode record "
                                   f"({type(exc).__name__}: {exc})") from None
    return records


def from_run(run_dir: Path | str) -> list[dict]:
    """The behaviour-log records of one run directory, or of every job of a sweep directory."""
    return from_runs([run_dir])


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m overhang_framework.behaviour.convert",
                                 description="Write model runs as one behaviour log, each repeat one participant.")
    ap.add_argument("runs", nargs="+", metavar="RUN_DIR", help="a run directory, or a sweep directory")
    ap.add_argument("--out", required=True, help="the log to write: JSON Lines, or CSV when it ends in .csv")
    args = ap.parse_args(argv)
    try:
        df = to_frame(from_runs(args.runs))
        if args.out.lower().endswith(".csv"):
            to_csv(df, args.out)
        else:
            write_log(df, args.out)
    except OverhangError as exc:
        print(f"error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    print(f"{describe(df)}; written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

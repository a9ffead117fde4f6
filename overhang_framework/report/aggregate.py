"""One row per job of a sweep (or per run directory), with its overrides as columns: ``results.csv``.

A job directory is any directory under the sweep directory that holds a
``run.json`` (written before a run's first episode) or Hydra's
``.hydra/overrides.yaml``. Each row has:

* ``job``: the directory, relative to the sweep directory;
* ``status``: ``complete``, ``incomplete`` (stopped early; rerun to resume),
  ``failed`` (with ``error``, the first line of what went wrong) or
  ``missing`` (started, no results yet);
* one column per override of the job (``predictor``, ``planner.depth``, ...);
* the job's metrics: mean and SEM of reward, stability and overhang, the
  episodes finished and expected, wall time.

Everything is read from the files the jobs wrote, so it works the same for
jobs that ran on other machines (a cluster's shared file system) and for a
sweep that is still running or was interrupted.

    python -m overhang_framework.report.aggregate multirun/2026-11-23/10-00-00
"""

from __future__ import annotations

import csv
import io
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.results import atomic_write_text

METRICS = ("reward_mean", "reward_sem", "success_mean", "stable_placement_mean", "overhang_successful_mean",
           "decision_time_mean", "episodes", "episodes_expected", "wall_time")


def job_dirs(sweep_dir: Path | str) -> list[Path]:
    """The job directories under ``sweep_dir`` (itself, for a single run), in a stable order."""
    root = Path(sweep_dir)
    found = {p.parent for p in root.rglob("run.json")}
    found |= {p.parent.parent for p in root.rglob(".hydra/overrides.yaml")}
    if (root / "multirun.yaml").exists() or (root / ".hydra" / "multirun.yaml").exists():
        found.discard(root)
    return sorted(found, key=lambda p: [int(s) if s.isdigit() else s for s in p.relative_to(root).parts])


def overrides_of(job: Path) -> dict[str, str]:
    """The job's overrides as ``{key: value}`` (from Hydra's record of them)."""
    path = job / ".hydra" / "overrides.yaml"
    if not path.exists():
        return {}
    import yaml

    out = {}
    for word in yaml.safe_load(path.read_text()) or []:
        key, _, value = str(word).partition("=")
        out[key.lstrip("+~")] = value
    return out


def job_row(job: Path, root: Path) -> dict:
    """The ``results.csv`` row of one job."""
    row: dict = {"job": str(job.relative_to(root)) if job != root else ".", "status": "missing", "error": ""}
    row.update(overrides_of(job))
    metrics_file = job / "metrics.json"
    if metrics_file.exists():
        try:
            metrics = json.loads(metrics_file.read_text())
        except ValueError:
            metrics = {}
            row.update(status="failed", error="metrics.json is not JSON")
        if metrics:
            row["status"] = metrics.get("status") or ("complete" if metrics.get("complete") else "incomplete")
            row["error"] = metrics.get("error", "")
            for key in METRICS:
                row[key] = metrics.get(key)
    return row


def collect(sweep_dir: Path | str) -> list[dict]:
    root = Path(sweep_dir)
    return [job_row(job, root) for job in job_dirs(root)]


def to_csv(rows: list[dict]) -> str:
    """CSV text: ``job``, ``status``, the override columns in order of appearance, the metrics, ``error``."""
    overrides: list[str] = []
    for row in rows:
        for key in row:
            if key not in ("job", "status", "error", *METRICS) and key not in overrides:
                overrides.append(key)
    fields = ["job", "status", *overrides, *METRICS, "error"]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=fields, lineterminator="\n", extrasaction="ignore")
    writer.writeheader()
    for row in rows:
        writer.writerow({k: _cell(row.get(k)) for k in fields})
    return buf.getvalue()


def _cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def write_results(sweep_dir: Path | str) -> tuple[Path, list[dict]]:
    """Write ``results.csv`` into ``sweep_dir`` (atomically); return its path and rows."""
    rows = collect(sweep_dir)
    path = Path(sweep_dir) / "results.csv"
    atomic_write_text(path, to_csv(rows))
    return path, rows


def describe(rows: list[dict]) -> str:
    """One line: how many jobs, how many complete, and each failed or unfinished job by name."""
    counts: dict[str, int] = {}
    for row in rows:
        counts[row["status"]] = counts.get(row["status"], 0) + 1
    parts = [f"{len(rows)} job{'' if len(rows) == 1 else 's'}"] + [f"{n} {status}" for status, n in sorted(counts.items())]
    failed = [f"{r['job']} ({_overrides_text(r)}): {r['error']}" for r in rows if r["status"] == "failed"]
    line = ", ".join(parts)
    if failed:
        line += "; failed: " + "; ".join(failed)
    return line


def _overrides_text(row: dict) -> str:
    skip = {"job", "status", "error", *METRICS}
    return " ".join(f"{k}={v}" for k, v in row.items() if k not in skip and not k.startswith("hydra"))


def main(argv: Optional[Sequence[str]] = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m overhang_framework.report.aggregate",
                                     description="Write results.csv for a sweep directory.")
    parser.add_argument("sweep_dir")
    args = parser.parse_args(argv)
    if not Path(args.sweep_dir).is_dir():
        print(f"error: {args.sweep_dir} is not a directory", file=sys.stderr)
        return 2
    path, rows = write_results(args.sweep_dir)
    print(f"{path}: {describe(rows)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Running the leaderboard's rows again, each from its own command, timed: ``leaderboard rerun``.

Every row of the leaderboard keeps the command that made it. ``rerun`` runs those commands one after the
other, each into a directory of its own under ``OUT``, with the number of episodes played at once and the
reference's verdict cache set for the whole table (by default a cache of the table's own, so the table is
timed from a cold start), and writes the row's results, as the benchmark does. It keeps the wall time of
every sitting in ``OUT/timing.json`` (rewritten every few seconds, so a sitting that is killed is counted
to within them), so a table that takes longer than one sitting is run in parts and its time added up part
by part: run the same command again and it continues, the finished rows skipped, a stopped row from its
last kept episode. A row that fails is reported and the rest still run::

    python -m overhang_framework.benchmark.leaderboard rerun --out runs/leaderboard --dry-run   # the plan
    python -m overhang_framework.benchmark.leaderboard rerun --out runs/leaderboard --add       # run it
    python -m overhang_framework.benchmark.leaderboard rerun --out runs/leaderboard --report    # the times
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional, Sequence

PREFIX = ["python", "-m", "overhang_framework.benchmark"]
#: Words of a row's command that the rerun sets itself.
SET_HERE = ("hydra.run.dir=", "jobs=", "verdicts=", "progress=")
TIMING = "timing.json"
HEARTBEAT = 5.0


def slug(agent: str, split: str, ladder: bool) -> str:
    """The directory name of a row: ``test/lookahead-d-3-veridical``."""
    name = re.sub(r"[^a-z0-9]+", "-", agent.lower()).strip("-")
    return f"{split}/{name}{'-ladder' if ladder else ''}"


def row_words(command: str) -> list[str]:
    """The Hydra overrides of a leaderboard row's command, less the words the rerun sets."""
    try:
        words = shlex.split(command)
    except ValueError as err:
        raise ValueError(f"the command {command!r} does not parse as shell words ({err})") from None
    if words[:3] != PREFIX:
        raise ValueError(f"the command {command!r} is not a benchmark run (python -m overhang_framework.benchmark ...)")
    return [w for w in words[3:] if not w.startswith(SET_HERE)]


def timed(row) -> bool:
    """Whether a leaderboard row carries its wall time (a rerun put it there)."""
    return str(row.get("wall_seconds", "")) not in ("", "nan", "None")


def plan(board, out: Path, split: Optional[str] = None, agents: Sequence[str] = (), untimed: bool = False) -> list[dict]:
    """The rows to run, in the leaderboard's order: agent, split, directory and overrides of each (with
    ``untimed``, only the rows without a wall time)."""
    rows = []
    for _, r in board.iterrows():
        if split and r["split"] != split:
            continue
        if agents and r["agent"] not in agents:
            continue
        if untimed and timed(r):
            continue
        rows.append({"agent": r["agent"], "split": r["split"], "ladder": bool(r["curve"]),
                     "dir": str(out / slug(r["agent"], r["split"], bool(r["curve"]))), "words": row_words(r["command"])})
    missing = [a for a in agents if a not in set(board["agent"])]
    if missing:
        raise ValueError(f"no leaderboard row of agent {missing[0]!r}; agents: {', '.join(sorted(set(board['agent'])))}")
    return rows


def load_timing(out: Path) -> dict:
    path = out / TIMING
    if not path.exists():
        return {"segments": []}
    try:
        data = json.loads(path.read_text())
        assert isinstance(data.get("segments"), list)
        return data
    except (json.JSONDecodeError, AssertionError, AttributeError):
        raise ValueError(f"{path} is not a rerun's timing file (a JSON object with a list of segments)") from None


def _save_timing(out: Path, timing: dict) -> None:
    from overhang_framework.results import atomic_write_text

    atomic_write_text(out / TIMING, json.dumps(timing, indent=1) + "\n")


def finished(row: dict) -> bool:
    return (Path(row["dir"]) / "summary.json").exists()


def _episodes(row: dict) -> int:
    from overhang_framework.benchmark.run import played

    try:
        return played(Path(row["dir"]))
    except (OSError, ValueError):
        return 0


def run_row(row: dict, out: Path, timing: dict, jobs: int, verdicts: str) -> dict:
    """Run one row's command into its directory, its sitting kept in ``timing`` as it goes."""
    argv = [sys.executable, "-m", "overhang_framework.benchmark", *row["words"], f"hydra.run.dir={row['dir']}",
            f"jobs={jobs}", f"verdicts={verdicts}", "progress=true"]
    segment = {"agent": row["agent"], "split": row["split"], "ladder": row["ladder"], "dir": row["dir"],
               "started": _dt.datetime.now().isoformat(timespec="seconds"), "wall": 0.0, "jobs": jobs,
               "episodes_before": _episodes(row), "episodes_after": None, "returncode": None,
               "load_max": os.getloadavg()[0], "cpus": os.cpu_count()}
    timing["segments"].append(segment)
    _save_timing(out, timing)
    log_path = Path(row["dir"] + ".log")
    log_path.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with open(log_path, "a") as log:
        log.write(f"\n$ {shlex.join(argv)}\n")
        log.flush()
        # a session of its own: a Ctrl-C reaches the row through this process, which stops it cleanly
        proc = subprocess.Popen(argv, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            while True:
                try:
                    proc.wait(timeout=HEARTBEAT)
                    break
                except subprocess.TimeoutExpired:
                    pass
                segment["wall"] = round(time.perf_counter() - start, 1)
                segment["load_max"] = max(segment["load_max"], os.getloadavg()[0])
                _save_timing(out, timing)
        except BaseException:
            proc.send_signal(signal.SIGINT)  # the benchmark keeps every finished episode
            try:
                proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                os.killpg(proc.pid, signal.SIGKILL)  # the row's workers and programs too
                proc.wait()
            raise
        finally:
            segment["wall"] = round(time.perf_counter() - start, 1)
            segment["returncode"] = proc.poll()
            segment["episodes_after"] = _episodes(row)
            _save_timing(out, timing)
    return segment


def last_error(row: dict) -> str:
    """The last line of a failed row's log that says what went wrong."""
    try:
        lines = [ln.strip() for ln in Path(row["dir"] + ".log").read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return "no log"
    errors = [ln for ln in lines if ln.lower().startswith(("error", "usage", "traceback")) or "Error" in ln]
    return (errors or lines or ["no output"])[-1][:300]


def report(rows: Sequence[dict], timing: dict) -> str:
    """A Markdown table of the rows' wall times (every sitting added up), their state and the load seen."""
    lines = ["| agent | split | state | sittings | wall | episodes | s / decision (run's own) | highest load |",
             "|---|---|---|---|---|---|---|---|"]
    total = 0.0
    for row in rows:
        segs = [s for s in timing["segments"] if s["dir"] == row["dir"]]
        wall = sum(s["wall"] for s in segs)
        total += wall
        summary = Path(row["dir"]) / "summary.json"
        secs = ""
        if summary.exists():
            s = json.loads(summary.read_text())
            state, secs = "done", ("" if s.get("seconds_per_decision") is None else f"{s['seconds_per_decision']:.3f}")
        elif not segs:
            state = "to run"
        elif segs[-1]["returncode"] in (None, 130) or segs[-1]["returncode"] < 0:
            state = "stopped"  # interrupted or killed: the same command continues it
        else:
            state = "failed"
        load = f"{max(s['load_max'] for s in segs):.1f}" if segs else ""
        agent = row["agent"] + (" (ladder)" if row["ladder"] else "")
        lines.append(f"| {agent} | {row['split']} | {state} | {len(segs)} | {_clock(wall)} | {_episodes(row)} | {secs} | "
                     f"{load} |")
    done = sum(finished(r) for r in rows)
    lines.append(f"\n{done} of {len(rows)} rows done; wall time of every sitting added up: {_clock(total)}")
    return "\n".join(lines)


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


def rerun(board_file: Path, out: Path, split: Optional[str] = None, agents: Sequence[str] = (), jobs: Optional[int] = None,
          verdicts: Optional[str] = None, add: bool = False, dry_run: bool = False, show_report: bool = False,
          untimed: bool = False) -> int:
    """The ``rerun`` subcommand: 0 when every chosen row is done, 1 when one failed."""
    from overhang_framework.benchmark.board import load

    board = load(board_file)
    rows = plan(board, out, split, agents, untimed)
    if not rows:
        raise ValueError(f"no leaderboard rows to run in {board_file}" + (f" on split {split}" if split else ""))
    jobs = jobs or os.cpu_count() or 1
    if jobs < 1:
        raise ValueError(f"--jobs must be at least 1, got {jobs}")
    verdicts = str(Path(verdicts).expanduser().resolve()) if verdicts else str((out / "verdicts.sqlite").resolve())
    timing = load_timing(out)
    if show_report:
        print(report(rows, timing))
        return 0
    if dry_run:
        for k, row in enumerate(rows, 1):
            state = "done" if finished(row) else (f"{_episodes(row)} episodes kept" if _episodes(row) else "to run")
            print(f"[{k}/{len(rows)}] {row['agent']} ({row['split']}; {state}): python -m overhang_framework.benchmark "
                  f"{shlex.join(row['words'])} hydra.run.dir={row['dir']} jobs={jobs} verdicts={verdicts}")
        return 0
    out.mkdir(parents=True, exist_ok=True)
    failed = []
    previous = signal.signal(signal.SIGTERM, _stop)
    # A shell starts a background job with SIGINT ignored, and a row would inherit that and could not be
    # stopped cleanly; a handler of this process's own is the default again in each row's process.
    ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    if ignored:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        _run_rows(rows, out, timing, jobs, verdicts, board_file, add, failed)
    finally:
        signal.signal(signal.SIGTERM, previous)
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
    print(report(rows, timing))
    if failed:
        print(f"error: {len(failed)} rows failed: {', '.join(r['agent'] + ' (' + r['split'] + ')' for r in failed)}; "
              f"their logs are beside their directories under {out}", file=sys.stderr)
        return 1
    return 0


def _stop(signum, frame):
    raise KeyboardInterrupt


def _run_rows(rows, out, timing, jobs, verdicts, board_file, add, failed) -> None:
    """Run every row not yet done, in order; a failed one goes into ``failed`` and the next runs."""
    from overhang_framework.benchmark.board import add as add_rows, row_of

    for k, row in enumerate(rows, 1):
        name = f"[{k}/{len(rows)}] {row['agent']} ({row['split']}{', ladder' if row['ladder'] else ''})"
        if finished(row):
            print(f"{name}: done before, skipped", flush=True)
            continue
        print(f"{name}: running into {row['dir']} (log {row['dir']}.log)", flush=True)
        segment = run_row(row, out, timing, jobs, verdicts)
        if segment["returncode"] != 0 or not finished(row):
            failed.append(row)
            print(f"{name}: failed (exit {segment['returncode']}): {last_error(row)}", flush=True)
            continue
        print(f"{name}: done in {_clock(segment['wall'])} ({segment['episodes_after'] - segment['episodes_before']} "
              f"episodes this sitting)", flush=True)
        if add:
            try:
                segments = [s for s in timing["segments"] if s["dir"] == row["dir"]]
                used = {s["jobs"] for s in segments}
                add_rows([row_of(Path(row["dir"]), row["agent"], sum(s["wall"] for s in segments),
                                 used.pop() if len(used) == 1 else None)], board_file)
            except (FileNotFoundError, KeyError, ValueError) as err:
                failed.append(row)
                print(f"{name}: finished, but not put into the leaderboard: {err}", flush=True)

"""Benchmark runs that a refused command, a bad option or a faulty program cannot corrupt or make irreproducible."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from test_benchmark import FIVE, ROOT, bench, scores_without_time

from overhang_framework.benchmark import score


def _snapshot(folder: Path) -> dict:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ------------------------------------------------------------------------------------------------ refused runs

def test_a_refused_run_leaves_the_finished_folder_byte_identical(tmp_path):
    out, _ = bench(tmp_path, FIVE, "seeds=1")
    before = _snapshot(out)
    assert ".hydra/overrides.yaml" in before and "summary.json" in before
    _, proc = bench(tmp_path, FIVE, "seeds=2", check=False)
    assert proc.returncode == 2 and "holds results of a different config (seeds: 1 -> 2)" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert _snapshot(out) == before


@pytest.mark.parametrize("value", ["0", "-1", "abc"])
def test_a_bad_agent_timeout_is_one_line_and_writes_nothing(tmp_path, value):
    out, proc = bench(tmp_path, "agent=command", "agent.command=[python3,examples/agents/lean.py]",
                      f"agent.timeout={value}", FIVE, check=False)
    assert proc.returncode == 2, proc.stderr
    shown = repr(value) if value == "abc" else value
    assert proc.stderr.strip().splitlines() == [
        f"error: agent.timeout must be a number of seconds > 0 (the default is 30), got {shown}"]
    assert not out.exists()


def test_every_bad_option_is_named_in_the_one_line(tmp_path):
    out, proc = bench(tmp_path, "agent=command", "agent.command=[python3,examples/agents/lean.py]",
                      "agent.timeout=0", "seeds=0", "agent.render=maybe", check=False)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    for part in ("seeds must be a whole number >= 1", "agent.timeout must be", "agent.render must be true or false"):
        assert part in proc.stderr, proc.stderr
    assert not out.exists()


def test_a_string_command_is_told_to_be_a_list_not_missing(tmp_path):
    _, proc = bench(tmp_path, "agent=command", "agent.command='python3 examples/agents/lean.py'", FIVE, check=False)
    assert proc.returncode == 2
    assert "agent.command must be a list of words, got the string 'python3 examples/agents/lean.py'" in proc.stderr
    assert "agent.command=[python3,examples/agents/lean.py]" in proc.stderr
    assert "needs agent.command" not in proc.stderr


@pytest.mark.parametrize("command,message", [
    ("[no-such-program-here]", "agent.command's program 'no-such-program-here' is not found on the PATH"),
    ("[python3,no_such_agent.py]", "agent.command exited (exit code 2) before it answered anything"),
], ids=["missing", "exits"])
def test_a_program_that_cannot_start_is_refused_before_the_first_episode(tmp_path, command, message):
    out, proc = bench(tmp_path, "agent=command", f"agent.command={command}", FIVE, check=False)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert message in proc.stderr
    # refused by the command line's check (nothing written), or, on a machine too busy for it to exit within
    # the check's second, by its first decision (no episode played)
    assert not out.exists() or not (out / "episodes.jsonl").read_text().strip()


SLOW_TO_FAIL = '''
import sys, time
time.sleep(1.5)  # as a program that loads a large library first
sys.exit("cannot load the model: weights.bin is missing")
'''


def test_a_program_that_fails_after_the_check_stops_the_run_at_its_first_decision(tmp_path):
    program = tmp_path / "slow_to_fail.py"
    program.write_text(SLOW_TO_FAIL)
    out, proc = bench(tmp_path, "agent=command", f"agent.command=[{sys.executable},{program}]", FIVE, check=False)
    assert proc.returncode == 2, proc.stderr
    line = proc.stderr.strip().splitlines()[-1]
    assert line.startswith("error: agent.command exited (exit code 1) before it answered anything: ") and \
        line.endswith("cannot load the model: weights.bin is missing"), line
    assert not (out / "episodes.jsonl").read_text().strip() and not (out / "scores.csv").exists()


GARBAGE = '''
import sys
for line in sys.stdin:
    if '"decision"' in line:
        print("no", flush=True)
'''


def test_a_run_whose_every_episode_is_a_fault_says_so(tmp_path):
    program = tmp_path / "garbage.py"
    program.write_text(GARBAGE)
    out, proc = bench(tmp_path, "agent=command", f"agent.command=[{sys.executable},{program}]",
                      "ids=[w121223,w122321]", "seeds=1")
    assert "warning: every episode ended in a fault of the agent, e.g. 'malformed answer at placement 1" \
           in proc.stderr, proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failures"] == {"malformed answer": 2}
    rows = pd.read_csv(out / "scores.csv", keep_default_na=False)
    assert (rows["calls"] == "").all()  # a program counts no predictor calls, faulted or not


# ------------------------------------------------------------------------------------------------ programs that exit

EXITS = '''
import json, sys, time
ended = 0
for line in sys.stdin:
    m = json.loads(line)
    if m["type"] == "end":
        ended += 1
        if ended % 2 == 0:
            time.sleep(DELAY)
            sys.exit(0)
        continue
    x, layer = max(m["legal"], key=lambda p: (p[1], -abs(p[0])))
    print(json.dumps({"x": x, "layer": layer}), flush=True)
'''


@pytest.mark.parametrize("delay", [pytest.param(0.0, marks=pytest.mark.slow), 0.3], ids=["at-once", "slowly"])
def test_a_program_that_exits_between_episodes_scores_the_same_on_every_run(tmp_path, delay):
    # slowly: the program is still alive when the next episode's first decision is sent, and dies reading it
    program = tmp_path / "exits.py"
    program.write_text(EXITS.replace("DELAY", str(delay)))
    word = f"agent.command=[{sys.executable},{program}]"
    three = "ids=[w121223,w122321,w212333]"
    runs = [bench(tmp_path, "agent=command", word, three, "seeds=2", name=f"r{k}")[0] for k in range(3)]
    first = scores_without_time(runs[0])
    assert len(first) == 6 and first["reason"].isna().all(), first["reason"].tolist()
    for other in runs[1:]:
        pd.testing.assert_frame_equal(first, scores_without_time(other))


STOPS = '''
import json, os, sys
for line in sys.stdin:
    m = json.loads(line)
    if m["type"] == "decision":
        x, layer = max(m["legal"], key=lambda p: (p[1], -abs(p[0])))
        print(json.dumps({"x": x, "layer": layer}), flush=True)
        if m["step"] == 1 and not os.path.exists("MARK"):  # only the first process stops; another would go on
            open("MARK", "w").close()
            sys.exit(4)
'''


def test_a_program_that_stops_during_an_episode_has_crashed_whatever_its_speed(tmp_path):
    from overhang_framework.benchmark.agents import play
    from overhang_framework.benchmark.external import CommandAgent
    from overhang_framework.benchmark.splits import task
    from overhang_framework.plugins import Registry

    program = tmp_path / "stops.py"
    program.write_text(STOPS.replace("MARK", str(tmp_path / "stopped")))
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    agent = CommandAgent(world, [sys.executable, str(program)], timeout=10, workdir=tmp_path)
    original = agent.choose

    def slow_choose(state, task_, step, budget):  # the program is surely gone before step 2 is sent
        if step == 2:
            time.sleep(0.5)
        return original(state, task_, step, budget)

    agent.choose = slow_choose
    try:
        record = play(agent, world, task("w121223"), 0)
    finally:
        agent.close()
    assert record["reason"] == "agent crashed at placement 2 (exit code 4); see agent.log"
    assert len(record["steps"]) == 1 and record["reward"] == 0


def test_a_timed_out_decision_counts_its_seconds_and_no_calls(tmp_path):
    from overhang_framework.benchmark.agents import play
    from overhang_framework.benchmark.external import CommandAgent
    from overhang_framework.benchmark.splits import task
    from overhang_framework.plugins import Registry

    program = tmp_path / "hangs.py"
    program.write_text("import sys, time\nfor line in sys.stdin:\n    time.sleep(60)\n")
    world = Registry().create("world", {"name": "overhang", "physics": "static"})
    agent = CommandAgent(world, [sys.executable, str(program)], timeout=0.5, workdir=tmp_path)
    try:
        record = play(agent, world, task("w121223"), 0)
    finally:
        agent.close()
    assert record["reason"].startswith("agent gave no answer within 0.5 s at placement 1")
    assert record["seconds"] >= 0.5 and record["calls"] is None


def test_agent_log_is_capped_and_says_how_much_it_dropped(tmp_path):
    from overhang_framework.benchmark.external import CappedLog

    log = CappedLog(tmp_path / "agent.log", cap=1000)
    for _ in range(5):
        log.write(b"x" * 400)
    log.close()
    text = (tmp_path / "agent.log").read_bytes()
    assert text.startswith(b"x" * 1000) and text.count(b"x") == 1000
    assert b"1000 more bytes of the program's stderr were dropped" in text
    again = CappedLog(tmp_path / "agent.log", cap=1000)  # a resumed run appends within the same cap
    again.write(b"y" * 10)
    again.close()
    assert b"yyyyyyyyyy" not in (tmp_path / "agent.log").read_bytes()


# ------------------------------------------------------------------------------------------------ summaries

def test_failures_are_counted_by_kind_not_by_their_particulars():
    reasons = ["illegal placement x=3.95, layer=1: off the grid (placement 1)",
               "illegal placement x=-2.1, layer=3: nothing below (placement 4)",
               "agent crashed at placement 1 (exit code 3); see agent.log",
               "agent crashed at placement 5 (exit code 1); see agent.log",
               "agent gave no answer within 2 s at placement 3", "the tower fell at placement 2",
               "malformed answer at placement 1: 'left' is not JSON", ""]
    rows = [{"task_id": f"w12122{k}", "seed": 0, "reward": 0.0, "normalised": 0.0, "stood": not r, "calls": None,
             "seconds": 1.0, "reason": r, "steps": 1} for k, r in enumerate(reasons)]
    assert score.summary(rows)["failures"] == {"agent crashed": 2, "agent gave no answer": 1, "fell": 1,
                                               "illegal placement": 2, "malformed answer": 1}


def test_simulated_people_that_coincide_are_drawn_as_one_line():
    from overhang_framework.benchmark.figures import _merged

    rows = [{"condition": "time_limited", "reward": 1.4335}, {"condition": "unconstrained", "reward": 1.4365}]
    assert _merged(rows, "reward") == [[("time_limited", 1.4335), ("unconstrained", 1.4365)]]
    apart = [{"condition": "time_limited", "reward": 1.2}, {"condition": "unconstrained", "reward": 1.4365}]
    assert len(_merged(apart, "reward")) == 2


def test_the_protocol_document_shows_what_the_benchmark_sends():
    from overhang_framework.benchmark.external import example_messages

    doc = (ROOT / "docs" / "benchmark-protocol.md").read_text()
    blocks = [json.loads(b) for b in re.findall(r"```json\n(.*?)\n```", doc, flags=re.S)]
    decision, end = example_messages()
    assert decision in blocks and end in blocks
    legal = {tuple(p) for p in decision["legal"]}
    assert len(legal) == len(decision["legal"])  # no placement listed twice
    assert "the largest `|x| + width / 2` over its blocks" in doc  # the reward is defined


# ------------------------------------------------------------------------------------------------ interrupts

def test_an_interrupt_while_results_are_written_still_leaves_them(tmp_path, monkeypatch):
    from omegaconf import OmegaConf

    from overhang_framework.benchmark import run as bench_run
    from overhang_framework.config import compose_config

    cfg = compose_config(["world.physics=static", "verdicts=null", "progress=false", "ids=[w121223]", "seeds=1"],
                         config_name="benchmark")
    OmegaConf.set_struct(cfg, False)
    written = bench_run.write_results

    def interrupted_write(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C after the last episode
        return written(*args, **kwargs)

    monkeypatch.setattr(bench_run, "write_results", interrupted_write)
    with pytest.raises(KeyboardInterrupt):
        bench_run.run(cfg, tmp_path / "run")
    assert (tmp_path / "run" / "score.png").exists() and (tmp_path / "run" / "summary.json").exists()


SLOW = '''
import json, sys, time
for line in sys.stdin:
    m = json.loads(line)
    if m["type"] == "decision":
        time.sleep(0.2)
        x, layer = m["legal"][0]
        print(json.dumps({"x": x, "layer": layer}), flush=True)
'''


@pytest.mark.parametrize("jobs", [1, 2])
def test_ctrl_c_stops_the_run_at_once_and_says_how_many_episodes_are_kept(tmp_path, jobs):
    from test_benchmark import STATIC

    program = tmp_path / "slow.py"
    program.write_text(SLOW)
    out = tmp_path / "run"
    proc = subprocess.Popen([sys.executable, "-m", "overhang_framework.benchmark", *STATIC, "agent=command",
                             f"agent.command=[{sys.executable},{program}]", FIVE, "seeds=8", f"jobs={jobs}",
                             f"hydra.run.dir={out}"], cwd=ROOT, stderr=subprocess.PIPE, text=True)
    episodes = out / "episodes.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (episodes.exists() and episodes.read_text().count("\n") >= 2):
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    stopped = time.time()
    _, err = proc.communicate(timeout=60)
    # the 40 episodes take about 40 s of the agent's time; a stopped run does not play the rest first
    assert proc.returncode == 130 and time.time() - stopped < 10, err
    kept = len(episodes.read_text().splitlines())
    assert kept < 20 and f"interrupted: {kept} of 40 episodes are kept in {episodes}" in err, err
    time.sleep(2)  # a worker ends with its parent within a second
    left = subprocess.run(["pgrep", "-f", str(program)], capture_output=True, text=True).stdout.split()
    assert not left, "the agent's programs outlived the run"


# ------------------------------------------------------------------------------------------------ leaderboard

def test_the_leaderboard_refuses_a_run_of_task_ids_and_an_unknown_split(tmp_path):
    from overhang_framework.benchmark import leaderboard

    out, _ = bench(tmp_path, "ids=[w121223]", "seeds=1")
    board = tmp_path / "board.csv"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework.benchmark.leaderboard", "add", str(out),
                           "--file", str(board)], cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2 and not board.exists()
    assert "played a list of task ids (ids=[...]), not a split; the leaderboard ranks whole splits" in proc.stderr
    assert leaderboard.main(["show", "--split", "tset", "--file", str(board)]) == 2


def _board_row(agent: str, split: str, command: str) -> dict:
    from overhang_framework.benchmark import leaderboard

    row = {c: "" for c in leaderboard.COLUMNS}
    return {**row, "agent": agent, "split": split, "score": 0.5, "ci_low": 0.4, "ci_high": 0.6, "stood": 1.0,
            "reward": 1.0, "n_tasks": 10, "seeds": 1, "command": command, "date": "2000-01-01"}


def test_rerun_runs_each_row_again_timed_keeps_going_past_a_failure_and_continues_where_it_stopped(tmp_path):
    from overhang_framework.benchmark import leaderboard

    board = tmp_path / "board.csv"
    random_row = "python -m overhang_framework.benchmark split=cross agent=random seeds=1 figure=false"
    leaderboard.add([_board_row("random", "cross", random_row),
                     _board_row("myopic + nonesuch", "cross", "python -m overhang_framework.benchmark split=cross "
                                "predictor=nonesuch")], board)
    out = tmp_path / "rerun"

    def rerun(*words):
        return subprocess.run([sys.executable, "-m", "overhang_framework.benchmark.leaderboard", "rerun", "--out",
                               str(out), "--file", str(board), "--jobs", "1", *words], cwd=ROOT, capture_output=True,
                              text=True, timeout=600)

    plan = rerun("--dry-run")
    assert plan.returncode == 0 and plan.stdout.count("to run") == 2 and not (out / "timing.json").exists()
    first = rerun("--add")
    assert first.returncode == 1, first.stderr
    assert "myopic + nonesuch (cross): failed (exit 2): " in first.stdout and "nonesuch" in first.stdout.split(
        "failed (exit 2): ")[1].splitlines()[0]
    assert "error: 1 rows failed: myopic + nonesuch (cross)" in first.stderr
    run_dir = out / "cross" / "random"
    summary = json.loads((run_dir / "summary.json").read_text())
    rows = leaderboard.load(board).set_index("agent")
    assert float(rows.loc["random", "score"]) == pytest.approx(summary["score"], abs=1e-6)
    assert rows.loc["random", "date"] != "2000-01-01" and rows.loc["myopic + nonesuch", "date"] == "2000-01-01"
    assert float(rows.loc["random", "wall_seconds"]) > 0 and int(rows.loc["random", "jobs"]) == 1
    # the row's command is the one it ran, less this machine's verdict cache
    assert rows.loc["random", "command"] == random_row + " jobs=1"
    assert re.search(r"\| random \| cross \| .* \| \d+\.\d min \(1\) \|$", leaderboard.markdown(rows.reset_index()),
                     re.M)
    timing = json.loads((out / "timing.json").read_text())["segments"]
    assert sorted((s["agent"], s["returncode"], s["episodes_before"], s["episodes_after"]) for s in timing) == [
        ("myopic + nonesuch", 2, 0, 0), ("random", 0, 0, 10)]
    assert all(s["wall"] > 0 and s["jobs"] == 1 for s in timing)
    second = rerun()  # the finished row is skipped, the failed one tried again
    assert second.returncode == 1 and "random (cross): done before, skipped" in second.stdout
    assert sorted(s["agent"] for s in json.loads((out / "timing.json").read_text())["segments"]) == [
        "myopic + nonesuch", "myopic + nonesuch", "random"]
    report = rerun("--report").stdout
    assert re.search(r"\| random \| cross \| done \| 1 \| 0:00:\d\d \| 10 \|", report), report
    assert "| myopic + nonesuch | cross | failed | 2 |" in report and "1 of 2 rows done" in report
    assert rerun("--agent", "nobody", "--dry-run").stderr.startswith("error: no leaderboard row of agent 'nobody'")
    untimed = rerun("--untimed", "--dry-run").stdout  # the random row carries its wall time now
    assert "myopic + nonesuch" in untimed and "random" not in untimed


@pytest.mark.parametrize("background", [False, True], ids=["foreground", "background"])
def test_a_stopped_rerun_counts_its_sitting_and_the_next_one_continues_from_the_kept_episodes(tmp_path, background):
    """Also started as a shell starts a background job, with SIGINT ignored: the row is still stopped by its
    SIGINT (exit 130), not killed after the minute the rerun gives it."""
    from overhang_framework.benchmark import leaderboard

    program = tmp_path / "slow.py"
    program.write_text(SLOW)
    board = tmp_path / "board.csv"
    command = (f"python -m overhang_framework.benchmark split=cross agent=command 'agent.command=[{sys.executable},"
               f"{program}]' seeds=1 world.physics=static figure=false")
    leaderboard.add([_board_row("command: slow.py", "cross", command)], board)
    out = tmp_path / "rerun"
    argv = [sys.executable, "-m", "overhang_framework.benchmark.leaderboard", "rerun", "--out", str(out), "--file",
            str(board), "--jobs", "1"]
    ignore = (lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)) if background else None
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=ignore)
    episodes = out / "cross" / "command-slow-py" / "episodes.jsonl"
    deadline = time.time() + 120
    while time.time() < deadline and not (episodes.exists() and episodes.read_text().count("\n") >= 2):
        time.sleep(0.1)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130 and "interrupted: every finished episode is kept" in err, err
    kept = len(episodes.read_text().splitlines())
    [segment] = json.loads((out / "timing.json").read_text())["segments"]
    assert 2 <= kept < 10 and segment["episodes_after"] == kept and segment["returncode"] == 130
    assert segment["wall"] > 0
    report = subprocess.run([*argv, "--report"], cwd=ROOT, capture_output=True, text=True, timeout=120).stdout
    assert "| command: slow.py | cross | stopped | 1 |" in report and "0 of 1 rows done" in report, report
    done = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    segments = json.loads((out / "timing.json").read_text())["segments"]
    assert [(s["episodes_before"], s["episodes_after"]) for s in segments] == [(0, kept), (kept, 10)]
    assert "1 of 1 rows done" in done.stdout


def test_every_leaderboard_row_can_run_again_from_a_clean_clone():
    from overhang_framework.benchmark import leaderboard
    from overhang_framework.benchmark.rerun import row_words
    from overhang_framework.envs.policies import policy_path

    board = leaderboard.load()
    assert len(board) and set(board["split"]) <= set(leaderboard.SPLITS)
    for _, row in board.iterrows():
        words = dict(w.split("=", 1) for w in row_words(row["command"]))
        if "planner.path" in words:
            assert policy_path(words["planner.path"]).is_relative_to(ROOT), row["agent"]
        if "agent.command" in words:
            program = words["agent.command"].strip("[]").split(",")[-1]
            assert (ROOT / program).is_file(), row["agent"]

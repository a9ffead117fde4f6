"""A run never loses finished work: interrupt, resume, refusal of another config's directory."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from overhang_framework.results import read_episodes, without_timing
from overhang_framework.rundir import RunDir, RunDirError

ROOT = Path(__file__).resolve().parents[1]
# Three short tasks judged and played on full PyBullet: slow enough (about a second an episode) to
# interrupt. (The default tiered world plays them in about 0.1 s each, too fast on a loaded machine.)
SLOW = ["tasks=custom", "tasks.sequences=[[1.2,0.6,1.8],[0.6,1.2,1.2],[1.8,0.6,0.6]]", "world.physics=pybullet"]
FAST = ["tasks=custom", "tasks.sequences=[[1.2,0.6,1.8],[0.6,1.2,1.2]]", "world.physics=static",
        "progress=false"]


def command(*args):
    return [sys.executable, "-m", "overhang_framework", *args]


def start(*args) -> subprocess.Popen:
    """The command in a child that Ctrl-C reaches, as at a terminal: a shell without job control (a
    script's ``cmd &``, nohup) starts its children with SIGINT ignored, and they would inherit that."""
    return subprocess.Popen(command(*args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def run(*args):
    return subprocess.run(command(*args), capture_output=True, text=True, cwd=ROOT)


def interrupt_after_first_episode(args, partial: Path) -> subprocess.CompletedProcess:
    proc = start(*args)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if partial.exists() and partial.read_text().count("\n") >= 1:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


@pytest.mark.slow
def test_an_interrupted_run_resumes_and_keeps_every_finished_episode_once(tmp_path):
    out = tmp_path / "run"
    args = [*SLOW, f"hydra.run.dir={out}"]
    stopped = interrupt_after_first_episode(args, out / "episodes.jsonl.partial")
    assert stopped.returncode == 130, stopped.stderr
    last = stopped.stderr.strip().splitlines()[-1]
    assert last.startswith("interrupted: ") and f"hydra.run.dir={out}" in last
    assert "Traceback" not in stopped.stderr
    finished = (out / "episodes.jsonl.partial").read_bytes()
    n_finished = finished.count(b"\n")
    assert 1 <= n_finished < 3 and f"{n_finished} of 3 episodes finished" in last
    metrics = json.loads((out / "metrics.json").read_text())
    assert (metrics["complete"], metrics["episodes"], metrics["episodes_expected"]) == (False, n_finished, 3)

    resumed = run(*args, "progress=false")
    assert resumed.returncode == 0, resumed.stderr
    assert f"({n_finished} finished earlier in this directory)" in resumed.stdout
    final = (out / "episodes.jsonl").read_bytes()
    assert final.startswith(finished), "the finished episodes are kept byte for byte"
    episodes = read_episodes(out / "episodes.jsonl")
    assert [(e["task_index"], e["repeat"]) for e in episodes] == [(0, 0), (1, 0), (2, 0)]
    after = json.loads((out / "metrics.json").read_text())
    assert after["complete"] is True
    # the wall time and the physics counters cover both sessions, not only the resumed one
    assert after["wall_time"] == pytest.approx(metrics["wall_time"] + after["wall_time_session"], rel=1e-9)
    assert after["wall_time_session"] < after["wall_time"]

    fresh = run(*SLOW, "progress=false", f"hydra.run.dir={tmp_path / 'fresh'}")
    assert fresh.returncode == 0, fresh.stderr
    assert without_timing(episodes) == without_timing(read_episodes(tmp_path / "fresh" / "episodes.jsonl"))
    alone = json.loads((tmp_path / "fresh" / "metrics.json").read_text())["world_stats"]["cache"]
    both = after["world_stats"]["cache"]
    # the same episodes ask the same questions; both sessions together asked at least as many
    assert both["hits"] + both["misses"] >= alone["hits"] + alone["misses"]
    assert both["misses"] >= metrics["world_stats"]["cache"]["misses"]
    assert both["hit_rate"] == pytest.approx(both["hits"] / (both["hits"] + both["misses"]))
    assert not (out / ".run.lock").exists() and not (tmp_path / "fresh" / ".run.lock").exists()


def test_rerunning_a_finished_run_changes_nothing(tmp_path):
    args = [*FAST, f"hydra.run.dir={tmp_path}"]
    assert run(*args).returncode == 0
    before = (tmp_path / "episodes.jsonl").read_bytes()
    metrics = (tmp_path / "metrics.json").read_bytes()
    again = run(*args)
    assert again.returncode == 0, again.stderr
    assert "(2 finished earlier in this directory)" in again.stdout
    assert (tmp_path / "episodes.jsonl").read_bytes() == before
    assert json.loads((tmp_path / "metrics.json").read_text())["episodes"] == 2
    assert (tmp_path / "metrics.json").read_bytes() == metrics, "the finished run's metrics are kept"


def test_a_directory_of_another_config_is_refused_unless_overwrite(tmp_path):
    assert run(*FAST, "seed=1", f"hydra.run.dir={tmp_path}").returncode == 0
    before = (tmp_path / "episodes.jsonl").read_bytes()
    refused = run(*FAST, "seed=2", "world.resolution=0.2", f"hydra.run.dir={tmp_path}")
    assert refused.returncode == 2
    assert refused.stderr.strip().splitlines() == [
        f"error: {tmp_path} holds results of a different config (seed: 1 -> 2; world.resolution: 0.1 -> 0.2); "
        "use another hydra.run.dir, or overwrite=true to replace them"]
    assert (tmp_path / "episodes.jsonl").read_bytes() == before
    assert "seed=1" in (tmp_path / ".hydra" / "overrides.yaml").read_text(), "a refused run writes nothing"
    replaced = run(*FAST, "seed=2", "world.resolution=0.2", "overwrite=true", f"hydra.run.dir={tmp_path}")
    assert replaced.returncode == 0, replaced.stderr
    assert {e["seed"] for e in read_episodes(tmp_path / "episodes.jsonl")} == {2}


def test_presentation_settings_do_not_count_as_another_config(tmp_path):
    assert run(*FAST, f"hydra.run.dir={tmp_path}").returncode == 0
    assert run(*FAST, "progress=true", f"hydra.run.dir={tmp_path}").returncode == 0


def test_episodes_without_a_run_description_are_refused(tmp_path):
    (tmp_path / "episodes.jsonl").write_text('{"task_index": 0, "repeat": 0}\n')
    with pytest.raises(RunDirError, match="episodes of an unknown config"):
        RunDir(tmp_path).prepare({"seed": 0})


def test_a_line_cut_short_by_a_crash_is_dropped_and_the_rest_kept(tmp_path):
    rundir = RunDir(tmp_path)
    assert rundir.prepare({"seed": 0}) == []
    good = json.dumps({"task_index": 0, "repeat": 0, "reward": 1.5}) + "\n"
    (tmp_path / "episodes.jsonl.partial").write_text(good + '{"task_index": 1, "rep')
    assert rundir.prepare({"seed": 0}) == [json.loads(good)]
    assert (tmp_path / "episodes.jsonl.partial").read_text() == good
    assert len(rundir.notes) == 1 and "episodes.jsonl.partial line 2 was cut short" in rundir.notes[0]


def test_resuming_after_a_cut_line_says_it_was_dropped(tmp_path):
    out = tmp_path / "run"
    assert run(*FAST, f"hydra.run.dir={out}").returncode == 0
    lines = (out / "episodes.jsonl").read_text().splitlines(keepends=True)
    (out / "episodes.jsonl").unlink()
    (out / "episodes.jsonl.partial").write_text(lines[0] + lines[1][: len(lines[1]) // 2])
    (out / "metrics.json").unlink()
    resumed = run(*FAST, f"hydra.run.dir={out}")
    assert resumed.returncode == 0, resumed.stderr
    notes = [line for line in resumed.stderr.splitlines() if "cut short" in line]
    assert notes == [f"note: {out / 'episodes.jsonl.partial'} line 2 was cut short (the run stopped while writing "
                     "it); dropped it, and its episode runs again"]
    assert [without_timing(json.loads(line)) for line in (out / "episodes.jsonl").read_text().splitlines()] == \
        [without_timing(json.loads(line)) for line in lines]


def test_a_corrupt_line_in_the_middle_is_reported_with_its_number(tmp_path):
    rundir = RunDir(tmp_path)
    rundir.prepare({"seed": 0})
    (tmp_path / "episodes.jsonl").write_text('{"task_index": 0, "repeat": 0}\nnot json\n{"task_index": 1}\n')
    with pytest.raises(RunDirError, match=r"episodes.jsonl line 2 is not a JSON episode record"):
        rundir.prepare({"seed": 0})


def test_two_runs_cannot_write_one_directory_at_once(tmp_path):
    with RunDir(tmp_path).lock():
        with pytest.raises(RunDirError, match="another run is writing to"):
            with RunDir(tmp_path).lock():
                pass
    assert not (tmp_path / ".run.lock").exists(), "a finished run leaves no lock file behind"
    with RunDir(tmp_path).lock():  # released
        assert (tmp_path / ".run.lock").exists()
        with pytest.raises(RunDirError, match="another run is writing to"):
            RunDir(tmp_path).check_free()
    RunDir(tmp_path).check_free()
    assert not (tmp_path / ".run.lock").exists()


def test_a_lock_taken_on_a_file_its_holder_removed_is_taken_again_on_the_new_file(tmp_path, monkeypatch):
    import fcntl

    take = RunDir._take
    calls = []

    def take_then_lose_the_race(self, fh):
        take(self, fh)
        calls.append(fh.name)
        if len(calls) == 1:  # the run that held the file removes it as it ends, just after we locked it
            (tmp_path / ".run.lock").unlink()

    monkeypatch.setattr(RunDir, "_take", take_then_lose_the_race)
    with RunDir(tmp_path).lock():
        assert len(calls) == 2, "the lock on the removed file does not count; the new file is locked"
        with open(tmp_path / ".run.lock") as fh, pytest.raises(OSError):
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    assert not (tmp_path / ".run.lock").exists()


def test_sigterm_ends_the_run_like_an_interrupt(tmp_path):
    out = tmp_path / "run"
    proc = start(*SLOW, f"hydra.run.dir={out}")
    partial = out / "episodes.jsonl.partial"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if partial.exists() and partial.read_text().count("\n") >= 1:
            break
        time.sleep(0.05)
    proc.terminate()
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 143
    assert err.strip().splitlines()[-1].startswith("terminated (SIGTERM): ")
    assert json.loads((out / "metrics.json").read_text())["complete"] is False
    assert "terminated (SIGTERM)" in (out / "run.log").read_text()


def test_interrupting_an_overwrite_run_says_to_resume_without_overwrite(tmp_path):
    out = tmp_path / "run"
    stopped = interrupt_after_first_episode([*SLOW, "overwrite=true", f"hydra.run.dir={out}"],
                                            out / "episodes.jsonl.partial")
    assert stopped.returncode == 130
    assert "rerun the same command without overwrite=true" in stopped.stderr.strip().splitlines()[-1]


def test_ctrl_c_while_starting_is_one_line(tmp_path):
    proc = start(*SLOW, f"hydra.run.dir={tmp_path / 'run'}")
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (tmp_path / "run" / ".hydra").exists():
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130, err
    assert "Traceback" not in err and len([line for line in err.splitlines() if line.startswith(("interrupted", "error"))]) == 1


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the dropped exception, as intended
def test_a_sigterm_that_a_finaliser_swallows_is_still_seen_between_episodes():
    from overhang_framework import app

    assert not issubclass(app.Terminated, Exception), "code that handles errors broadly must not take it"

    class Finalised:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)  # the handler runs here, and Python drops its exception

    before = signal.getsignal(signal.SIGTERM)
    with app._sigterm_stops_the_run() as received:
        Finalised()  # collected at once
    assert received == [signal.SIGTERM]
    assert signal.getsignal(signal.SIGTERM) is before


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the dropped exception, as intended
def test_a_ctrl_c_that_a_finaliser_swallows_is_remembered_until_a_run_acts_on_it():
    from overhang_framework import app, interrupts

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with interrupts.remember_ctrl_c():
            assert signal.getsignal(signal.SIGINT) is not signal.default_int_handler

            class Finalised:
                def __del__(self):
                    os.kill(os.getpid(), signal.SIGINT)
                    time.sleep(0.2)  # the handler runs here, and Python drops its KeyboardInterrupt

            Finalised()  # collected at once; no exception reaches this frame
            assert interrupts.ctrl_c_seen()
            with pytest.raises(KeyboardInterrupt):
                app._stop_if_asked([])
            assert not interrupts.ctrl_c_seen()  # acted on once
            app._stop_if_asked([])
            interrupts._CTRL_C.append(signal.SIGINT)
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler and not interrupts.ctrl_c_seen()
    finally:
        signal.signal(signal.SIGINT, before)


def test_remembering_ctrl_c_leaves_a_handler_of_its_own_alone():
    from overhang_framework import interrupts

    def own(signum, frame):
        pass

    before = signal.signal(signal.SIGINT, own)
    try:
        with interrupts.remember_ctrl_c():
            assert signal.getsignal(signal.SIGINT) is own
    finally:
        signal.signal(signal.SIGINT, before)


@pytest.mark.parametrize("after", [0, 1])
def test_a_dropped_ctrl_c_stops_the_run_before_its_first_episode_or_after_the_one_it_came_in(tmp_path, monkeypatch,
                                                                                             capsys, after):
    """A Ctrl-C whose exception Python dropped (the record holds it, nothing was raised) stops the run where
    it checks: before its first episode, or after the episode during which it came; the finished ones kept."""
    from overhang_framework import app, interrupts
    from overhang_framework.cli import main

    play = app.play_run_episode
    played = []

    def play_then_drop(*args, **kwargs):
        record = play(*args, **kwargs)
        played.append(record)
        if len(played) == after:
            interrupts._CTRL_C.append(signal.SIGINT)
        return record

    monkeypatch.setattr(app, "play_run_episode", play_then_drop)
    monkeypatch.setattr(interrupts, "_CTRL_C", [signal.SIGINT] if after == 0 else [])
    with pytest.raises(SystemExit) as stopped:
        main([*FAST, f"hydra.run.dir={tmp_path / 'run'}"])
    assert stopped.value.code == 130 and len(played) == after
    assert f"interrupted: {after} of 2 episodes finished" in capsys.readouterr().err
    assert not interrupts.ctrl_c_seen()

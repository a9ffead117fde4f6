"""The main job end to end: output files, summary, reproducibility, one-line errors."""

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from overhang_framework.results import read_episodes, without_timing

QUICK = ["tasks=custom", "tasks.sequences=[[1.2,0.6,1.8],[0.6,1.2,1.2]]", "progress=false"]


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "overhang_framework", *args],
                          capture_output=True, text=True, cwd=cwd)


def test_main_job_writes_episodes_and_metrics(tmp_path):
    out = tmp_path / "run"
    proc = run_cli(*QUICK, "seed=3", f"hydra.run.dir={out}")
    assert proc.returncode == 0, proc.stderr
    assert "terminal reward" in proc.stdout and "decision time (s)" in proc.stdout
    episodes = read_episodes(out / "episodes.jsonl")
    assert [e["task_id"] for e in episodes] == ["custom00", "custom01"]
    for e in episodes:
        assert e["seed"] == 3
        assert set(e) >= {"task_id", "sequence", "steps", "reward", "overhang", "stable_throughout"}
        for s in e["steps"]:
            assert set(s) >= {"x", "layer", "predicted_stability", "stable", "decision_time", "spend"}
            assert s["spend"]["predictor_calls"] >= 1
        assert e["reward"] == (e["overhang"] if e["stable_throughout"] else 0.0)
        assert len(e["steps"]) == len(e["sequence"]) - 1 or not e["stable_throughout"]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["episodes"] == 2
    assert metrics["reward_mean"] == pytest.approx(sum(e["reward"] for e in episodes) / 2)
    times = [s["decision_time"] for e in episodes for s in e["steps"]]
    assert metrics["decision_time_median"] == pytest.approx(float(np.median(times)))
    assert metrics["decision_time_max"] == pytest.approx(max(times))
    assert f"{'decision time median':<24}{metrics['decision_time_median']:>10.3f}" in proc.stdout
    assert not (out / "episodes.jsonl.partial").exists()


def test_the_summary_counts_the_decisions_over_the_time_limit(tmp_path):
    limited = run_cli(*QUICK, "condition=time_limited", "condition.time_limit=1e-9", f"hydra.run.dir={tmp_path / 'a'}")
    assert limited.returncode == 0, limited.stderr
    metrics = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert metrics["time_limit"] == 1e-9 and metrics["over_time_limit"] == metrics["placements"] > 0
    assert (f"over the time limit of 1e-09 s: {metrics['over_time_limit']} of {metrics['placements']} decisions"
            in limited.stdout)
    free = run_cli(*QUICK, "condition=unconstrained", f"hydra.run.dir={tmp_path / 'b'}")
    assert free.returncode == 0 and "time limit" not in free.stdout
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["time_limit"] is None


def test_same_seed_same_episodes(tmp_path):
    runs = []
    for name in ("a", "b"):
        proc = run_cli(*QUICK, "seed=11", f"hydra.run.dir={tmp_path / name}")
        assert proc.returncode == 0, proc.stderr
        runs.append(without_timing(read_episodes(tmp_path / name / "episodes.jsonl")))
    assert runs[0] == runs[1]


@pytest.mark.parametrize("args, expected", [
    (["predictor=nonexistent"], "unknown predictor 'nonexistent'; installed predictors: "),
    (["-m", "planner=myopic,nonexistent"], "unknown planner 'nonexistent'; installed planners: "),
    (["tasks=custom", "tasks.sequences=[[0.6,0.7]]"], "illegal block width 0.7; allowed widths are 0.6, 1.2, 1.8"),
])
def test_bad_input_exits_non_zero_with_one_line(tmp_path, args, expected):
    proc = run_cli(*args, f"hydra.run.dir={tmp_path}", "hydra.sweep.dir=" + str(tmp_path / "m"))
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert expected in lines[0]
    assert "veridical" in lines[0] or "myopic" in lines[0] or "width" in lines[0]


def test_example_plugin_runs_through_the_cli(example_plugin, tmp_path, capsys):
    from overhang_framework.cli import main

    main([*QUICK, "planner=random", "planner.min_stability=0.9", f"hydra.run.dir={tmp_path}"])
    episodes = read_episodes(tmp_path / "episodes.jsonl")
    assert len(episodes) == 2
    assert all(s["predicted_stability"] >= 0.9 for e in episodes for s in e["steps"])
    assert "terminal reward" in capsys.readouterr().out


@pytest.mark.parametrize("override, expected", [
    ("world.resolution=-1", "world 'overhang': resolution must be a positive number of metres, got -1"),
    ("world.physics=nope", "unknown physics 'nope'; allowed: pybullet, static"),
    ("+world.bogus=1", "world 'overhang' has no parameter bogus; its parameters: cache, physics,"),
    ("+world.static.bogus=1", "unknown parameter(s) bogus for physics backend 'static'; allowed: compiled, friction,"),
    ("world.pybullet.time_step=0", "PyBulletParams.time_step must be a number > 0, got 0"),
    ("world.static.friction=-1", "StaticParams.friction must be a number >= 0, got -1"),
    ("world.workers=0", "workers must be a whole number >= 1, got 0"),
    ("world.cache=maybe", "cache must be true or false, got 'maybe'"),
    ("+predictor.bogus=1", "predictor 'veridical' has no parameter bogus; its parameters: backend, backend_params"),
    ("seed=-1", "seed must be a whole number >= 0, got -1"),
    ("repeats=abc", "repeats must be a whole number >= 1, got 'abc'"),
    ("condition.time_limit=-1", "condition.time_limit must be a number of seconds > 0 or null, got -1"),
])
def test_bad_config_values_stop_before_any_episode(tmp_path, capsys, override, expected):
    from overhang_framework.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, override, f"hydra.run.dir={tmp_path}"])
    assert exit_info.value.code == 2
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "build time" not in line]
    assert err == [f"error: {err[0][7:]}"] and expected in err[0]
    assert not (tmp_path / "episodes.jsonl").exists() and not (tmp_path / "episodes.jsonl.partial").exists()


@pytest.mark.parametrize("args", [["predictor=nope", "--cfg", "job"], ["--cfg", "job", "predictor=nope"]])
def test_unknown_names_are_caught_around_hydra_flags(args, capsys):
    from overhang_framework.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    assert "unknown predictor 'nope'" in capsys.readouterr().err


def test_glob_sweeps_are_left_to_hydra():
    from overhang_framework.cli import check_overrides

    check_overrides(["predictor=glob(*)", "-m"])  # does not raise


def test_a_crashed_worker_stops_the_run_and_keeps_finished_episodes(tmp_path, capsys, monkeypatch):
    import overhang_framework.app as app
    import overhang_framework.episode as episode
    from overhang_framework.cli import main
    from overhang_framework.physics.pool import PoolCrashed

    real, calls = episode.run_episode, []

    def crash_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise PoolCrashed("a PyBullet pool worker died while checking a batch of 9 geometries")
        return real(*args, **kwargs)

    monkeypatch.setattr(episode, "run_episode", crash_on_second)
    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, f"hydra.run.dir={tmp_path}"])
    assert exit_info.value.code == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip() and "build time" not in line]
    assert len(err) == 1 and "pool worker died" in err[0] and "episodes.jsonl.partial" in err[0]
    kept = read_episodes(tmp_path / "episodes.jsonl.partial")
    assert [e["task_id"] for e in kept] == ["custom00"]
    assert not (tmp_path / "episodes.jsonl").exists()
    assert "to resume, rerun the same command" in err[0]
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert (metrics["complete"], metrics["episodes"], metrics["episodes_expected"]) == (False, 1, 2)


@pytest.mark.parametrize("args, expected", [
    (["planer=myopic"],
     "error: unknown config key 'planer' (did you mean 'planner'?); top-level keys: condition, jobs, overwrite, planner,"),
    (["+planer=myopic"],
     "error: nothing reads the added config key 'planer' (did you mean 'planner'?); top-level keys: condition,"),
    (["+tasks.bogus=1"], "error: nothing reads the added config key 'tasks.bogus'; keys of tasks 'custom': ids,"),
    (["world.resoluton=0.05"],
     "error: unknown config key 'world.resoluton' (did you mean 'world.resolution'?); keys of world 'overhang':"),
    (["planner.depth=3"], "error: unknown config key 'planner.depth'; keys of planner 'myopic': beta, choice, name"),
    (["progress=maybe"], "error: progress must be true or false, got 'maybe'"),
    (["overwrite=yes please"], "error: overwrite must be true or false, got 'yes please'"),
    (["predictor=ipe", "predictor.K=abc"], "error: predictor 'ipe': K must be a whole number >= 1, got 'abc'"),
    (["predictor=ipe", "predictor.sigma=abc"], "error: predictor 'ipe': sigma must be a number >= 0, got 'abc'"),
    (["predictor=ipe", "predictor.k=100"],
     "error: unknown config key 'predictor.k' (did you mean 'predictor.K'?); keys of predictor 'ipe': K, backend,"),
    (["predictor=ipe", "+predictor.k=100"],
     "error: predictor 'ipe' has no parameter k (did you mean K?); its parameters: K, backend,"),
    (["seed=[1"], "error: cannot read the override 'seed=[1': no viable alternative at input '[1'; overrides are"),
    (["seed=1,2"], "error: 'seed=1,2' gives several values: add -m (--multirun) to sweep over them, or write "
                   "seed=[...] for a list"),
    (["predictor=hybird", "planner=lookahaed", "planner.depth=3"],
     "error: unknown predictor 'hybird' and planner 'lookahaed'; installed predictors: cnn, hand, hybrid, ipe, veridical; "
     "installed planners: edge, lookahead, mcts, myopic, optimal"),
    (["-m", "predictor=veridical,nope", "value=nada"],
     "error: unknown predictor 'nope' and value 'nada'; installed predictors: cnn, hand, hybrid, ipe, veridical; installed values:"),
    (["-m", "seed=1,2", "world.resoluton=0.05"], "error: unknown config key 'world.resoluton'"),
    (["hydra/launcher=nope"], "error: unknown hydra/launcher 'nope'; available: basic, joblib"),
    (["planer=myopic", "predicter=ipe"], "error: unknown config key 'planer' (did you mean 'planner'?); top-level "
     "keys: condition, jobs, overwrite, planner, predictor, progress, repeats, seed, tasks, value, world | unknown "
     "config key 'predicter' (did you mean 'predictor'?)"),
    (["=3"], "error: cannot read '=3': the override names no key"),
    (["plugin"], "error: cannot read 'plugin': overrides are key=value, +key=value (add) or ~key (remove); "
                 "did you mean the command 'plugins'?"),
    (["--foo"], "error: unknown option '--foo'"),
    (["--cfg", "jb"], "error: --cfg takes one of job, hydra, all, got 'jb'"),
    (["-m", "seed=0,-1"], "error: seed must be a whole number >= 0, got -1"),
    (["-m", "world.resolution=0.1,abc"], "error: world 'overhang': resolution must be a positive number"),
    (["world.pybullet=5"], "error: world 'overhang': pybullet must be a mapping of pybullet parameters, got 5"),
    (["world.pybullet.early_stop=maybe"], "error: world 'overhang': PyBulletParams.early_stop must be true or false"),
    (["-m", "seed=0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=abc"],
     "error: bad value for 'hydra.launcher.n_jobs': Value 'abc' of type 'str' could not be converted to Integer"),
    (["-m", "seed=0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=0"],
     "error: hydra.launcher.n_jobs must be a whole number other than 0"),
    (["hydra.run.dri=x"], "error: unknown config key 'hydra.run.dri' (did you mean 'hydra.run.dir'?); keys of "
                          "hydra.run: dir"),
    (["++foo=3"], "error: nothing reads the added config key 'foo'"),
    (["predictor=ipe", "+predictor.backend_params.x=1"],
     "error: predictor 'ipe': unknown parameter(s) x for physics backend 'static'; allowed: "),
    (["predictor=ipe", "predictor.sigma=-1"], "error: predictor 'ipe': sigma must be a number >= 0, got -1"),
    (["tasks.ids=a"], "error: tasks.ids must be a list of ids, one per sequence, got 'a'"),
    (["tasks.sequences=[[0.6,1.2,abc]]"], "error: task custom00: width 'abc' is not a number; allowed widths"),
    (["tasks=paper20", "tasks.sequences=[[0.6,1.8,1.2]]"],
     "error: tasks.sequences of paper20 were changed; for your own sequences use tasks=custom"),
    (["hydra.run.dir="], "error: hydra.run.dir is empty; give the directory the results go to"),
    (["~world"], "error: the run needs a world; choose one with world=NAME (installed: overhang)"),
])
def test_command_line_mistakes_end_with_one_line_and_status_2(tmp_path, capsys, args, expected):
    from overhang_framework.cli import main

    run_dir = [] if any(a.startswith("hydra.run.dir") for a in args) else [f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, *run_dir, f"hydra.sweep.dir={tmp_path / 'm'}", *args])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(expected), err
    assert not (tmp_path / "run").exists() and not (tmp_path / "m").exists(), "nothing is written"


@pytest.mark.parametrize("directory", ["/proc/overhang-run", "/dev/null/run"])
def test_an_unwritable_run_directory_is_one_line_as_typed(directory):
    proc = run_cli(*QUICK, f"hydra.run.dir={directory}")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines() == [
        f"error: cannot write the output directory '{directory}' "
        f"({'/dev/null is not a directory' if directory.startswith('/dev/null') else 'No such file or directory'}); "
        "choose another with hydra.run.dir=DIR (hydra.sweep.dir=DIR with -m)"]


def test_a_typo_is_one_line_as_typed_from_the_repository_root():
    from pathlib import Path

    proc = run_cli("planer=myopic", cwd=Path(__file__).resolve().parents[1])
    assert proc.returncode == 2 and proc.stdout == ""
    assert proc.stderr.startswith("error: unknown config key 'planer' (did you mean 'planner'?)")
    assert proc.stderr.count("\n") == 1


TOP_FIT = "cache, cv, depths, jobs, logs, models, motor, out, pooled, progress, shard, shards, states, truth, value, world"


MISSPELT = [
    ("fit", ["LOG", "--out", "OUT", "modles.ipe.K=10"],
     f"error: unknown config key 'modles' (did you mean 'models'?); top-level keys: {TOP_FIT}"),
    ("fit", ["LOG", "--out", "OUT", "+modles.ipe.K=10"],
     f"error: unknown config key 'modles' (did you mean 'models'?); top-level keys: {TOP_FIT}"),
    ("fit", ["LOG", "--out", "OUT", "models.ipe.KK=10"],
     "error: unknown config key 'models.ipe.KK' (did you mean 'models.ipe.K'?); keys of models.ipe: K, predictor, "
     "sigma"),
    ("experiment", ["prot=8001"], "error: unknown config key 'prot' (did you mean 'port'?); top-level keys: "),
    ("experiment", ["export", "--out", "OUT", "databse=sqlite:///x.sqlite"],
     "error: unknown config key 'databse' (did you mean 'database'?); top-level keys: "),
    ("experiment", ["expot", "--out", "OUT"], "error: cannot read 'expot': overrides are key=value, +key=value (add) "
                                              "or ~key (remove); did you mean the command 'export'?"),
    ("participants", ["cohort.parameters.bta=1"], "error: unknown config key 'cohort.parameters.bta' (did you mean "
                                                  "'cohort.parameters.beta'?); keys of cohort.parameters: "),
    ("fit.recovery", ["--out", "OUT", "participnts=2"],
     "error: unknown config key 'participnts' (did you mean 'participants'?); top-level keys: "),
    ("check", ["TOWERS", "world.physcs=static"],
     "error: unknown config key 'world.physcs' (did you mean 'world.physics'?); keys of world 'overhang': "),
    ("order_dependency", ["TOWERS", "wrld.physics=static"],
     "error: unknown config key 'wrld' (did you mean 'world'?); top-level keys: "),
    ("bench.fit", ["--world", "wrld.physics=static"],
     "error: --world: unknown config key 'wrld' (did you mean 'world'?); top-level keys: "),
]


@pytest.fixture(scope="module")
def misspelt(tmp_path_factory):
    """Each case of MISSPELT run once, two at a time, each in a directory of its own."""
    from commands import run_each

    base = tmp_path_factory.mktemp("misspelt")
    towers = base / "towers.jsonl"
    towers.write_text('{"blocks": [[1.2, 0.0, 0]]}\n')
    argvs, outs = [], []
    for k, (command, args, _) in enumerate(MISSPELT):
        where = base / str(k)
        paths = {"LOG": str(where / "log.jsonl"), "OUT": str(where / "out"), "TOWERS": str(towers)}
        argvs.append([sys.executable, "-m", f"overhang_framework.{command}", *[paths.get(a, a) for a in args]])
        outs.append(where / "out")
    procs = run_each(argvs, env={**os.environ, "OVERHANG_ADMIN_TOKEN": "a-long-admin-token"})
    return list(zip(procs, outs))


@pytest.mark.parametrize("case", range(len(MISSPELT)), ids=[f"{c}-{k}" for k, (c, _, _) in enumerate(MISSPELT)])
def test_every_command_names_a_misspelt_key_in_one_line_with_the_closest_one(misspelt, case):
    """The commands that take overrides answer a misspelt key as the main command does: one line, with
    "did you mean", never Hydra's own message (which advises appending the misspelt key with +)."""
    expected = MISSPELT[case][2]
    proc, out = misspelt[case]
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.startswith(expected) and proc.stderr.count("\n") == 1, proc.stderr
    assert "To append" not in proc.stderr and "Could not override" not in proc.stderr
    assert not out.exists()


def test_help_is_the_projects_own_page(capsys):
    from overhang_framework.cli import main
    from overhang_framework.config import group_options

    main(["--help"])
    page = capsys.readouterr().out
    assert "powered by Hydra" not in page
    for group in ("world", "predictor", "planner", "value", "condition", "tasks"):
        line = next(line for line in page.splitlines() if line.strip().startswith(group + " "))
        assert all(name in line for name in group_options(group))
    for needed in ("plugins", "overhang-framework", "episodes.jsonl", "metrics.json", "run.log", "-m ",
                   "hydra.run.dir", "--hydra-help"):
        assert needed in page


def test_progress_moves_per_placement_on_a_terminal(tmp_path):
    import fcntl
    import os
    import pty
    import struct
    import termios

    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # a terminal 120 wide
    try:
        proc = subprocess.run([sys.executable, "-m", "overhang_framework", "tasks=custom",
                               "tasks.sequences=[[1.2,0.6,1.8,0.6]]", "progress=true", f"hydra.run.dir={tmp_path}"],
                              stdout=subprocess.PIPE, stderr=follower, text=True)
        os.close(follower)
        chunks = []
        while True:
            try:
                chunk = os.read(leader, 65536)
            except OSError:
                break
            if not chunk:
                break
            chunks.append(chunk)
    finally:
        os.close(leader)
    assert proc.returncode == 0
    frames = b"".join(chunks).decode(errors="replace")
    assert "\r" in frames
    frames = frames.replace("\r", "\n")
    assert "placements:" in frames and "1/3 [" in frames and "3/3 [" in frames
    assert "build time" not in frames + proc.stdout


@pytest.mark.slow
def test_progress_off_a_terminal_writes_whole_lines_now_and_then(tmp_path):
    import os

    args = ("tasks=custom", "tasks.sequences=[[1.2,0.6,1.8,0.6],[0.6,1.2,0.6]]", "progress=true")
    proc = run_cli(*args, f"hydra.run.dir={tmp_path / 'a'}")
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("placements:")]
    assert len(lines) == 1 and "5/5 [" in lines[0]  # a short run: only the closing line
    env = {**os.environ, "OVERHANG_PROGRESS_SECONDS": "0.000001"}
    proc = subprocess.run([sys.executable, "-m", "overhang_framework", *args, f"hydra.run.dir={tmp_path / 'b'}"],
                          capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    assert "\r" not in proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.startswith("placements:")]
    assert any("1/5 [" in line for line in lines) and "5/5 [" in lines[-1]
    env["OVERHANG_PROGRESS_SECONDS"] = "0"
    proc = subprocess.run([sys.executable, "-m", "overhang_framework", *args, f"hydra.run.dir={tmp_path / 'c'}"],
                          capture_output=True, text=True, env=env)
    assert proc.returncode == 0 and "placements" not in proc.stderr


def test_results_hold_readable_numbers_and_the_log_is_written(tmp_path):
    import re

    proc = run_cli("tasks=example", "world.physics=static", "progress=false", f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    for name in ("episodes.jsonl", "metrics.json", "run.json"):
        text = (tmp_path / name).read_text()
        assert not re.search(r"\d\.\d*(0000000000|9999999999)\d", text), name
    episodes = read_episodes(tmp_path / "episodes.jsonl")
    assert all(round(s["overhang"], 9) == s["overhang"] for e in episodes for s in e["steps"])
    log = (tmp_path / "run.log").read_text()
    assert "episode example00 repeat 0: reward" in log and "finished: reward" in log


def test_the_summary_names_the_tasks_picked(tmp_path):
    proc = run_cli("tasks.only=[paper00,paper07]", "world.physics=static", "progress=false",
                   f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    assert "tasks=paper20[paper00,paper07]" in proc.stdout.splitlines()[0]
    assert json.loads((tmp_path / "metrics.json").read_text())["config"]["tasks"] == "paper20[paper00,paper07]"


def test_run_outputs_are_ignored_by_git():
    from pathlib import Path

    ignored = (Path(__file__).resolve().parents[1] / ".gitignore").read_text().split()
    assert {"runs/", "outputs/", "multirun/"} <= set(ignored)


def test_flags_may_follow_the_overrides(tmp_path):
    proc = run_cli(*QUICK, "world.physics=static", "seed=0,1", "-m", f"hydra.sweep.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.isdigit()) == ["0", "1"]


def test_version_names_the_project(capsys):
    from overhang_framework.cli import main

    main(["--version"])
    assert capsys.readouterr().out.startswith("overhang-framework ")


def test_plugins_refuses_unknown_options(capsys):
    from overhang_framework.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["plugins", "--jsn"])
    assert exit_info.value.code == 2
    assert capsys.readouterr().err.strip() == "error: plugins takes only --json, got --jsn"


def test_a_single_episode_has_no_sem_and_metrics_are_strict_json(tmp_path):
    proc = run_cli("tasks=example", "world.physics=static", "progress=false", f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    metrics = json.loads((tmp_path / "metrics.json").read_text(),
                         parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert metrics["reward_sem"] is None and metrics["reward_mean"] > 0
    assert "1 episode, 5 placements" in proc.stdout
    assert next(line for line in proc.stdout.splitlines() if line.startswith("terminal reward")).split()[-1] == "-"


def test_a_model_failing_mid_run_is_one_line_and_keeps_finished_episodes(tmp_path, capsys, monkeypatch):
    import overhang_framework.app as app
    import overhang_framework.episode as episode
    from overhang_framework.cli import main

    real, calls = episode.run_episode, []

    def fail_on_second(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            raise ZeroDivisionError("a planner bug")
        return real(*args, **kwargs)

    monkeypatch.setattr(episode, "run_episode", fail_on_second)
    with pytest.raises(SystemExit) as exit_info:
        main([*QUICK, "world.physics=static", f"hydra.run.dir={tmp_path}"])
    assert exit_info.value.code == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ZeroDivisionError: a planner bug (traceback in ")
    assert "Traceback" in (tmp_path / "run.log").read_text()
    assert len(read_episodes(tmp_path / "episodes.jsonl.partial")) == 1


@pytest.mark.parametrize("launch", ["run", "basic sweep", "joblib sweep"])
def test_each_job_builds_its_models_once(tmp_path, monkeypatch, launch):
    import overhang_framework.app as app
    import overhang_framework.plugins as plugins
    from overhang_framework.cli import main

    real, built = plugins.build_models, []

    def counting(cfg, *args, **kwargs):
        built.append(cfg.seed)
        return real(cfg, *args, **kwargs)

    monkeypatch.setattr(plugins, "build_models", counting)
    if launch == "run":
        main([*QUICK, "world.physics=static", f"hydra.run.dir={tmp_path}"])
        assert len(built) == 1  # the check's models run
        assert (tmp_path / "metrics.json").exists()
    else:
        joblib = ["hydra/launcher=joblib", "hydra.launcher.n_jobs=2"] if launch == "joblib sweep" else []
        main(["-m", *QUICK, "world.physics=static", "seed=1,2", *joblib, f"hydra.sweep.dir={tmp_path}"])
        # the basic launcher's jobs run here and take the check's models; joblib's workers build their own
        assert sorted(built) == [1, 2]
        assert all((tmp_path / job / "metrics.json").exists() for job in ("0", "1"))
    assert not any(app._kept_models.values())  # nothing is left holding models


@pytest.mark.parametrize("overrides, said", [
    (["planner=lookahead", "planner.depth=9"],
     "planner.depth=9 is more than the 5 placements of the longest task: each decision searches to the end of "
     "its episode, which is what planner.depth=5 does"),
    (["planner=optimal", "planner.stored=false", "tasks=custom", "tasks.sequences=[[1.2,0.6,1.8,0.6,1.2,1.8]]"],
     "planner=optimal proves each decision by exhaustive search over every remaining placement: with "
     "predictor=veridical and world.physics=tiered, one paper20 task's optimum took from 1.5 to 21 min"),
    (["planner=optimal", "tasks=custom", "tasks.sequences=[[1.2,0.6,1.8]]", "world.physics=static"],
     "one task's optimum took from 13 s to 16 min to prove"),
    (["planner=mcts", "planner.iterations=400"], "planner=mcts planner.iterations=400"),
])
def test_settings_known_to_be_slow_or_to_mean_less_are_said_before_the_run(overrides, said):
    from overhang_framework.advice import run_notes
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    cfg = compose_config(overrides)
    notes = run_notes(cfg, tasks_from_config(cfg.tasks), build_models(cfg))
    assert len(notes) == 1 and said in notes[0]


@pytest.mark.parametrize("overrides", [
    ["planner=lookahead", "planner.depth=5"], ["planner=optimal", "world.physics=static"], ["planner=mcts"],
    ["predictor=hybrid", "planner=lookahead", "planner.depth=3"]])
def test_ordinary_settings_get_no_note(overrides):
    from overhang_framework.advice import run_notes
    from overhang_framework.plugins import build_models
    from overhang_framework.config import compose_config
    from overhang_framework.tasks import tasks_from_config

    cfg = compose_config([*overrides, "world.physics=static"] if "world.physics=static" not in overrides else overrides)
    assert run_notes(cfg, tasks_from_config(cfg.tasks), build_models(cfg)) == []


def test_a_note_is_said_once_on_stderr_and_the_run_goes_on(tmp_path):
    proc = run_cli("tasks=custom", "tasks.sequences=[[1.2,0.6,1.8]]", "planner=lookahead", "planner.depth=4",
                   "world.physics=static", "progress=false", f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.count("note: planner.depth=4 is more than the 2 placements of the longest task") == 1
    assert "note: planner.depth=4" in (tmp_path / "run.log").read_text()

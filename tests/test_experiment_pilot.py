"""The pilot through the server: simulated participants as real HTTP clients of a real server process.

The quick test runs the command a lab types (the pilot starts its own server, a uvicorn process on a
free loopback port), exports what the server stored with the ``export`` command, and compares it with
the offline simulation of the same participants with the same seed in the server's orders. The
timeout test starts a server itself and points the pilot at it with ``--url``. The PostgreSQL variant
runs when ``OVERHANG_TEST_POSTGRES_URL`` names a server (skipped without, failed under CI); the
recovery test (fits of the exported and the offline logs) is marked slow.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from overhang_framework.experiment.__main__ import sidecar_of
from overhang_framework.experiment.pilot import SAME, offline_twin, placements_alike

pytest.importorskip("httpx")
pytest.importorskip("uvicorn")

ROOT = Path(__file__).resolve().parents[1]
PG_ENV = "OVERHANG_TEST_POSTGRES_URL"
#: Two participants (one a condition), two tasks each.
COHORT = ["cohort=small", "cohort.n_tasks=2", "cohort.participants.time_limited=1",
          "cohort.participants.unconstrained=1", "seed=3"]


def run(*args, check=True, timeout=600):
    done = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    if check:
        assert done.returncode == 0, done.stderr[-3000:]
    return done


def pilot(out, *args, check=True):
    return run("-m", "overhang_framework.experiment", "pilot", "--out", str(out), "--no-progress", *args, check=check)


def export(out, *args):
    log = out / "log.jsonl"
    run("-m", "overhang_framework.experiment", "export", f"run_dir={out}", *args, "--out", str(log))
    return [json.loads(line) for line in log.read_text().splitlines()]


def truth(out):
    with open(out / "participants.csv") as f:
        return {r["id"]: r for r in csv.DictReader(f)}


def same(records):
    return sorted(({k: r[k] for k in SAME} for r in records), key=lambda r: (r["participant"], r["trial"], r["step"]))


# the same pilot on PostgreSQL (below) checks the equality in the default suite
@pytest.mark.slow
def test_a_pilot_through_the_server_stores_what_the_offline_simulation_places(tmp_path):
    out = tmp_path / "pilot"
    done = pilot(out, "--time-scale", "0.05", "--serve", "workers=1", "--serve", "physics_processes=0", *COHORT)
    assert "2 participants (2 finished, 0 screened out" in done.stdout, done.stdout
    summary = json.loads((out / "pilot.json").read_text())
    assert set(summary["conditions"]) == {"time_limited", "unconstrained"}
    # the export the pilot's last line suggests, run as written, writes its participants' placements
    import shlex

    suggested = shlex.split(done.stdout.strip().splitlines()[-1].split("the log: ", 1)[1])
    assert suggested[:2] == ["python", "-m"] and "--include-simulated" in suggested
    run(*suggested[1:])
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    table = truth(out)
    assert set(table) == {"pilot-001", "pilot-002"} == {r["participant"] for r in records}
    assert {r["condition"] for r in table.values()} == {"time_limited", "unconstrained"}
    # the same participants, tasks, placements and outcomes as offline; the server rounds overhangs to 1e-9
    twin = offline_twin(COHORT, records, table)
    assert same(records) == same(twin)
    assert placements_alike(records, twin) == (len(records), len(records))
    assert len({(r["participant"], r["task_id"]) for r in records}) == 4
    key = lambda r: (r["participant"], r["trial"], r["step"])  # noqa: E731
    for a, b in zip(sorted(records, key=key), sorted(twin, key=key)):
        assert (a["reward"] is None) == (b["reward"] is None)
        if a["reward"] is not None:
            assert a["reward"] == pytest.approx(b["reward"], abs=2e-9)
    # the client waited its scaled decision time before posting, and the server's clock measured it
    decisions = [json.loads(line) for line in (out / "decisions.jsonl").read_text().splitlines()]
    assert any(d["phase"] == "practice" for d in decisions)
    mains = [d for d in decisions if d["phase"] == "main"]
    assert len(mains) == len(records)
    for d in decisions:
        if not d["claimed_timeout"]:
            assert d["waited"] == pytest.approx(0.05 * d["simulated_time"], abs=1e-3)
            assert d["server_time"] >= d["waited"] - 0.01, d
            # the simulator's planning is not the participant's: the server's clock leaves it out (latency aside)
            assert d["server_time"] <= d["waited"] + 0.5, d
    by_step = {(d["participant"], d["trial"], d["step"]): d for d in mains}
    for r in records:
        assert r["server_time"] == by_step[(r["participant"], r["trial"], r["step"])]["server_time"]


def _serve(tmp_path, overrides, database=None):
    """A server process of the experiment's app, as the ``serve`` command's workers run it."""
    from overhang_framework.experiment.__main__ import SETTINGS_ENV
    from overhang_framework.experiment.pilot import free_port
    from overhang_framework.experiment.settings import ADMIN_ENV, load_settings
    from overhang_framework.experiment.store import Store

    port = free_port()
    tmp_path.mkdir(parents=True, exist_ok=True)
    words = [f"run_dir={tmp_path}", f"port={port}", "workers=1", "physics_processes=0",
             *([f"database={database}"] if database else []), *overrides]
    Store(load_settings(words, need_admin_token=False).database).close()
    env = {**os.environ, SETTINGS_ENV: json.dumps(words), ADMIN_ENV: "pilot-test-admin"}
    process = subprocess.Popen([sys.executable, "-m", "uvicorn", "overhang_framework.experiment.__main__:app_factory",
                                "--factory", "--port", str(port), "--log-level", "warning"], cwd=ROOT, env=env)
    return process, f"http://127.0.0.1:{port}", words


def _wait(url, process):
    import time

    import httpx

    for _ in range(600):
        assert process.poll() is None, "the server stopped"
        try:
            httpx.get(url + "/api/session", timeout=2)
            return
        except httpx.HTTPError:
            time.sleep(0.2)
    pytest.fail("the server did not answer")


def test_a_too_slow_participant_times_out_on_the_servers_clock(tmp_path, monkeypatch):
    # one time-limited participant whose every decision takes 60 s (1.2 s at a time scale of 0.02), against a
    # server with a 0.1 s limit (and its 0.5 s grace); the client posts its placements, never a timeout
    process, url, words = _serve(tmp_path / "server", ["conditions=[time_limited]", "time_limit=0.1",
                                                       "practice.max_attempts=2", "tasks.only=[paper00]"])
    try:
        _wait(url, process)
        out = tmp_path / "pilot"
        monkeypatch.setenv("OVERHANG_ADMIN_TOKEN", "pilot-test-admin")  # the study's: its sessions are simulated
        done = pilot(out, "--url", url, "--time-scale", "0.02", "--timeouts", "server", "cohort=small",
                     "cohort.participants.time_limited=1", "cohort.participants.unconstrained=0",
                     "cohort.decision_time.t0=60", "cohort.decision_time.per_call=0", "cohort.decision_time.noise=0")
        # a second pilot of the same live study, with the same ids, is told to give its own
        again = pilot(tmp_path / "pilot2", "--url", url, "--time-scale", "0.02", "cohort=small",
                      "cohort.participants.time_limited=1", "cohort.participants.unconstrained=0", check=False)
        assert again.returncode == 1, again.stderr
        assert ("pilot-001 is in this study already (an earlier pilot's participant): give this pilot ids of its "
                "own with --prefix (e.g. --prefix pilot2)") in again.stderr, again.stderr
        # a cohort whose conditions are not the study's is refused before any session is opened
        other = pilot(tmp_path / "pilot3", "--url", url, "--prefix", "other", "cohort=small",
                      "cohort.participants.time_limited=1", "cohort.participants.unconstrained=1", check=False)
        assert other.returncode == 1 and ("the study serves the conditions time_limited, and the cohort has "
                                          "participants in time_limited, unconstrained") in other.stderr, other.stderr
        import httpx

        held = httpx.get(url + "/api/admin/participants", headers={"X-Admin-Token": "pilot-test-admin"}).json()
        assert [p["participant"] for p in held] == ["pilot-001"]
    finally:
        process.terminate()
        process.wait(timeout=30)
    # a server stopped as a service is stopped leaves what it stored in the database file, not in its -wal
    wal = tmp_path / "server" / "experiment.sqlite-wal"
    assert not wal.exists() or wal.stat().st_size == 0
    assert "1 screened out in the practice" in done.stdout, done.stdout
    assert json.loads((out / "pilot.json").read_text())["screened_out"] == 1
    decisions = [json.loads(line) for line in (out / "decisions.jsonl").read_text().splitlines()]
    assert len(decisions) == 2 and not any(d["claimed_timeout"] for d in decisions)
    assert all(d["x"] is not None for d in decisions)
    log = tmp_path / "log.jsonl"
    where = [w for w in words if w.split("=")[0] in ("run_dir",)]
    # the server's study is a study of people: the pilot's participants are stored as simulated and left out
    left = run("-m", "overhang_framework.experiment", "export", *where, "--out", str(log), "--include-screened-out")
    assert log.read_text() == ""
    assert "1 simulated participant (a pilot's) left out: add --include-simulated to export them" in left.stderr
    assert json.loads(sidecar_of(log).read_text())["participants"]["simulated"] == 1
    run("-m", "overhang_framework.experiment", "export", *where, "--out", str(log), "--include-screened-out",
        "--include-simulated")
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(records) == 2 and {r["source"] for r in records} == {"simulated"}
    for r, d in zip(records, decisions):
        assert r["timed_out"] is True and r["x"] is None and r["reward"] == 0.0
        assert r["late_action"] == [d["x"], d["layer"]]  # what the client placed, stored as late
        assert r["server_time"] >= 1.2 > 0.1 + 0.5
    assert truth(out)["pilot-001"]["screened_out"] == "True"


def test_bad_pilot_options_stop_with_one_line_and_write_nothing(tmp_path, capsys, monkeypatch):
    from overhang_framework.experiment.__main__ import main

    out = tmp_path / "pilot"
    monkeypatch.delenv("OVERHANG_ADMIN_TOKEN", raising=False)
    for words, message in (
            (["--time-scale", "0", "cohort=small"], "--time-scale must be a number > 0"),
            (["cohort=small", "cohort.participants.time_limited=3"], "as many participants in each condition"),
            (["cohort=smal"], "cohort"),
            (["--url", "http://127.0.0.1:1", "--serve", "workers=1", "cohort=small"], "leave it out with --url"),
            (["--url", "http://127.0.0.1:1", "cohort=small"],
             "a pilot of a running study needs its admin token in the environment variable OVERHANG_ADMIN_TOKEN")):
        assert main(["pilot", "--out", str(out), *words]) == 2
        err = capsys.readouterr().err
        assert err.startswith("error: ") and err.strip().count("\n") == 0 and message in err, err
    assert not out.exists()


def test_a_pilot_on_postgresql(tmp_path):
    url = os.environ.get(PG_ENV)
    if not url:
        if os.environ.get("CI"):
            pytest.fail(f"{PG_ENV} is not set: .ci/run starts a PostgreSQL server and sets it")
        pytest.skip(f"no PostgreSQL server ({PG_ENV} not set)")
    from sqlalchemy import create_engine

    from overhang_framework.experiment.store import Base

    engine = create_engine(url)
    Base.metadata.drop_all(engine)
    engine.dispose()
    overrides = ["cohort=small", "cohort.n_tasks=1", "cohort.participants.time_limited=0",
                 "cohort.participants.unconstrained=1"]
    out = tmp_path / "pilot"
    pilot(out, "--time-scale", "0.02", "--serve", "workers=1", "--serve", "physics_processes=0",
          "--serve", f"database={url}", *overrides)
    records = export(out, f"database={url}")
    assert records and {r["participant"] for r in records} == {"pilot-001"}
    assert {r["source"] for r in records} == {"simulated"}  # a pilot's own server says who took part
    assert same(records) == same(offline_twin(overrides, records, truth(out)))
    # the same stored study as a Psych-DS dataset: valid, and read back as the JSON Lines export
    from overhang_framework.behaviour.log import read_log
    from overhang_framework.behaviour.psychds import check_dataset

    dataset = out / "dataset"
    run("-m", "overhang_framework.experiment", "export", "--format", "psych-ds", f"run_dir={out}",
        f"database={url}", "--out", str(dataset))
    assert check_dataset(dataset) == []
    pd.testing.assert_frame_equal(read_log(dataset), read_log(out / "log.jsonl"))
    sidecar = json.loads((dataset / "study.json").read_text())
    assert sidecar == json.loads((out / "log.study.json").read_text())
    assert {r["settings_hash"] for r in records} == {sidecar["study"]["settings_hash"]}


@pytest.mark.slow
def test_the_fit_of_the_exported_log_recovers_depths_as_the_offline_logs_fit_does(tmp_path):
    # four participants (depth 1 or 2, as cohort=small plants them), three tasks, a quick time scale; the
    # IPE at depths 1 and 2 fitted to the export and to the offline log of the same cohort and seed
    from overhang_framework.bench.pilot_recovery import main

    out = tmp_path / "recovery"
    assert main(["--out", str(out), "--time-scale", "0.05", "--serve", "workers=1", "--serve", "physics_processes=0",
                 "--fit", "~models.cnn", "--fit", "~models.hybrid", "--fit", "models.ipe.K=20",
                 "--fit", "models.ipe.sigma=[0.03]", "cohort=small", "cohort.n_tasks=3",
                 "cohort.participants.time_limited=2", "cohort.participants.unconstrained=2", "seed=1"]) == 0
    result = json.loads((out / "recovery.json").read_text())
    assert result["alike"]["equal_offline_in_server_order"] == result["alike"]["placements"] > 0
    exported, offline = result["exported"], result["offline"]
    assert exported["participants"] == offline["participants"] == 4
    planted = {k: sum(v.values()) for k, v in exported["confusion"].items()}
    assert planted == {k: sum(v.values()) for k, v in offline["confusion"].items()}  # the same participants
    assert exported["recovered"] >= offline["recovered"] - 1
    assert exported["recovered"] >= 2


def test_a_pilot_stopped_midway_leaves_its_files_and_says_what_it_left_on_the_server(tmp_path):
    import signal
    import time

    from overhang_framework.experiment.store import Store

    out = tmp_path / "pilot"
    # a faithful time scale: each decision waits seconds, so the pilot is surely midway when it is stopped
    proc = subprocess.Popen([sys.executable, "-m", "overhang_framework.experiment", "pilot", "--out", str(out),
                             "--no-progress", *COHORT], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    database = out / "experiment.sqlite"
    deadline = time.time() + 180
    started = 0
    while time.time() < deadline and started < 2:
        time.sleep(0.5)
        if database.exists():
            store = None
            try:  # the server may be creating the tables at this moment, and so may this store
                store = Store(f"sqlite:///{database}")
                started = sum(p.consented_at is not None for p in store.participants())
            except Exception:  # noqa: BLE001 - the tables may not be there yet
                started = 0
            finally:
                if store is not None:
                    store.close()
    assert started == 2, "the pilot's participants did not start"
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    line = err.strip().splitlines()[-1]
    assert line.startswith("interrupted: 2 session(s) were opened; its own server's database keeps what their "
                           "participants placed, 2 participant(s) unfinished (pilot-001, pilot-002), stored as "
                           "simulated"), line
    rows = truth(out)
    assert set(rows) == {"pilot-001", "pilot-002"}
    summary = json.loads((out / "pilot.json").read_text())
    assert summary["stopped"] == "interrupted" and summary["unfinished"] == ["pilot-001", "pilot-002"]
    store = Store(f"sqlite:///{database}")
    try:
        assert {p.id: p.source for p in store.participants()} == {"pilot-001": "simulated", "pilot-002": "simulated"}
    finally:
        store.close()


@pytest.mark.slow
def test_a_graded_pilot_at_the_default_concurrency_against_a_served_study_is_exported_and_analysed(tmp_path,
                                                                                                   monkeypatch):
    """The graded study served as a lab serves it (``study=graded_budgets``), a pilot of two participants a level
    through it at the pilot's default concurrency (8: every participant at once, each building its hybrid predictor's
    CNN at the same moment), the export the pilot suggests, and ``study graded_budgets --log`` on it: the full
    report, opening with what its size cannot support."""
    tasks = "tasks.only=[paper00,paper03]"
    process, url, words = _serve(tmp_path / "server", ["study=graded_budgets", tasks])
    try:
        _wait(url, process)
        out = tmp_path / "pilot"
        monkeypatch.setenv("OVERHANG_ADMIN_TOKEN", "pilot-test-admin")
        done = pilot(out, "--url", url, "--time-scale", "0.02", "cohort=graded_budgets", tasks, "seed=7",
                     "cohort.participants={limit_2_5s: 2, time_limited: 2, limit_10s: 2, unconstrained: 2}")
        assert "8 participants (" in done.stdout and "Traceback" not in done.stderr, done.stdout + done.stderr[-2000:]
        import shlex

        suggested = shlex.split(done.stdout.strip().splitlines()[-1].split("the log: ", 1)[1])
        run(*suggested[1:])  # the export the pilot suggests, from the live study
    finally:
        process.terminate()
        process.wait(timeout=30)
    table = truth(out)
    finished = [r for r in table.values() if r["screened_out"] == "False"]
    assert len(table) == 8 and finished, table
    records = [json.loads(line) for line in (out / "log.jsonl").read_text().splitlines()]
    assert {r["participant"] for r in records} == {r["id"] for r in finished}  # the screened-out are left out
    analysis = run("-m", "overhang_framework.study", "graded_budgets", "--log", str(out / "log.jsonl"),
                   "--out", str(tmp_path / "analysis"), "--no-fit", "--resamples", "20", "--no-progress",
                   timeout=1200)
    lines = analysis.stdout.splitlines()
    assert lines[0] == "# The graded-budget study: what people did"
    assert lines[2].startswith("**Nothing can be concluded from this study:** it has "), lines[:4]
    report = (tmp_path / "analysis" / "study.md").read_text()
    assert "## Each level" in report and "simulated" not in report.split("## Steps")[0]
    trends = pd.read_csv(tmp_path / "analysis" / "trends.csv")
    assert {"overhang", "gamma", "lateral"} <= set(trends["measure"])

"""The experiment's settings and command: one-line errors before the server listens, practice optima that the
reference physics confirms, and the export command."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from overhang_framework.errors import ConfigError
from overhang_framework.experiment.settings import ADMIN_ENV, load_settings
from overhang_framework.geometry import Action
from overhang_framework.plugins import Registry


@pytest.fixture(autouse=True)
def no_admin_env(monkeypatch):
    monkeypatch.delenv(ADMIN_ENV, raising=False)


@pytest.mark.parametrize("overrides, words", [
    ([], "no admin token"),
    (["admin_token=short"], "at least 16 characters, got 5"),
    (["admin_token=fifteen-chars-x"], "at least 16 characters, got 15"),
    (["admin_token=long-enough-token", "database=experiment.sqlite"], "SQLAlchemy URL"),
    (["admin_token=long-enough-token", "conditions=[time_limited,fast]"], "conditions must be"),
    (["admin_token=long-enough-token", "practice.threshold=2"], "practice.threshold"),
    (["admin_token=long-enough-token", "time_limit=0"], "time_limit"),
    (["admin_token=long-enough-token", "port=-1"], "port"),
    (["admin_token=long-enough-token", "workers=0"], "workers must be"),
    (["admin_token=long-enough-token", "physics_processes=-1"], "physics_processes must be"),
    (["admin_token=long-enough-token", "practice.ids=[paper00,practice2,practice3]"], "also main tasks"),
    (["admin_token=long-enough-token", "world.physics=static"], "python -m overhang_framework.optimum"),
    (["admin_token=long-enough-token", "predictor=ipe"], "predictor"),
])
def test_bad_settings_fail_in_one_line(tmp_path, overrides, words):
    with pytest.raises(ConfigError) as err:
        load_settings([f"run_dir={tmp_path}", *overrides])
    assert words in str(err.value) and "\n" not in str(err.value)


def test_the_admin_token_can_come_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv(ADMIN_ENV, "from-the-environment")
    assert load_settings([f"run_dir={tmp_path}"]).admin_token == "from-the-environment"


def test_practice_optima_stand_step_by_step_under_the_reference(tmp_path):
    settings = load_settings([f"run_dir={tmp_path}", "admin_token=long-enough-token"])
    reference = Registry().create("world", {**settings.world, "physics": "pybullet"})
    assert len(settings.practice) == 3
    for practice in settings.practice:
        state = reference.initial_state(practice.task)
        for width, x, layer in practice.optimal_tower[1:]:
            assert reference.illegal_reason(state, Action(x, layer)) is None
            state = reference.successor(state, Action(x, layer))
            assert reference.is_stable(state.geometry), (practice.task.id, state.geometry)
        assert reference.overhang(state.geometry) == pytest.approx(practice.optimum)


def test_the_command_refuses_bad_settings_in_one_line(tmp_path):
    done = subprocess.run([sys.executable, "-m", "overhang_framework.experiment", f"run_dir={tmp_path}"],
                          capture_output=True, text=True, env={"PATH": "/usr/bin:/bin"}, timeout=120)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"error: no admin token: set admin_token=... or the environment "
                                                f"variable {ADMIN_ENV}"]


def _played(tmp_path):
    """A study in ``tmp_path`` where P9 passed the practice and finished one main trial; (overrides, client, session)."""
    from fastapi.testclient import TestClient

    from overhang_framework.experiment.api import create_app

    overrides = [f"run_dir={tmp_path}", "tasks.only=[paper03]"]
    settings = load_settings([*overrides, "admin_token=long-enough-token"])
    client = TestClient(create_app(settings))
    s = client.post("/api/sessions", json={"params": {"participant": "P9"}}).json()
    h = {"Authorization": f"Bearer {s['token']}"}
    client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h)

    def place(phase, trial, step, x, layer):
        body = {"phase": phase, "trial": trial, "step": step}
        client.post("/api/steps/start", json=body, headers=h)
        reply = client.post("/api/placements", json={**body, "x": x, "layer": layer, "decision_time": 1.5}, headers=h)
        assert reply.status_code == 200, reply.text

    for k, pt in enumerate(settings.practice, 1):
        for step, (_, x, layer) in enumerate(pt.shown_tower[1:], 1):
            place("practice", k, step, x, layer)
    seq = [t for t in settings.tasks if t.id == "paper03"][0].sequence
    for step in range(1, len(seq)):
        place("main", 1, step, 0.0, step)
    return overrides, client, {**s, "sequence": seq}


def _without_admin_token() -> dict:
    return {k: v for k, v in os.environ.items() if k != ADMIN_ENV}


def test_export_command_writes_a_log_the_toolkit_reads_without_the_admin_token(tmp_path):
    from overhang_framework.behaviour.log import read_log

    overrides, _, s = _played(tmp_path)
    seq = s["sequence"]
    out = tmp_path / "log.jsonl"
    done = subprocess.run([sys.executable, "-m", "overhang_framework.experiment", "export", "--out", str(out),
                           *overrides], capture_output=True, text=True, timeout=120, env=_without_admin_token())
    assert done.returncode == 0, done.stderr
    log = read_log(out)
    assert len(log) == len(seq) - 1 and list(log.page_decision_time) == [1.5] * (len(seq) - 1)
    assert (log.decision_time == log.server_time).all() and (log.decision_time < 1.5).all()  # the server's time
    assert json.loads(out.read_text().splitlines()[0])["task_id"] == "paper03"


def test_reissue_command_prints_a_link_that_replaces_the_old_token(tmp_path):
    overrides, client, s = _played(tmp_path)
    done = subprocess.run([sys.executable, "-m", "overhang_framework.experiment", "reissue", "P9", *overrides,
                           "public_url=https://study.example.org/tower"],
                          capture_output=True, text=True, timeout=120, env=_without_admin_token())
    assert done.returncode == 0, done.stderr
    link = done.stdout.strip()
    assert link.startswith("https://study.example.org/tower/?participant=P9&token=")
    token = link.split("token=")[1]
    assert client.get("/api/session", headers={"Authorization": f"Bearer {s['token']}"}).status_code == 403
    assert client.get("/api/session", headers={"Authorization": f"Bearer {token}"}).json()["position"]["phase"] == "done"
    missing = subprocess.run([sys.executable, "-m", "overhang_framework.experiment", "reissue", "P0", *overrides],
                             capture_output=True, text=True, timeout=120, env=_without_admin_token())
    assert missing.returncode == 2 and missing.stderr.strip().splitlines() == [
        "error: no participant 'P0'; the study has 1: P9"]


def test_the_command_serves_the_page_and_the_api_with_its_default_processes(tmp_path):
    import socket
    import time

    import httpx

    from overhang_framework.experiment.web import dist_dir

    if not (dist_dir() / "index.html").exists():
        pytest.skip("the front end is not built (tests/test_experiment_e2e.py builds it)")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    server = subprocess.Popen([sys.executable, "-m", "overhang_framework.experiment", f"run_dir={tmp_path}",
                               "admin_token=long-enough-token", f"port={port}"],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.time() + 90
        while True:
            try:
                page = httpx.get(url + "/", timeout=5)
                break
            except httpx.HTTPError:
                assert server.poll() is None and time.time() < deadline, server.stderr.read() if server.poll() else ""
                time.sleep(0.5)
        assert page.status_code == 200 and "<html" in page.text
        conditions = [httpx.post(url + "/api/sessions", json={"params": {"participant": f"S{i}"}}, timeout=30).json()
                      ["condition"] for i in range(4)]
        assert sorted(conditions) == ["time_limited"] * 2 + ["unconstrained"] * 2
        listed = httpx.get(url + "/api/admin/participants", headers={"X-Admin-Token": "long-enough-token"}, timeout=30)
        assert [r["participant"] for r in listed.json()] == ["S0", "S1", "S2", "S3"]
    finally:
        server.terminate()
        server.wait(timeout=30)


def _built_front_end(tmp_path):
    web = tmp_path / "web"
    web.mkdir()
    (web / "index.html").write_text("<html></html>")
    return web


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_the_command_checks_run_dir_and_port_before_it_prints_or_writes_anything(tmp_path, capsys):
    import socket

    from overhang_framework.experiment.__main__ import main

    serve = ["admin_token=long-enough-token", f"web_dir={_built_front_end(tmp_path)}"]
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main([f"run_dir={blocker / 'run'}", *serve]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"error: cannot write the output directory '{blocker / 'run'}' ({blocker} is not a directory); "
        "choose another with run_dir=DIR"]
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main([f"run_dir={tmp_path / 'run'}", f"port={port}", *serve]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: cannot listen on 127.0.0.1:{port} ("), err
    assert "choose another port=P" in err[0]
    assert not (tmp_path / "run").exists()


def test_a_second_server_on_the_same_run_dir_is_refused(tmp_path, capsys, monkeypatch):
    import uvicorn

    from overhang_framework.experiment.__main__ import SETTINGS_ENV, main

    monkeypatch.setenv(SETTINGS_ENV, "")
    serve = ["admin_token=long-enough-token", f"web_dir={_built_front_end(tmp_path)}", "workers=2"]
    seen = []

    def listening(*args, **kwargs):  # while the first server runs, a second is started
        if not seen:
            assert capsys.readouterr().err.startswith("experiment: http://127.0.0.1:")
            seen.append(main([f"run_dir={tmp_path / 'run'}", f"port={_free_port()}", *serve]))
            seen.append(capsys.readouterr().err.splitlines())
            seen.append(main([f"run_dir={tmp_path / 'other'}", f"port={_free_port()}", *serve]))

    monkeypatch.setattr(uvicorn, "run", listening)
    assert main([f"run_dir={tmp_path / 'run'}", f"port={_free_port()}", *serve]) == 0
    refused, err, elsewhere = seen
    assert refused == 2 and err == [f"error: another server is serving the study in {tmp_path / 'run'}; stop it "
                                    "first, or give this one another run_dir=DIR"]
    assert elsewhere == 0
    assert main([f"run_dir={tmp_path / 'run'}", f"port={_free_port()}", *serve]) == 0  # the first one has stopped


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_a_second_server_on_the_same_database_is_refused_whatever_its_run_dir(tmp_path, capsys, monkeypatch, kind):
    import uvicorn

    from overhang_framework.experiment.__main__ import SETTINGS_ENV, main
    from overhang_framework.experiment.store import Store

    if kind == "sqlite":
        database, drop = f"sqlite:///{tmp_path / 'shared.sqlite'}", (lambda: None)
    else:
        from test_experiment_ops import fresh_postgres_database

        database, drop = fresh_postgres_database()
    monkeypatch.setenv(SETTINGS_ENV, "")
    serve = ["admin_token=long-enough-token", f"web_dir={_built_front_end(tmp_path)}", "workers=2", f"database={database}"]
    seen = []

    def listening(*args, **kwargs):  # while the first server runs, a second starts from another run_dir
        if not seen:
            capsys.readouterr()
            seen.append(main([f"run_dir={tmp_path / 'other'}", f"port={_free_port()}", *serve]))
            seen.append(capsys.readouterr().err.splitlines())

    monkeypatch.setattr(uvicorn, "run", listening)
    try:
        first_port = _free_port()
        assert main([f"run_dir={tmp_path / 'run'}", f"port={first_port}", *serve]) == 0
        refused, err = seen
        assert refused == 2 and len(err) == 1 and err[0].startswith(
            "error: another server is serving the study in the database "), err
        assert "stop it first" in err[0] and "long-enough" not in err[0]
        store = Store(database)
        assert store.study().address == f"http://127.0.0.1:{first_port}"  # not rewritten by the refused one
        store.close()
        assert main([f"run_dir={tmp_path / 'other'}", f"port={_free_port()}", *serve]) == 0  # the first has stopped
    finally:
        drop()


def test_export_counts_placements_and_timeouts_apart_and_refuses_an_unwritable_out(tmp_path, capsys):
    from fastapi.testclient import TestClient

    from overhang_framework.behaviour.log import read_log
    from overhang_framework.experiment.__main__ import main
    from overhang_framework.experiment.api import create_app

    overrides = [f"run_dir={tmp_path}", "tasks.only=[paper03,paper00]", "conditions=[time_limited]",
                 "physics_processes=0"]
    settings = load_settings([*overrides, "admin_token=long-enough-token"])
    now = [1_000_000.0]
    client = TestClient(create_app(settings, clock=lambda: now[0]))
    s = client.post("/api/sessions", json={"params": {"participant": "P9"}}).json()
    h = {"Authorization": f"Bearer {s['token']}"}
    client.post("/api/consent", json={"version": s["consent"]["version"]}, headers=h)

    def step(phase, trial, k, x, layer, seconds=1.0):
        body = {"phase": phase, "trial": trial, "step": k}
        client.post("/api/steps/start", json=body, headers=h)
        now[0] += seconds
        timed_out = x is None
        reply = client.post("/api/placements", json={**body, "x": x, "layer": layer, "timed_out": timed_out,
                                                     "decision_time": min(seconds, 5.0)}, headers=h)
        assert reply.status_code == 200, reply.text

    for k, pt in enumerate(settings.practice, 1):
        for j, (_, x, layer) in enumerate(pt.shown_tower[1:], 1):
            step("practice", k, j, x, layer)
    step("main", 1, 1, 0.0, 1)
    step("main", 1, 2, None, None, seconds=6.0)         # a timeout ends the first trial
    step("main", 2, 1, None, None, seconds=6.0)         # and the second
    out = tmp_path / "log.jsonl"
    assert main(["export", "--out", str(out), *overrides]) == 0
    log = read_log(out)
    assert (len(log), int(log.timed_out.sum())) == (3, 2)
    assert capsys.readouterr().err == (f"wrote {out}: 1 placement and 2 timeouts; the study's settings and versions "
                                       f"in {out.parent / 'log.study.json'}\n")
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    assert main(["export", "--out", str(blocker / "log.jsonl"), *overrides]) == 2
    assert capsys.readouterr().err == (f"error: cannot write the output directory '{blocker}' ({blocker} is not a "
                                       "directory); choose another with --out FILE\n")


def test_the_database_can_come_from_the_environment_and_a_bad_url_is_one_line(tmp_path, monkeypatch):
    from overhang_framework.experiment.settings import DATABASE_ENV

    url = "postgresql+psycopg://overhang:secret@db.example.org/overhang?sslmode=require"
    monkeypatch.setenv(DATABASE_ENV, url)
    assert load_settings([f"run_dir={tmp_path}"], need_admin_token=False).database == url
    given = f"sqlite:///{tmp_path / 'x.sqlite'}"
    assert load_settings([f"run_dir={tmp_path}", f"database={given}"], need_admin_token=False).database == given
    monkeypatch.delenv(DATABASE_ENV)
    assert load_settings([f"run_dir={tmp_path}"], need_admin_token=False).database.endswith("experiment.sqlite")
    with pytest.raises(ConfigError, match=r"^database: postgres:// is not a kind of database the server can open "
                                          r"\(write postgresql\+psycopg://\.\.\.\)"):
        load_settings([f"run_dir={tmp_path}", "database=postgres://u:p@h/db"], need_admin_token=False)


@pytest.mark.parametrize("url", ["sqlite:///C:\\data\\x.sqlite", 'postgresql+psycopg://u:p"q@h/db?a=1&b=2',
                                 "sqlite:///tmp/x\\", "postgresql+psycopg://overhang@/overhang?host=/run/postgresql&port=5433"])
def test_a_database_url_is_taken_as_written(url, tmp_path):
    assert load_settings([f"run_dir={tmp_path}", f"database={url}"], need_admin_token=False).database == url


def test_a_server_that_cannot_reach_its_database_exits_for_the_service_to_retry(tmp_path, capsys):
    from overhang_framework.experiment.__main__ import UNAVAILABLE, main

    code = main([f"run_dir={tmp_path / 'run'}", f"port={_free_port()}", "admin_token=long-enough-token",
                 "database=postgresql+psycopg://nobody:wrong@127.0.0.1:1/overhang"])
    err = capsys.readouterr().err
    assert code == UNAVAILABLE != 2  # the unit's RestartPreventExitStatus=2 keeps only refusals down
    assert err.count("\n") == 1 and err.startswith("error: cannot reach the database: ") and "wrong" not in err


def test_a_server_that_cannot_write_the_checkout_asks_for_the_build_in_one_line(tmp_path, monkeypatch):
    """A service user that does not own the checkout meets a front end without a build (or older than its sources):
    it is told to build it as the owner, and npm is not run."""
    import time

    from overhang_framework.errors import ConfigError
    from overhang_framework.experiment import web

    checkout = tmp_path / "web"
    (checkout / "dist").mkdir(parents=True)
    (checkout / "package.json").write_text("{}")
    monkeypatch.setattr(web, "REPO_WEB", checkout)
    monkeypatch.setattr(web.subprocess, "run", lambda *a, **k: pytest.fail(f"npm was run: {a}"))
    monkeypatch.setattr(web.os, "access", lambda path, mode: Path(path) != checkout)  # as its service user sees it
    with pytest.raises(ConfigError, match=r"^the front end has no build, and this user cannot write .*web to build it: run python "
                                          r"-m overhang_framework.experiment build as the checkout's owner first"):
        web.ensure_built()
    (checkout / "dist" / "index.html").write_text("<!doctype html>")
    old = time.time() - 60
    os.utime(checkout / "dist" / "index.html", (old, old))
    with pytest.raises(ConfigError, match="the front end is older than its sources, and this user cannot write"):
        web.ensure_built()
    monkeypatch.setattr(web.os, "access", lambda path, mode: True)
    os.utime(checkout / "package.json", (old - 60, old - 60))
    assert web.ensure_built() == checkout / "dist"  # built and current: served, nothing to write

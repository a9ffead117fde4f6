"""The experiment's settings and command: one-line errors before the server listens, practice optima that the
reference physics confirms, and the export command."""

from __future__ import annotations

import json
import os
import subprocess
import sys

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
    (["admin_token=short"], "at least 8"),
    (["admin_token=long-enough", "database=experiment.sqlite"], "SQLAlchemy URL"),
    (["admin_token=long-enough", "conditions=[time_limited,fast]"], "conditions must be"),
    (["admin_token=long-enough", "practice.threshold=2"], "practice.threshold"),
    (["admin_token=long-enough", "time_limit=0"], "time_limit"),
    (["admin_token=long-enough", "port=-1"], "port"),
    (["admin_token=long-enough", "workers=0"], "workers must be"),
    (["admin_token=long-enough", "physics_processes=-1"], "physics_processes must be"),
    (["admin_token=long-enough", "practice.ids=[paper00,practice2,practice3]"], "also main tasks"),
    (["admin_token=long-enough", "world.physics=static"], "python -m overhang_framework.optimum"),
    (["admin_token=long-enough", "predictor=ipe"], "predictor"),
])
def test_bad_settings_fail_in_one_line(tmp_path, overrides, words):
    with pytest.raises(ConfigError) as err:
        load_settings([f"run_dir={tmp_path}", *overrides])
    assert words in str(err.value) and "\n" not in str(err.value)


def test_the_admin_token_can_come_from_the_environment(tmp_path, monkeypatch):
    monkeypatch.setenv(ADMIN_ENV, "from-the-environment")
    assert load_settings([f"run_dir={tmp_path}"]).admin_token == "from-the-environment"


def test_practice_optima_stand_step_by_step_under_the_reference(tmp_path):
    settings = load_settings([f"run_dir={tmp_path}", "admin_token=long-enough"])
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
    settings = load_settings([*overrides, "admin_token=long-enough"])
    client = TestClient(create_app(settings))
    s = client.post("/api/sessions", json={"params": {"participant": "P9"}}).json()
    h = {"Authorization": f"Bearer {s['token']}"}

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
                               "admin_token=long-enough", f"port={port}"],
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
        listed = httpx.get(url + "/api/admin/participants", headers={"X-Admin-Token": "long-enough"}, timeout=30)
        assert [r["participant"] for r in listed.json()] == ["S0", "S1", "S2", "S3"]
    finally:
        server.terminate()
        server.wait(timeout=30)

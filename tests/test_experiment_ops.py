"""The experiment in production, piece by piece: links behind a proxy, the health check, backup and restore,
the nginx and systemd files.

The PostgreSQL tests create databases of their own on the server that ``OVERHANG_TEST_POSTGRES_URL`` names
(its role needs CREATEDB, as ``.ci/run`` grants); without it they are skipped, except under CI, where they
fail. The whole set-up through nginx, end to end, is ``tests/test_experiment_deploy.py``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import uuid

import pytest
from fastapi.testclient import TestClient

from overhang_framework.experiment.__main__ import main
from overhang_framework.experiment.api import create_app
from overhang_framework.experiment.settings import load_settings
from overhang_framework.experiment.store import Store

ADMIN = "ops-admin-token-1"
PG_ENV = "OVERHANG_TEST_POSTGRES_URL"


def fresh_postgres_database():
    """A new, empty PostgreSQL database (its URL) and a function that drops it."""
    from sqlalchemy import create_engine, text
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ProgrammingError

    url = os.environ.get(PG_ENV)
    if not url:
        if os.environ.get("CI"):
            pytest.fail(f"{PG_ENV} is not set: .ci/run starts a PostgreSQL server and sets it")
        pytest.skip(f"no PostgreSQL server ({PG_ENV} not set)")
    name = f"overhang_ops_{uuid.uuid4().hex[:12]}"
    admin = create_engine(url, isolation_level="AUTOCOMMIT")
    try:
        with admin.connect() as c:
            c.execute(text(f"CREATE DATABASE {name}"))
    except ProgrammingError:
        admin.dispose()
        if os.environ.get("CI"):
            pytest.fail("the test role cannot create databases (.ci/run grants CREATEDB)")
        pytest.skip("the test role cannot create databases (ALTER ROLE ... CREATEDB)")

    def drop():
        with admin.connect() as c:
            c.execute(text(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)"))
        admin.dispose()

    return make_url(url).set(database=name).render_as_string(hide_password=False), drop


@pytest.fixture
def pg_database():
    url, drop = fresh_postgres_database()
    yield url
    drop()


@pytest.fixture(scope="module")
def base_overrides(tmp_path_factory):
    run = tmp_path_factory.mktemp("ops")
    return [f"run_dir={run}", f"admin_token={ADMIN}", "tasks.only=[paper00,paper03]", "physics_processes=0"]


def client_for(overrides, **changes):
    settings = load_settings(overrides)
    for key, value in changes.items():
        setattr(settings, key, value)
    store = Store(settings.database)
    client = TestClient(create_app(settings, store=store))
    client.store = store
    return client


# links behind a proxy -----------------------------------------------------------------------------------------
PROXIED = {"X-Forwarded-Proto": "https", "X-Forwarded-Host": "study.example.org:8443",
           "X-Forwarded-For": "203.0.113.7"}


def reissued(client, headers=None):
    assert client.post("/api/sessions", json={"params": {"participant": "L1"}}).status_code == 201
    reply = client.post("/api/admin/participants/L1/reissue", headers={"X-Admin-Token": ADMIN, **(headers or {})})
    assert reply.status_code == 200, reply.text
    return reply.json()["resume_url"]


@pytest.mark.parametrize("trusted, public_url, expected", [
    ("testclient", None, "https://study.example.org:8443/?participant=L1&token="),  # a trusted proxy's address
    ("127.0.0.1", None, "http://testserver/?participant=L1&token="),  # anyone else's headers are ignored
    ("testclient", "https://lab.example.net/tower", "https://lab.example.net/tower/?participant=L1&token="),
])
def test_a_link_made_in_a_request_has_the_address_the_participant_opened(base_overrides, tmp_path, trusted,
                                                                         public_url, expected):
    client = client_for([*base_overrides, f"database=sqlite:///{tmp_path / 'links.sqlite'}"],
                        forwarded_allow_ips=trusted, public_url=public_url)
    link = reissued(client, PROXIED)
    assert link.startswith(expected), link
    client.store.close()


def test_a_forwarded_host_that_is_no_host_is_ignored(base_overrides, tmp_path):
    client = client_for([*base_overrides, f"database=sqlite:///{tmp_path / 'links.sqlite'}"],
                        forwarded_allow_ips="testclient")
    link = reissued(client, {**PROXIED, "X-Forwarded-Host": "evil.example/@x"})
    assert link.startswith("https://testserver/?"), link
    client.store.close()


@pytest.mark.parametrize("value, words", [("not-an-address", "forwarded_allow_ips"), ("''", "at least one")])
def test_forwarded_allow_ips_must_name_addresses(base_overrides, value, words):
    from overhang_framework.errors import ConfigError

    with pytest.raises(ConfigError, match=words):
        load_settings([*base_overrides, f"forwarded_allow_ips={value}"])
    assert load_settings([*base_overrides, "forwarded_allow_ips=[127.0.0.1,10.0.0.0/8]"]).forwarded_allow_ips \
        == "127.0.0.1,10.0.0.0/8"


# the health check -----------------------------------------------------------------------------------------------
def test_health_is_200_while_the_database_answers_and_503_when_it_is_gone(base_overrides, tmp_path):
    folder = tmp_path / "db"
    folder.mkdir()
    client = client_for([*base_overrides, f"database=sqlite:///{folder / 'health.sqlite'}", "workers=3"])
    reply = client.get("/api/health")  # no admin token: a monitor asks
    assert reply.status_code == 200
    body = reply.json()
    assert body["status"] == "ok" and body["database"] is True and body["workers"] == 3
    assert body["version"] and body["pid"] == os.getpid()
    shutil.rmtree(folder)  # the disk under the database went away
    client.store.engine.dispose()
    reply = client.get("/api/health")
    assert reply.status_code == 503
    body = reply.json()
    assert body["status"] == "unavailable" and body["database"] is False
    assert "\n" not in body["error"] and "database" in body["error"]


def test_health_is_503_when_the_postgresql_database_is_dropped(base_overrides):
    url, drop = fresh_postgres_database()
    client = client_for([*base_overrides, f"database={url}"])
    try:
        assert client.get("/api/health").status_code == 200
        drop()  # terminates the server's connections too
        reply = client.get("/api/health")
        assert reply.status_code == 503 and reply.json()["database"] is False
    finally:
        client.store.close()
        drop()


# backup and restore ---------------------------------------------------------------------------------------------
def play(client, pid, main_trials=1):
    """Participant ``pid`` through the practice (the shown towers) and ``main_trials`` main trials."""
    session = client.post("/api/sessions", json={"params": {"participant": pid}}).json()
    headers = {"Authorization": f"Bearer {session['token']}"}
    agreed = client.post("/api/consent", json={"version": session["consent"]["version"]}, headers=headers)
    assert agreed.status_code == 200, agreed.text
    settings = client.app.state.settings

    def place(phase, trial, step, x, layer):
        key = {"phase": phase, "trial": trial, "attempt": 1, "step": step}
        assert client.post("/api/steps/start", json=key, headers=headers).status_code == 200
        reply = client.post("/api/placements", json={**key, "x": x, "layer": layer, "decision_time": 1.0},
                            headers=headers)
        assert reply.status_code == 200, reply.text

    for k, practice in enumerate(settings.practice, 1):
        for step, (_, x, layer) in enumerate(practice.shown_tower[1:], 1):
            place("practice", k, step, x, layer)
    order = client.store.participant(pid).order
    by_id = {t.id: t for t in settings.tasks}
    for trial in range(1, main_trials + 1):
        for step in range(1, len(by_id[order[trial - 1]].sequence)):
            place("main", trial, step, 0.0, step)


def export(overrides, out):
    assert main(["export", "--out", str(out), *overrides]) == 0
    return out.read_text()


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_a_backup_restored_into_a_fresh_database_exports_the_same_log(base_overrides, tmp_path, kind, capsys):
    if kind == "sqlite":
        source, target = (f"sqlite:///{tmp_path / name}" for name in ("study.sqlite", "restored.sqlite"))
        drops = []
    else:
        (source, drop_source), (target, drop_target) = fresh_postgres_database(), fresh_postgres_database()
        drops = [drop_source, drop_target]
    try:
        client = client_for([*base_overrides, f"database={source}"])
        play(client, "B1", main_trials=2)
        play(client, "B2", main_trials=1)
        client.store.close()
        backup = tmp_path / ("study.backup" if kind == "sqlite" else "study.dump")
        assert main(["backup", "--out", str(backup), *base_overrides, f"database={source}"]) == 0
        said = capsys.readouterr().err
        assert f"a {kind} backup of 2 participants and" in said
        assert [p.name for p in tmp_path.iterdir() if p.name.startswith(f".{backup.name}")] == []  # no leftovers

        assert main(["restore", str(backup), *base_overrides, f"database={target}"]) == 0
        assert "2 participants" in capsys.readouterr().err
        before = export([*base_overrides, f"database={source}"], tmp_path / "before.jsonl")
        after = export([*base_overrides, f"database={target}"], tmp_path / "after.jsonl")
        assert after == before and len(before.splitlines()) >= 3 * 3
        assert {json.loads(line)["participant"] for line in after.splitlines()} == {"B1", "B2"}
        # the restored study goes on: its participants resume with their tokens, and newcomers are balanced
        restored = client_for([*base_overrides, f"database={target}"])
        assert restored.get("/api/admin/participants", headers={"X-Admin-Token": ADMIN}).json()[0]["participant"] == "B1"
        play(restored, "B3", main_trials=1)
        conditions = [p.condition for p in restored.store.participants()]
        assert sorted(conditions.count(c) for c in set(conditions)) == [1, 2]
        restored.store.close()

        # a second restore into the same database is refused, in one line, and changes nothing
        capsys.readouterr()
        assert main(["restore", str(backup), *base_overrides, f"database={target}"]) == 2
        message = capsys.readouterr().err.strip()
        assert message.startswith("error:") and "\n" not in message
        assert "exists" in message or "already holds a study" in message
        again = export([*base_overrides, f"database={target}"], tmp_path / "again.jsonl")
        assert len(again.splitlines()) > len(after.splitlines())  # B3's trial, nothing lost
    finally:
        for drop in drops:
            drop()


def test_backup_and_restore_refuse_bad_input_in_one_line(base_overrides, tmp_path, capsys):
    out = tmp_path / "copy.sqlite"
    assert main(["backup", "--out", str(out), *base_overrides, f"database=sqlite:///{tmp_path / 'none.sqlite'}"]) == 2
    assert "no database at" in capsys.readouterr().err and not out.exists()
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"not a backup")
    assert main(["restore", str(junk), *base_overrides, f"database=sqlite:///{tmp_path / 'r.sqlite'}"]) == 2
    assert "neither a SQLite database nor a pg_dump archive" in capsys.readouterr().err
    source = tmp_path / "s.sqlite"
    client = client_for([*base_overrides, f"database=sqlite:///{source}"])
    play(client, "C1", main_trials=0)
    client.store.close()
    assert main(["backup", "--out", str(out), *base_overrides, f"database=sqlite:///{source}"]) == 0
    assert main(["restore", str(out), *base_overrides, "database=postgresql+psycopg://u:p@127.0.0.1:1/x"]) == 2
    err = capsys.readouterr().err
    assert "is a sqlite backup and the database is postgresql" in err and "p@" not in err


def test_pg_dump_missing_from_path_is_one_line(base_overrides, tmp_path, monkeypatch, capsys, pg_database):
    client = client_for([*base_overrides, f"database={pg_database}"])
    client.store.close()
    monkeypatch.setenv("PATH", str(tmp_path))  # a PATH without PostgreSQL's client programs
    out = tmp_path / "x.dump"
    assert main(["backup", "--out", str(out), *base_overrides, f"database={pg_database}"]) == 2
    err = capsys.readouterr().err
    assert "pg_dump is not on PATH" in err and "postgresql-client" in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


# the nginx and systemd files ------------------------------------------------------------------------------------
def test_the_nginx_site_names_the_server_and_passes_nginx_t(tmp_path, capsys):
    out = tmp_path / "site.conf"
    assert main(["nginx-config", "--server-name", "study.example.org", "--out", str(out), "port=8123",
                 "--certificate", str(tmp_path / "c.pem"), "--certificate-key", str(tmp_path / "k.pem")]) == 0
    text = out.read_text()
    assert "server 127.0.0.1:8123;" in text and "server_name study.example.org;" in text
    assert "return 301 https://$host$request_uri;" in text
    for header in ("X-Forwarded-Proto $scheme", "X-Forwarded-For $proxy_add_x_forwarded_for",
                   "X-Forwarded-Host $http_host"):
        assert f"proxy_set_header {header};" in text
    assert "@" not in text.replace("@NAME@", "")  # every placeholder filled
    other = tmp_path / "other.conf"
    assert main(["nginx-config", "--server-name", "a.example.org", "--https-port", "8443", "--out", str(other)]) == 0
    assert "return 301 https://$host:8443$request_uri;" in other.read_text()
    assert "/etc/letsencrypt/live/a.example.org/fullchain.pem" in other.read_text()
    assert main(["nginx-config", "--server-name", "x y;", "--out", str(tmp_path / "bad.conf")]) == 2
    assert not (tmp_path / "bad.conf").exists()


def test_the_systemd_unit_runs_the_checked_overrides_as_the_user(tmp_path, capsys, service_user):
    from overhang_framework.experiment.deploy import exec_start_words

    out = tmp_path / "unit.service"
    assert main(["systemd-unit", "--user", "overhang", "--out", str(out), "run_dir=relative/study", "workers=3",
                 "contact='Lab, lab@example.org'"]) == 0
    text = out.read_text()
    assert "User=overhang" in text and "EnvironmentFile=/etc/overhang-experiment.env" in text
    words = exec_start_words(text)
    assert words[1:3] == ["-m", "overhang_framework.experiment"] and "workers=3" in words
    assert f"run_dir={(os.getcwd() + '/relative/study')}" in words  # made absolute
    assert "contact='Lab, lab@example.org'" in words
    assert main(["systemd-unit", "--user", "overhang", "workers=0"]) == 2  # checked as the server checks it
    assert "workers must be" in capsys.readouterr().err
    assert main(["systemd-unit", "--user", "overhang", "admin_token=a-long-secret-token"]) == 2
    assert "OVERHANG_ADMIN_TOKEN" in capsys.readouterr().err
    # a user the machine does not have, a password in the unit, a database the server cannot open: one line each
    for words, said in [
        (["--user", "nosuchuser"], "there is no user 'nosuchuser' on this machine; make it first"),
        (["--user", "overhang", "database=postgresql+psycopg://overhang:secret@db.example.org/overhang"],
         "leave the database's password out of the unit"),
        (["--user", "overhang", "database=postgres://overhang@/overhang"],
         "database: postgres:// is not a kind of database the server can open"),
    ]:
        assert main(["systemd-unit", *words, "--out", str(tmp_path / "refused.service")]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and said in err, err
        assert "secret" not in err
    assert not (tmp_path / "refused.service").exists()
    assert "RestartPreventExitStatus=2" in text.splitlines()  # a refused start is not restarted every 5 s
    # a database URL with a query (a socket directory, a port, sslmode) is taken as written
    query = "postgresql+psycopg://overhang@/overhang?host=/run/postgresql&port=5433"
    assert main(["systemd-unit", "--user", "overhang", "--out", str(out), f"database={query}"]) == 0
    assert f"database={query}" in exec_start_words(out.read_text())
    from overhang_framework.experiment.settings import load_settings

    assert load_settings([f"database={query}"], need_admin_token=False).database == query


# docs/deploy.md -------------------------------------------------------------------------------------------------
def deploy_commands():
    """The ``overhang_framework.experiment`` commands of docs/deploy.md's shell blocks, continuation lines joined,
    as argument lists (after the module)."""
    import re
    import shlex
    from pathlib import Path

    text = (Path(__file__).resolve().parents[1] / "docs" / "deploy.md").read_text()
    blocks = re.findall(r"```bash\n(.*?)```", text, flags=re.S)
    lines = "\n".join(blocks).replace("\\\n", " ").splitlines()
    out = []
    for line in lines:
        words = shlex.split(line.split(" #")[0])
        if "overhang_framework.experiment" in words:
            out.append(words[words.index("overhang_framework.experiment") + 1:])
    return out, text


def test_the_deploy_guide_s_commands_write_what_it_says(tmp_path, monkeypatch, capsys, service_user):
    from test_experiment_deploy import OPENSSL

    commands, text = deploy_commands()
    by_name = {c[0]: c for c in commands}
    assert {"build", "systemd-unit", "nginx-config", "export", "backup", "restore"} <= set(by_name)
    # the files: the guide's commands as written, into a temporary directory instead of /etc
    for name in ("systemd-unit", "nginx-config"):
        words = list(by_name[name])
        words[words.index("--out") + 1] = str(tmp_path / name)
        assert main(words) == 0, capsys.readouterr().err
    unit = (tmp_path / "systemd-unit").read_text()
    assert "User=overhang" in unit and "database=postgresql+psycopg://overhang@/overhang" in unit
    assert "public_url=https://study.example.org" in unit and "ReadWritePaths=-/srv/overhang/study" in unit
    site = (tmp_path / "nginx-config").read_text()
    assert "ssl_certificate /etc/letsencrypt/live/study.example.org/fullchain.pem;" in site
    # the self-signed certificate is the one the deployment test makes
    assert OPENSSL.format(key="/etc/ssl/private/overhang.key", cert="/etc/ssl/certs/overhang.pem") in text


@pytest.mark.parametrize("kind", ["sqlite", "postgresql"])
def test_a_backup_taken_while_the_server_writes_is_one_moment(tmp_path, kind):
    """Each newcomer's transaction adds a participant and counts it in ``newcomers``: a copy of one moment
    holds as many participants as it counted, whatever the writer was doing while it was taken."""
    import threading
    import time

    from sqlalchemy import create_engine, text

    from overhang_framework.experiment.backup import backup, restore
    from overhang_framework.experiment.store import Participant

    if kind == "sqlite":
        source, drops = f"sqlite:///{tmp_path / 'busy.sqlite'}", []
    else:
        (source, drop), drops = fresh_postgres_database(), []
        drops.append(drop)
    store = Store(source)
    done = threading.Event()

    def write():
        n = 0
        while not done.is_set():
            n += 1
            store.add_newcomer(["a"], lambda counts, n=n: Participant(
                id=f"W{n}", token_hash=uuid.uuid4().hex, condition="a", time_limit=None, order=[]))

    writer = threading.Thread(target=write)
    writer.start()
    try:
        deadline = time.time() + 30
        while store.count()["participants"] < 5 and time.time() < deadline:  # the writer is under way
            time.sleep(0.01)
        copies = []
        for k in range(3):
            out = tmp_path / f"busy-{k}.backup"
            copies.append((out, backup(source, out)))
    finally:
        done.set()
        writer.join()
        store.close()
    try:
        for k, (out, copied) in enumerate(copies):
            if kind == "sqlite":
                target = f"sqlite:///{tmp_path / f'check-{k}.sqlite'}"
            else:
                target, drop = fresh_postgres_database()
                drops.append(drop)
            restored = restore(out, target)
            engine = create_engine(target)
            with engine.connect() as c:
                counted = c.execute(text("SELECT assigned FROM newcomers WHERE id = 1")).scalar()
                held = c.execute(text("SELECT count(*) FROM participants")).scalar()
            engine.dispose()
            assert counted == held == copied.participants == restored.participants
        assert 5 <= copies[0][1].participants < copies[-1][1].participants  # taken while the writer wrote
    finally:
        for drop in drops:
            drop()


def test_a_database_that_refuses_the_commands_is_one_line(tmp_path, capsys):
    refusing = "database=postgresql+psycopg://nobody:wrong@127.0.0.1:1/overhang"  # nothing listens on port 1
    for words in (["export", "--out", str(tmp_path / "log.jsonl")], ["reissue", "P1"], ["withdraw", "P1", "--yes"]):
        assert main([*words, refusing, f"run_dir={tmp_path}"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and err.startswith("error: cannot reach the database: "), err
        assert "wrong" not in err
    assert not (tmp_path / "log.jsonl").exists()


def test_the_pilot_helps_examples_set_up_a_server_that_starts(tmp_path):
    """Every example of ``pilot --help`` that starts its own server has settings the server takes (a stored
    practice tower under its physics, among them)."""
    import shlex

    from overhang_framework.experiment.pilot import parser, plan, server_overrides
    from overhang_framework.experiment.settings import load_settings

    epilog = parser().epilog.replace("\\\n", " ")
    examples = [shlex.split(line)[4:] for line in epilog.splitlines() if "experiment pilot" in line]
    assert len(examples) >= 3
    for words in examples:
        args = parser().parse_args(words)
        if args.url:
            continue
        settings = load_settings(server_overrides(plan(args.overrides), args.time_scale, tmp_path, 8000) + args.serve,
                                 need_admin_token=False)
        assert settings.practice, words


def test_the_deploy_guide_installs_a_cpu_torch_and_checks_a_self_signed_server():
    _, text = deploy_commands()
    assert "pip install torch==2.14.1 torchvision==0.29.1 --index-url" in text  # not the 6.5 GB CUDA build
    assert "curl -sk https://localhost/api/health" in text
    assert "OVERHANG_DATABASE_URL=" in text and "RestartPreventExitStatus=2" in text
    assert "the server's lock and log" not in text  # the log is the journal


def test_the_deploy_guides_environment_file_is_made_private_before_a_secret_goes_in(tmp_path):
    """The guide's step 3 as written (into a temporary file): the file is 600 before the first secret is
    appended, and every line of it survives (nothing later overwrites it)."""
    import re

    _, text = deploy_commands()
    step = text.split("## 3.", 1)[1].split("```bash\n", 1)[1].split("```", 1)[0]
    env = tmp_path / "overhang-experiment.env"
    lines = [line.split(" #")[0] for line in step.replace("/etc/overhang-experiment.env", str(env)).splitlines()
             if line.strip() and not line.startswith("#")]
    assert lines[0].startswith("install -m 600 ") and all(">>" in line for line in lines[1:])
    assert not any(re.search(r"[^>]> ", line) for line in lines)  # no overwrite after the first line
    subprocess.run(["bash", "-c", "\n".join(lines)], check=True)
    assert oct(env.stat().st_mode & 0o777) == "0o600"
    written = env.read_text().splitlines()
    assert [w.split("=")[0] for w in written] == ["OVERHANG_ADMIN_TOKEN", "OVERHANG_DATABASE_URL"]

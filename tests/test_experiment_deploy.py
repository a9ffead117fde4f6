"""The production set-up of docs/deploy.md, end to end: Debian's nginx with TLS in front of two server
processes on PostgreSQL, and one participant in Chromium from the consent to the completion page over https.

The server is started with the command of the systemd unit that ``systemd-unit`` writes (its ExecStart, in
its WorkingDirectory, with its environment file), nginx with the site that ``nginx-config`` writes and a
self-signed certificate made by the command docs/deploy.md gives, on free loopback ports. The test checks
that http is redirected to https, that other host names get nothing, that every request of the page went
over https to the proxy, and that the links the server makes (a reissued resume link) are the proxy's.

Without nginx, openssl, Chromium, npm or a PostgreSQL server the test is skipped, except under CI, where it
fails.
"""

from __future__ import annotations

import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from test_experiment_e2e import ARGS, CHROMIUM, TASKS, ScriptedParticipant
from test_experiment_ops import fresh_postgres_database

from overhang_framework.experiment.__main__ import main

ADMIN = "deploy-admin-token"
#: The self-signed certificate of docs/deploy.md ("Trying it without a domain"), for ``localhost``.
OPENSSL = ("openssl req -x509 -newkey rsa:2048 -nodes -days 30 -subj /CN=localhost "
           "-addext subjectAltName=DNS:localhost,IP:127.0.0.1 -keyout {key} -out {cert}")
INSTALL = {"nginx": "apt-get install nginx", "openssl": "apt-get install openssl",
           "chromium": "apt-get install chromium", "npm": "apt-get install npm"}


def need(what: str, ok: bool) -> None:
    if not ok:
        if os.environ.get("CI"):
            pytest.fail(f"{what} is missing ({INSTALL[what]}); under CI the deployment test runs, never skips")
        pytest.skip(f"{what} is missing: the deployment test needs it ({INSTALL[what]})")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(check, what: str, timeout: float, process=None):
    deadline = time.time() + timeout
    while time.time() < deadline:
        if process is not None and process.poll() is not None:
            raise AssertionError(f"{what}: the process ended with exit code {process.returncode}")
        try:
            result = check()
            if result:
                return result
        except Exception:
            pass
        time.sleep(0.2)
    raise AssertionError(f"{what}: not ready after {timeout} s")


def stop(process, sig=signal.SIGTERM):
    if process is not None and process.poll() is None:
        process.send_signal(sig)
        try:
            process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def children(pid: int) -> list[int]:
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


NGINX_MAIN = """worker_processes 1;
events {{ worker_connections 256; }}
http {{
    include /etc/nginx/mime.types;
    access_log {prefix}/access.log;
    client_body_temp_path {prefix}/tmp/body;
    proxy_temp_path {prefix}/tmp/proxy;
    fastcgi_temp_path {prefix}/tmp/fastcgi;
    uwsgi_temp_path {prefix}/tmp/uwsgi;
    scgi_temp_path {prefix}/tmp/scgi;
    include {site};
}}
"""


def service_python(root: Path) -> str:
    """A Python the service user can run, with this test run's packages: a venv of the system's Python 3 (this
    run's interpreter may live where that user cannot enter, as under /root) whose one ``.pth`` line adds this
    run's site-packages (the project's editable install among them)."""
    import site
    import sysconfig

    venv = root / "service-venv"
    subprocess.run(["/usr/bin/python3", "-m", "venv", "--without-pip", str(venv)], check=True, capture_output=True)
    version = subprocess.run([str(venv / "bin" / "python"), "-c", "import sys; print(sys.version_info[:2])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    assert version == str(sys.version_info[:2]), f"the system's Python is {version}, this run's {sys.version_info[:2]}"
    packages = sysconfig.get_paths()["purelib"]
    target = next(venv.glob("lib/python3*/site-packages"))
    (target / "overhang-test-run.pth").write_text(f"import site; site.addsitedir({packages!r})\n")
    assert site  # the .pth line runs in the service's Python, not here
    return str(venv / "bin" / "python")


@pytest.fixture(scope="module")
def deployment(tmp_path_factory, service_user):
    """The server (from the systemd unit's command, as the unit's user on a checkout that user does not own, with
    the database's password in the environment file) and nginx (with the generated site) on loopback ports."""
    import pwd
    import tempfile

    import httpx

    need("nginx", shutil.which("nginx") is not None)
    need("openssl", shutil.which("openssl") is not None)
    need("chromium", Path(CHROMIUM).exists())
    need("npm", shutil.which("npm") is not None)
    from overhang_framework.experiment.deploy import exec_start_words
    from overhang_framework.experiment.web import ensure_built

    ensure_built()
    setup = time.time()
    database, drop = fresh_postgres_database()
    root = tmp_path_factory.mktemp("deploy")
    user = pwd.getpwnam(service_user)
    as_root = os.geteuid() == 0
    # the service's directory: the user's own, where that user can reach it (pytest's own is root's alone)
    home = Path(tempfile.mkdtemp(prefix="overhang-service-", dir="/tmp"))
    study = home / "study"
    study.mkdir()
    if as_root:
        os.chmod(home, 0o755)
        os.chown(study, user.pw_uid, user.pw_gid)
    port, http_port, https_port = free_port(), free_port(), free_port()
    overrides = [f"port={port}", "workers=2", f"run_dir={study}", f"tasks.only=[{TASKS[0]}]", "practice.max_attempts=3"]
    server = nginx = None
    try:
        # the server, as systemd starts it: the password only in the environment file
        env_file = root / "overhang-experiment.env"
        env_file.write_text(f"OVERHANG_ADMIN_TOKEN={ADMIN}\nOVERHANG_DATABASE_URL={database}\n")
        unit = root / "overhang-experiment.service"
        assert main(["systemd-unit", "--user", service_user, "--env-file", str(env_file), "--out", str(unit),
                     *overrides]) == 0
        text = unit.read_text()
        assert database.split("@")[0] not in text and "OVERHANG_DATABASE_URL" in text  # no password in the unit
        assert "RestartPreventExitStatus=2" in text.splitlines()
        workdir = next(line.split("=", 1)[1] for line in text.splitlines() if line.startswith("WorkingDirectory="))
        env = {**os.environ, **dict(line.split("=", 1) for line in env_file.read_text().splitlines())}
        env.pop("OVERHANG_EXPERIMENT_OVERRIDES", None)
        words = exec_start_words(text)
        run_as = {}
        if as_root:  # as the unit's user, on a checkout root owns, with a Python that user can run
            assert Path(workdir).stat().st_uid != user.pw_uid
            words[0] = service_python(home)
            env.update(HOME=str(study), USER=service_user)
            run_as = dict(user=user.pw_uid, group=user.pw_gid, extra_groups=[])
        server = subprocess.Popen(words, cwd=workdir, env=env, stdout=subprocess.DEVNULL,
                                  stderr=open(root / "server.log", "w"), start_new_session=True, **run_as)
        wait_until(lambda: httpx.get(f"http://127.0.0.1:{port}/api/health", timeout=2).status_code == 200,
                   "the server", 120, server)

        # nginx with a self-signed certificate
        cert, key = root / "cert.pem", root / "key.pem"
        subprocess.run(shlex.split(OPENSSL.format(key=key, cert=cert)), check=True, capture_output=True)
        site = root / "overhang-experiment.conf"
        assert main(["nginx-config", "--server-name", "localhost", "--listen", "127.0.0.1", "--http-port",
                     str(http_port), "--https-port", str(https_port), "--certificate", str(cert),
                     "--certificate-key", str(key), "--out", str(site), f"port={port}"]) == 0
        (root / "tmp").mkdir()
        conf = root / "nginx.conf"
        conf.write_text(NGINX_MAIN.format(prefix=root, site=site))
        command = ["nginx", "-c", str(conf), "-p", str(root),
                   "-g", f"daemon off; pid {root}/nginx.pid; error_log {root}/error.log;"]
        checked = subprocess.run([*command, "-t"], capture_output=True, text=True)
        assert checked.returncode == 0, checked.stderr
        nginx = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                 start_new_session=True)
        url = f"https://localhost:{https_port}"
        wait_until(lambda: httpx.get(f"{url}/api/health", verify=False, timeout=2).status_code == 200, "nginx",
                   30, nginx)
        print(f"\nthe server (2 processes) and nginx ready in {time.time() - setup:.1f} s")
        yield {"url": url, "http_url": f"http://localhost:{http_port}", "database": database, "server": server,
               "overrides": [*overrides, f"database={database}"], "root": root, "as_root": as_root}
    finally:
        stop(nginx, signal.SIGQUIT)
        stop(server)
        drop()
        shutil.rmtree(home, ignore_errors=True)


def test_a_participant_takes_part_through_nginx_over_https(deployment, tmp_path):
    import httpx
    from playwright.sync_api import sync_playwright

    from overhang_framework.experiment.settings import load_settings
    from overhang_framework.experiment.store import Store
    from overhang_framework.plugins import Registry

    url = deployment["url"]
    # plain http is sent to https, address and query kept
    reply = httpx.get(f"{deployment['http_url']}/?participant=X&a=1", follow_redirects=False)
    assert reply.status_code == 301 and reply.headers["location"] == f"{url}/?participant=X&a=1"
    # a name the site does not serve gets nothing, neither over http nor over https
    with pytest.raises(httpx.HTTPError):
        httpx.get(deployment["http_url"].replace("localhost", "127.0.0.1") + "/api/health")
    with pytest.raises(httpx.HTTPError):
        httpx.get(url.replace("localhost", "127.0.0.1") + "/api/health", verify=False)
    # the health check through the proxy; two server processes
    health = httpx.get(f"{url}/api/health", verify=False).json()
    assert health["status"] == "ok" and health["database"] is True and health["workers"] == 2
    assert len(children(deployment["server"].pid)) >= 2
    if deployment["as_root"]:  # the server and its processes run as the unit's user, not as root
        import pwd

        uid = pwd.getpwnam("overhang").pw_uid
        for pid in [deployment["server"].pid, *children(deployment["server"].pid)]:
            status = Path(f"/proc/{pid}/status").read_text()
            assert int(status.split("Uid:")[1].split()[1]) == uid, status

    settings = load_settings([*deployment["overrides"], f"admin_token={ADMIN}"])
    store = Store(deployment["database"])
    server = {"url": url, "store": store, "settings": settings, "world": Registry().create("world", settings.world)}
    requests: list[str] = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS, headless=True)
        context = browser.new_context(viewport={"width": 1400, "height": 1000}, ignore_https_errors=True)
        page = context.new_page()
        page.on("request", lambda r: requests.append(r.url))
        started = time.time()
        page.goto(f"{url}/?participant=D1&animation_speed=40")
        page.get_by_test_id("agree").wait_for(timeout=30_000)
        participant = ScriptedParticipant(page, server, "D1", collapse_first_practice=False)
        participant.run()
        seconds = time.time() - started
        assert page.url == f"{url}/complete"
        context.close()
        browser.close()
    print(f"\none participant through nginx over https, consent to completion: {seconds:.1f} s")

    assert store.participant("D1").completed_at is not None
    # the code's identity, read by the service's user from a checkout it does not own, on every record
    from overhang_framework.version import commit

    assert commit() and {r.commit for r in store.placements("D1")} == {commit()}
    assert store.study().commit == commit()
    main_rows = [r for r in store.placements("D1") if r.phase == "main"]
    assert {r.trial for r in main_rows if r.trial_over} == {1}
    # every request of the page went to the proxy over https
    assert requests and all(r.startswith(f"{url}/") for r in requests if not r.startswith("data:")), \
        sorted({r.split("?")[0] for r in requests})
    assert any(r.startswith(f"{url}/api/placements") for r in requests)

    # the server's links are the proxy's: a resume link reissued through it starts with the public address
    reply = httpx.post(f"{url}/api/admin/participants/D1/reissue", headers={"X-Admin-Token": ADMIN}, verify=False)
    assert reply.status_code == 200, reply.text
    link = reply.json()["resume_url"]
    assert link.startswith(f"{url}/?participant=D1&token="), link
    token = link.split("token=")[1]
    session = httpx.get(f"{url}/api/session", headers={"Authorization": f"Bearer {token}"}, verify=False)
    assert session.status_code == 200 and session.json()["completed"] is True
    store.close()

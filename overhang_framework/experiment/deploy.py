"""The files of a production set-up, from the templates in ``deploy/`` at the repository's root.

    python -m overhang_framework.experiment nginx-config --server-name NAME [OPTIONS] [OVERRIDES...]
    python -m overhang_framework.experiment systemd-unit --user USER [OPTIONS] [OVERRIDES...]

``nginx-config`` fills ``deploy/nginx/overhang-experiment.conf``: https in front
of the server that ``host`` and ``port`` name, http redirected to https, the
forwarded headers the server reads (``forwarded.py``). ``systemd-unit`` fills
``deploy/systemd/overhang-experiment.service``: the server with the given
overrides, as ``USER``, restarted when it fails. docs/deploy.md takes a lab
through both.
"""

from __future__ import annotations

import re
import shlex
import sys
from pathlib import Path
from typing import Sequence

from overhang_framework.errors import ConfigError
from overhang_framework.experiment.settings import REPO_WEB

REPO = REPO_WEB.parent
NGINX_TEMPLATE = REPO / "deploy" / "nginx" / "overhang-experiment.conf"
SYSTEMD_TEMPLATE = REPO / "deploy" / "systemd" / "overhang-experiment.service"
PLACEHOLDER = re.compile(r"@([a-z_]+)@")
SERVER_NAME = re.compile(r"^(\*\.)?[A-Za-z0-9]([A-Za-z0-9.-]*[A-Za-z0-9])?$")


def fill(template: Path, values: dict) -> str:
    """``template`` with each ``@name@`` replaced by ``values[name]``."""
    if not template.is_file():
        raise ConfigError(f"the template {template} is missing; run from a clone of the repository")
    text = template.read_text()
    missing = sorted({m for m in PLACEHOLDER.findall(text) if m not in values})
    if missing:
        raise ConfigError(f"{template} names {', '.join(missing)}, which nothing fills in")
    return PLACEHOLDER.sub(lambda m: str(values[m.group(1)]), text)


def _port(value: int, what: str) -> int:
    if not 0 < value < 65536:
        raise ConfigError(f"{what} must be a port number in [1, 65535], got {value}")
    return value


def nginx_config(server_name: str, overrides: Sequence[str] = (), certificate: str | None = None,
                 certificate_key: str | None = None, http_port: int = 80, https_port: int = 443,
                 listen: Sequence[str] = (), acme_root: str = "/var/www/html") -> str:
    """The nginx site for the server of ``overrides`` (its ``host`` and ``port``) at ``server_name``.

    The certificate defaults to certbot's for ``server_name``; ``listen`` restricts the addresses nginx
    listens on (default: every IPv4 and IPv6 address).
    """
    from overhang_framework.experiment.settings import compose

    names = server_name.split()
    if not names or not all(SERVER_NAME.match(n) for n in names):
        raise ConfigError(f"--server-name must be the host name(s) participants open, such as study.example.org, "
                          f"got {server_name!r}")
    cfg = compose(overrides)
    port = cfg.port
    if isinstance(port, bool) or not isinstance(port, int) or not 0 < port < 65536:
        raise ConfigError(f"port must be a whole number in [1, 65535], got {port!r}")
    host = str(cfg.host)
    if host in ("0.0.0.0", "::", ""):
        host = "127.0.0.1"
    upstream = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    http_port, https_port = _port(http_port, "--http-port"), _port(https_port, "--https-port")
    live = f"/etc/letsencrypt/live/{names[0]}"
    addresses = [a if a.startswith("[") or ":" not in a else f"[{a}]" for a in listen] or ["", "[::]:"]
    addresses = [a if a.endswith(":") or not a else f"{a}:" for a in addresses]

    def lines(port: int, extra: str) -> str:
        return "\n".join(f"    listen {a}{port}{extra};" for a in addresses)

    return fill(NGINX_TEMPLATE, {
        "upstream": upstream, "server_name": " ".join(names),
        "listen_http": lines(http_port, ""), "listen_https": lines(https_port, " ssl http2"),
        "listen_default": lines(http_port, " default_server") + "\n" + lines(https_port, " ssl default_server"),
        "https_suffix": "" if https_port == 443 else f":{https_port}",
        "certificate": certificate or f"{live}/fullchain.pem", "certificate_key": certificate_key or f"{live}/privkey.pem",
        "acme_root": acme_root,
    })


def systemd_unit(user: str, overrides: Sequence[str] = (), group: str | None = None,
                 env_file: str = "/etc/overhang-experiment.env", python: str | None = None,
                 workdir: str | None = None) -> str:
    """The systemd unit that serves the experiment with ``overrides`` as ``user``.

    The overrides are checked first (a mistake stops here, not at the service's start); ``run_dir`` is made
    absolute, since a service's working directory is not where this command runs.
    """
    from overhang_framework.experiment.settings import load_settings

    import pwd

    from sqlalchemy.engine import make_url

    from overhang_framework.experiment.settings import DATABASE_ENV

    if not re.match(r"^[a-z_][a-z0-9_-]*$", user):
        raise ConfigError(f"--user must be a system user's name, such as overhang, got {user!r}")
    try:
        pwd.getpwnam(user)
    except KeyError:
        raise ConfigError(f"there is no user {user!r} on this machine; make it first (sudo adduser --system "
                          f"--group {user}), or name the user the service runs as") from None
    settings = load_settings(overrides, need_admin_token=False)
    if any(o.startswith("admin_token=") for o in overrides):
        raise ConfigError("leave admin_token out of the unit (any local user can read it there); put "
                          "OVERHANG_ADMIN_TOKEN=... into the environment file (--env-file)")
    if any(o.lstrip("+").startswith("database=") for o in overrides) and make_url(settings.database).password:
        raise ConfigError(f"leave the database's password out of the unit (any local user can read it there, and ps "
                          f"shows it); leave database= out and put {DATABASE_ENV}=URL into the environment file "
                          "(--env-file), as the admin token is")
    run_dir = settings.run_dir.absolute()
    words = [o for o in overrides if not o.startswith("run_dir=")] + [f"run_dir={run_dir}"]
    command = [python or sys.executable, "-m", "overhang_framework.experiment", *words]
    return fill(SYSTEMD_TEMPLATE, {
        "user": user, "group": group or user, "workdir": workdir or str(REPO), "env_file": env_file,
        "exec_start": " ".join(_systemd_word(w) for w in command), "run_dir": str(run_dir),
    })


def _systemd_word(word: str) -> str:
    """``word`` quoted as systemd's ExecStart reads it (``$`` and ``%`` escaped: no expansion)."""
    word = word.replace("%", "%%").replace("$", "$$")
    return word if re.match(r"^[A-Za-z0-9_./:=@+,\[\]-]+$", word) else '"' + word.replace("\\", "\\\\").replace('"', '\\"') + '"'


def exec_start_words(unit_text: str) -> list[str]:
    """The command of a unit's ``ExecStart=`` line, as systemd splits it (for the unit written above)."""
    line = next(l for l in unit_text.splitlines() if l.startswith("ExecStart="))
    return [w.replace("$$", "$").replace("%%", "%") for w in shlex.split(line[len("ExecStart="):])]

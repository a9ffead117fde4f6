"""``python -m overhang_framework.experiment``: serve the experiment, export its log, build its front end.

    python -m overhang_framework.experiment [OVERRIDES...]                  # serve on localhost
    python -m overhang_framework.experiment export --out log.jsonl [OVERRIDES...] [--url URL]
    python -m overhang_framework.experiment reissue PARTICIPANT [OVERRIDES...] [--url URL]
    python -m overhang_framework.experiment build                            # (re)build web/dist
    python -m overhang_framework.experiment pilot --out DIR [--url URL] [PARTICIPANTS OVERRIDES...]

Overrides are keys of ``conf/serve.yaml`` (``port=8080``, ``database=postgresql+psycopg://...``,
``'tasks.only=[paper00,paper01]'``). ``export`` reads the database the config names, or with ``--url``
asks a running server (with the admin token). ``reissue`` gives a participant a new session token (the old
one stops working) and prints the link that resumes their session in any browser. ``pilot`` lets a
simulated cohort take part through the HTTP API (``pilot --help``; docs/experiment.md, "A pilot before
people").
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Optional, Sequence


#: How the server's worker processes get the command line's settings.
SETTINGS_ENV = "OVERHANG_EXPERIMENT_OVERRIDES"


def _serve(overrides: Sequence[str]) -> int:
    import os

    import uvicorn

    from overhang_framework.experiment.api import create_app
    from overhang_framework.experiment.settings import load_settings
    from overhang_framework.experiment.store import Store
    from overhang_framework.experiment.web import ensure_built
    from overhang_framework.preflight import check_writable
    from overhang_framework.rundir import RunDir

    settings = load_settings(overrides)
    check_writable(settings.run_dir, "run_dir=DIR")
    _check_port(settings.host, settings.port)
    web_dir = ensure_built(settings.web_dir)
    # one server a run_dir: a second would share the database with other settings, and balance the
    # conditions and hand out the session tokens of its own
    busy = (f"another server is serving the study in {settings.run_dir}; stop it first, or give this one "
            "another run_dir=DIR")
    with RunDir(settings.run_dir, busy).lock():
        Store(settings.database).close()  # the tables, made once before the server processes open the database
        db = settings.database.split("://")[0]
        print(f"experiment: http://{settings.host}:{settings.port}/?participant=P1  (database {db}, "
              f"{len(settings.tasks)} main trials, conditions {', '.join(settings.conditions)}, "
              f"{settings.workers} server process(es))", file=sys.stderr)
        options = dict(host=settings.host, port=settings.port, log_level="warning",
                       timeout_keep_alive=int(settings.keep_alive))
        if settings.workers == 1:
            settings.web_dir = web_dir
            uvicorn.run(create_app(settings), **options)
        else:
            os.environ[SETTINGS_ENV] = json.dumps([*overrides, f"web_dir={web_dir}"])
            uvicorn.run("overhang_framework.experiment.__main__:app_factory", factory=True,
                        workers=settings.workers, **options)
    return 0


def _check_port(host: str, port: int) -> None:
    """Raise unless the server can listen on ``host``:``port`` (another program holds it, say)."""
    import socket

    from overhang_framework.errors import ConfigError

    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server sets it
            probe.bind(address)
    except OSError as err:
        raise ConfigError(f"cannot listen on {host}:{port} ({err.strerror or err}); another program (another "
                          "server?) uses the port: stop it, or choose another port=P") from None


def app_factory():
    """The app of one server process, from the settings the command line gave (in :data:`SETTINGS_ENV`)."""
    import os

    from overhang_framework.experiment.api import create_app
    from overhang_framework.experiment.settings import load_settings

    return create_app(load_settings(json.loads(os.environ[SETTINGS_ENV])))


def _ask_server(args, method: str, path: str, timeout: float):
    """A running server's reply to an admin request (``args.url``), or None with the reason printed."""
    import os

    import httpx

    from overhang_framework.experiment.settings import ADMIN_ENV, compose

    cfg = compose(args.overrides)
    token = cfg.admin_token or os.environ.get(ADMIN_ENV)
    if not token:
        print(f"error: no admin token: set admin_token=... or {ADMIN_ENV}", file=sys.stderr)
        return None
    try:
        reply = httpx.request(method, args.url.rstrip("/") + path, headers={"X-Admin-Token": str(token)},
                              timeout=timeout)
    except httpx.HTTPError as err:
        print(f"error: cannot reach {args.url}: {err}", file=sys.stderr)
        return None
    if reply.status_code != 200:
        is_json = reply.headers.get("content-type", "").startswith("application/json")
        print(f"error: {args.url} refused {path} ({reply.status_code}): "
              f"{reply.json().get('error', reply.text) if is_json else reply.text}", file=sys.stderr)
        return None
    return reply


def _export(args) -> int:
    from overhang_framework.behaviour.log import count_noun
    from overhang_framework.preflight import check_writable
    from overhang_framework.results import atomic_write_text

    if args.url and args.include_screened_out:
        print("error: --include-screened-out reads the database; leave out --url", file=sys.stderr)
        return 2
    check_writable(Path(args.out).absolute().parent, "--out FILE")
    if args.url:
        reply = _ask_server(args, "GET", "/api/admin/export", timeout=120)
        if reply is None:
            return 2
        text, unfinished = reply.text, None
    else:
        from overhang_framework.experiment.export import export_jsonl
        from overhang_framework.experiment.settings import load_settings

        settings = load_settings(args.overrides, need_admin_token=False)
        store = _open_store(settings)
        if store is None:
            return 2
        text, unfinished = export_jsonl(store, include_screened_out=args.include_screened_out)
        store.close()
    atomic_write_text(args.out, text)
    timeouts = sum(bool(json.loads(line).get("timed_out")) for line in text.splitlines() if line.strip())
    placements = sum(1 for line in text.splitlines() if line.strip()) - timeouts
    extra = "" if not unfinished else f"; {unfinished} unfinished trial(s) left out"
    print(f"wrote {args.out}: {count_noun(placements, 'placement')} and {count_noun(timeouts, 'timeout')}{extra}",
          file=sys.stderr)
    return 0


def _open_store(settings):
    """The study's store, or None (with the reason printed) when its SQLite file does not exist."""
    from overhang_framework.experiment.store import Store

    if settings.database.startswith("sqlite:///"):
        path = Path(settings.database[len("sqlite:///"):])
        if not path.exists():
            print(f"error: no database at {path}; give the run_dir or database the server used", file=sys.stderr)
            return None
    return Store(settings.database)


def _reissue(args) -> int:
    if args.url:
        reply = _ask_server(args, "POST", f"/api/admin/participants/{args.participant}/reissue", timeout=60)
        if reply is None:
            return 2
        link = reply.json()["resume_url"]
    else:
        from overhang_framework.experiment.api import Refused, reissue
        from overhang_framework.experiment.settings import load_settings

        settings = load_settings(args.overrides, need_admin_token=False)
        store = _open_store(settings)
        if store is None:
            return 2
        try:
            _, link = reissue(settings, store, args.participant)
        except Refused as err:
            print(f"error: {err.message}", file=sys.stderr)
            return 2
        finally:
            store.close()
        if settings.public_url is None:
            print(f"note: the link starts with http://{settings.host}:{settings.port}, from host and port; give "
                  "public_url=https://... (the address participants open) when that is not it", file=sys.stderr)
    print(f"participant {args.participant}: a new session token; the old one no longer works. Resume link "
          "(send it to the participant; it resumes where they stopped, in any browser):", file=sys.stderr)
    print(link)
    return 0


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    from overhang_framework.errors import OverhangError

    commands = ("serve", "export", "reissue", "build", "pilot")
    command = argv[0] if argv and argv[0] in commands else "serve"
    if argv and argv[0] == command:
        argv = argv[1:]
    if command == "pilot":
        from overhang_framework.experiment.pilot import main as pilot

        return pilot(argv)
    elif argv and not argv[0].startswith("-"):
        from overhang_framework.preflight import check_words

        try:  # a misspelt command is no override either: one line naming the commands
            check_words(argv[:1], commands)
        except OverhangError as err:
            print(f"error: {err}; commands: {', '.join(commands)}", file=sys.stderr)
            return 2
    parser = argparse.ArgumentParser(prog=f"python -m overhang_framework.experiment {command}",
                                     description=__doc__.split("\n\n")[0])
    if command == "reissue":
        parser.add_argument("participant", help="the participant's id (PROLIFIC_PID or participant)")
    parser.add_argument("overrides", nargs="*", help="keys of conf/serve.yaml, e.g. port=8080 database=URL")
    if command == "export":
        parser.add_argument("--out", required=True, help="the behaviour log to write (JSON Lines)")
        parser.add_argument("--include-screened-out", action="store_true",
                            help="add the practice attempts of participants screened out in the practice")
    if command in ("export", "reissue"):
        parser.add_argument("--url", help="a running server to ask (default: read the database directly)")
    if command == "build":
        parser.add_argument("--force", action="store_true", help="build even when web/dist exists")
    args = parser.parse_args(argv)
    try:
        if command == "export":
            return _export(args)
        if command == "reissue":
            return _reissue(args)
        if command == "build":
            from overhang_framework.experiment.web import ensure_built

            print(ensure_built(force=args.force))
            return 0
        return _serve(args.overrides)
    except (OverhangError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())

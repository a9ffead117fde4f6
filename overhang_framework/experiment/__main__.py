"""``python -m overhang_framework.experiment``: serve the experiment, export its log, build its front end.

    python -m overhang_framework.experiment [OVERRIDES...]                  # serve on localhost
    python -m overhang_framework.experiment export --out log.jsonl [OVERRIDES...] [--url URL]
    python -m overhang_framework.experiment export --format psych-ds --out DIR [OVERRIDES...] [--url URL]
    python -m overhang_framework.experiment reissue PARTICIPANT [OVERRIDES...] [--url URL]
    python -m overhang_framework.experiment withdraw PARTICIPANT --yes [OVERRIDES...] [--url URL]
    python -m overhang_framework.experiment build                            # (re)build web/dist
    python -m overhang_framework.experiment backup --out FILE [OVERRIDES...]  # a consistent copy of the database
    python -m overhang_framework.experiment restore FILE [OVERRIDES...]       # into an empty database
    python -m overhang_framework.experiment nginx-config --server-name NAME [OVERRIDES...]
    python -m overhang_framework.experiment systemd-unit --user USER [OVERRIDES...]
    python -m overhang_framework.experiment pilot --out DIR [--url URL] [PARTICIPANTS OVERRIDES...]

Overrides are keys of ``conf/serve.yaml`` (``port=8080``, ``database=postgresql+psycopg://...``,
``'tasks.only=[paper00,paper01]'``). ``export`` reads the database the config names, or with ``--url``
asks a running server (with the admin token). ``reissue`` gives a participant a new session token (the old
one stops working) and prints the link that resumes their session in any browser. ``withdraw`` deletes a
participant who withdrew their consent, with everything stored of them; the study keeps only a count.
``export`` also writes ``study.json`` beside the log: the study's settings, versions and dates.
``backup``, ``restore``, ``nginx-config`` and ``systemd-unit`` are the production set-up of docs/deploy.md.
``pilot`` lets a simulated cohort take part through the HTTP API (``pilot --help``; docs/experiment.md, "A
pilot before people").
"""

from __future__ import annotations

import argparse
import textwrap
import json
import sys
from pathlib import Path
from typing import Optional, Sequence

from overhang_framework.experiment.settings import SETTINGS_ENV


#: What each command does, for its --help.
DESCRIPTIONS = {
    "serve": "Serve the experiment (the page and its API) on host:port, with the settings of the overrides.",
    "export": "Write the study's whole main trials as a behaviour log (JSON Lines) or a Psych-DS dataset, and "
              "the study's settings and versions as a study.json sidecar.",
    "reissue": "Give a participant a new session token (the old one stops working) and print the link that "
               "resumes their session in any browser.",
    "withdraw": "Delete a participant who withdrew their consent, with everything stored of them; the study keeps "
                "only a count, and refuses their id if they come back.",
    "build": "Build the front end (web/dist) with npm.",
    "backup": "Write a consistent copy of the study's database while the server runs (SQLite: a database file; "
              "PostgreSQL: a pg_dump archive); an existing file at --out is replaced.",
    "restore": "Restore a backup into an empty database (a new SQLite file, or an empty PostgreSQL database).",
    "nginx-config": "Write the nginx site that serves the study over https in front of the server (docs/deploy.md).",
    "systemd-unit": "Write the systemd service that runs the server (docs/deploy.md).",
    "pilot": "Let a simulated cohort take part through the server's API, as a pilot before people.",
}

#: Each command in a line, for the list of commands.
SUMMARIES = {
    "serve": "serve the experiment (the default command)",
    "export": "the study's data: a behaviour log or a Psych-DS dataset, with study.json",
    "reissue": "a new resume link for a participant",
    "withdraw": "delete a participant who withdrew their consent",
    "build": "build the front end",
    "backup": "a consistent copy of the study's database",
    "restore": "a backup into an empty database",
    "nginx-config": "the nginx site for https in front of the server",
    "systemd-unit": "the systemd service that runs the server",
    "pilot": "simulated participants through the server, before people",
}

#: The exit status of a server that cannot reach its database (EX_TEMPFAIL): unlike 2 (a refusal that needs the
#: operator), the systemd unit restarts it.
UNAVAILABLE = 75


def _serve(overrides: Sequence[str]) -> int:
    import contextlib
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
    # one server a run_dir: a second would share the database with other settings, and balance the
    # conditions and hand out the session tokens of its own
    busy = (f"another server is serving the study in {settings.run_dir}; stop it first, or give this one "
            "another run_dir=DIR")
    with RunDir(settings.run_dir, busy).lock(), contextlib.ExitStack() as held:
        from overhang_framework.experiment.api import begin_study, public_base

        store = Store(settings.database)  # the tables, made once before the server processes open the database
        held.callback(store.close)
        # one server a study, whatever its run_dir or machine: a second would rewrite the study's address and
        # balance the conditions on its own; held until this server stops
        held.enter_context(store.serving(f"another server is serving the study in the database "
                                         f"{_shown(settings.database)}; stop it first"))
        known = len(getattr(store.study(), "history", None) or [])
        study = begin_study(settings, store)  # refused when the study runs with other settings
        address = public_base(settings, store=store)
        web_dir = ensure_built(settings.web_dir)
        db = settings.database.split("://")[0]
        if not study.commit:
            print(f"warning: the code's commit cannot be read (it does not run from a git checkout, or git is "
                  f"missing): the study's records name version {study.framework_version} without a commit",
                  file=sys.stderr)
        for event in study.history[known:]:
            if event["what"] == "settings":
                print(f"experiment: the study's settings changed ({'; '.join(event['changes'])}); recorded with "
                      "the study", file=sys.stderr)
        print(f"experiment: {address}/?participant=P1  (database {db}, "
              f"{len(settings.tasks)} main trials, conditions {', '.join(settings.conditions)}, "
              f"{settings.workers} server process(es))", file=sys.stderr)
        # the app reads the forwarded headers itself, from the proxies forwarded_allow_ips names (forwarded.py)
        options = dict(host=settings.host, port=settings.port, log_level="warning",
                       timeout_keep_alive=int(settings.keep_alive), proxy_headers=False)
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
    from overhang_framework.experiment.export import FORMATS, study_json, study_text
    from overhang_framework.preflight import check_writable
    from overhang_framework.results import atomic_write_text, json_line

    if args.format not in FORMATS:
        print(f"error: --format {args.format}: unknown format; formats: {', '.join(FORMATS)}", file=sys.stderr)
        return 2
    if args.url and args.include_screened_out:
        print("error: --include-screened-out reads the database; leave out --url", file=sys.stderr)
        return 2
    out = Path(args.out)
    check_writable(out.absolute().parent, "--out FILE" if args.format == "jsonl" else "--out DIR")
    if args.format == "jsonl":
        problem = _not_a_log_target(out)
        if problem:
            print(f"error: --out {args.out}: {problem}", file=sys.stderr)
            return 2
    if args.format == "psych-ds":
        from overhang_framework.behaviour.psychds import check_out

        check_out(out)  # before the database is read: an --out that cannot take a dataset is said at once
    if args.url:
        reply = _ask_server(args, "GET", "/api/admin/export" + ("?include_simulated=true" if args.include_simulated
                                                                 else ""), timeout=120)
        study = _ask_server(args, "GET", "/api/admin/study", timeout=60) if reply is not None else None
        if study is None:
            return 2
        text, unfinished, study = reply.text, None, study.json()
        records = [json_line(line) for line in text.splitlines() if line.strip()]
    else:
        from overhang_framework.experiment.export import log_records
        settings, store = _local_store(args)
        if store is None:
            return 2
        try:
            records, unfinished = log_records(store, include_screened_out=args.include_screened_out,
                                              include_simulated=args.include_simulated)
            study = study_json(store)
        finally:
            store.close()
    if args.format == "psych-ds":
        from overhang_framework.experiment.export import write_psychds

        files = write_psychds(records, out, study)
        where = f"{args.out} (Psych-DS, {count_noun(len(files), 'data file')})"
        sidecar = out / "study.json"
    else:
        from overhang_framework.behaviour.log import log_text

        sidecar = sidecar_of(out)
        atomic_write_text(out, text if args.url else log_text(records))
        atomic_write_text(sidecar, study_text(study))
        where = args.out
    timeouts = sum(bool(r.get("timed_out")) for r in records)
    placements = len(records) - timeouts
    extra = "" if not unfinished else f"; {unfinished} unfinished trial(s) left out"
    simulated = int((study.get("participants") or {}).get("simulated") or 0)
    of_people = ((((study.get("study") or {}).get("settings")) or {}).get("source") or "human") != "simulated"
    if simulated and of_people and not args.include_simulated:
        extra += (f"; {count_noun(simulated, 'simulated participant')} (a pilot's) left out: add --include-simulated "
                  "to export them")
    print(f"wrote {where}: {count_noun(placements, 'placement')} and {count_noun(timeouts, 'timeout')}{extra}; "
          f"the study's settings and versions in {sidecar}", file=sys.stderr)
    return 0


def sidecar_of(log: Path) -> Path:
    """Where a JSON Lines export's ``study.json`` goes: beside it, named after it (``log.jsonl`` ->
    ``log.study.json``), so that exports in one folder keep their own."""
    log = log.absolute()
    return log.with_name((log.name[: -len(log.suffix)] if log.suffix else log.name) + ".study.json")


def _not_a_log_target(out: Path) -> Optional[str]:
    """Why a JSON Lines export must not be written to ``out`` (None when it may: a new file, or an earlier
    behaviour log, which it replaces)."""
    if out.is_dir():
        return "is a folder; give the log's file name, e.g. log.jsonl (or --format psych-ds for a dataset folder)"
    if out.name.endswith(".study.json") or out.name == "study.json":
        return "is the name of an export's study.json sidecar; give the log's file name, e.g. log.jsonl"
    if out.exists() and out.stat().st_size:
        with open(out, "rb") as f:
            first = f.readline(100_000).strip()
        try:
            record = json.loads(first)
        except ValueError:
            record = None
        if not isinstance(record, dict) or "log_version" not in record:
            return ("exists and is not a behaviour log (its first line is no log record); the export would "
                    "replace it: give a new file name")
    return None


def _local_store(args):
    """The settings of ``args.overrides`` (no admin token needed: the database answers to whoever can read it)
    and the study's store, None when it has no database (the reason printed)."""
    from overhang_framework.experiment.settings import load_settings

    settings = load_settings(args.overrides, need_admin_token=False)
    return settings, _open_store(settings)


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
        settings, store = _local_store(args)
        if store is None:
            return 2
        study = store.study()
        stored_public = study is not None and study.public_url is not None
        known = store.participant(args.participant)
        if known is not None and (known.completed_at is not None or known.screened_out_at is not None):
            ended = "finished the study" if known.completed_at is not None else "was screened out in the practice"
            print(f"note: participant {args.participant} {ended}; the link shows them how it ended, nothing more",
                  file=sys.stderr)
        try:
            _, link = reissue(settings, store, args.participant)
        except Refused as err:
            print(f"error: {err.message}", file=sys.stderr)
            return 2
        finally:
            store.close()
        if settings.public_url is None and not stored_public:
            print(f"note: the link starts with {link.split('/?')[0]}, where the server listened; give "
                  "public_url=https://... (the address participants open) when that is not it", file=sys.stderr)
    print(f"participant {args.participant}: a new session token; the old one no longer works. Resume link "
          "(send it to the participant; it resumes where they stopped, in any browser):", file=sys.stderr)
    print(link)
    return 0


def _withdraw(args) -> int:
    if not args.yes:
        what = "everything stored of them"
        if not args.url:  # say what would go, or that there is no such participant
            from overhang_framework.experiment.api import unknown_participant

            _, store = _local_store(args)
            if store is None:
                return 2
            try:
                if store.participant(args.participant) is None:
                    print(f"error: {unknown_participant(store, args.participant).message}", file=sys.stderr)
                    return 2
                what = f"them with their {len(store.placements(args.participant))} placement(s) and step clocks"
            finally:
                store.close()
        print(f"error: withdrawing participant {args.participant} deletes {what}, for good; nothing was deleted: "
              "add --yes to do it", file=sys.stderr)
        return 2
    if args.url:
        reply = _ask_server(args, "POST", f"/api/admin/participants/{args.participant}/withdraw", timeout=60)
        if reply is None:
            return 2
        done = reply.json()
    else:
        from overhang_framework.experiment.api import Refused, withdraw
        settings, store = _local_store(args)
        if store is None:
            return 2
        try:
            done = withdraw(store, args.participant)
        except Refused as err:
            print(f"error: {err.message}", file=sys.stderr)
            return 2
        finally:
            store.close()
    deleted = done["deleted"]
    print(f"withdrew participant {args.participant}: deleted them with {deleted['placements']} placement(s) and "
          f"{deleted['clocks']} step clock(s); the study keeps only a count ({done['withdrawn']} withdrawn). Copies "
          "made before (exports, backups) still hold them.", file=sys.stderr)
    return 0


def _backup(args) -> int:
    from overhang_framework.experiment.backup import backup, check_backup_target, describe
    from overhang_framework.experiment.settings import load_settings

    out = check_backup_target(args.out)
    settings = load_settings(args.overrides, need_admin_token=False)
    copied = backup(settings.database, out)
    print(f"wrote {args.out}: a {copied.kind} backup of {describe(copied)}", file=sys.stderr)
    return 0


def _restore(args) -> int:
    from overhang_framework.experiment.backup import describe, restore
    from overhang_framework.experiment.settings import load_settings

    settings = load_settings(args.overrides, need_admin_token=False)
    copied = restore(args.file, settings.database)
    print(f"restored {args.file} into {settings.database.split('://')[0]} ({_shown(settings.database)}): "
          f"{describe(copied)}", file=sys.stderr)
    return 0


def _shown(url: str) -> str:
    from sqlalchemy.engine import make_url

    return make_url(url).render_as_string(hide_password=True)


def _write(text: str, out: Optional[str]) -> int:
    from overhang_framework.preflight import check_writable
    from overhang_framework.results import atomic_write_text

    if out is None:
        sys.stdout.write(text)
        return 0
    check_writable(Path(out).absolute().parent, "--out FILE")
    atomic_write_text(out, text)
    print(f"wrote {out}", file=sys.stderr)
    return 0


def parser(command: str = "serve") -> argparse.ArgumentParser:
    """The argument parser of ``command`` (one of :data:`SUMMARIES`, the pilot's aside: ``pilot.parser``); its
    arguments are read with ``parse_intermixed_args``."""
    commands = tuple(SUMMARIES)
    ap = argparse.ArgumentParser(
        prog=f"python -m overhang_framework.experiment {command}", description=textwrap.fill(DESCRIPTIONS[command], 100),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog=(("commands:\n" + "\n".join(f"  {c:<13} {SUMMARIES[c]}" for c in commands)
                 + "\n\npython -m overhang_framework.experiment COMMAND --help says more.")
                if command == "serve" else "Overrides are keys of conf/serve.yaml (docs/experiment.md); the\n"
                "commands that read the study's database need the run_dir=DIR or database=URL its server used."))
    if command in ("reissue", "withdraw"):
        ap.add_argument("participant", help="the participant's id (PROLIFIC_PID or participant)")
    if command == "withdraw":
        ap.add_argument("--yes", action="store_true",
                            help="delete them, for good (without it nothing is deleted: the command says what would "
                                 "be; exports and backups made before still hold them)")
    if command == "restore":
        ap.add_argument("file", help="a backup that the backup command wrote")
    ap.add_argument("overrides", nargs="*", help="keys of conf/serve.yaml, e.g. run_dir=DIR port=8080 "
                                                     "database=URL")
    if command == "backup":
        ap.add_argument("--out", required=True, help="the copy to write (SQLite: a database file; "
                                                         "PostgreSQL: a pg_dump archive, custom format)")
    if command == "nginx-config":
        ap.add_argument("--server-name", required=True, help="the host name participants open")
        ap.add_argument("--certificate", help="default: certbot's fullchain.pem for the server name")
        ap.add_argument("--certificate-key", help="default: certbot's privkey.pem for the server name")
        ap.add_argument("--http-port", type=int, default=80)
        ap.add_argument("--https-port", type=int, default=443)
        ap.add_argument("--listen", action="append", default=[],
                            help="an address to listen on (repeatable; default: every IPv4 and IPv6 address)")
    if command == "systemd-unit":
        ap.add_argument("--user", required=True, help="the system user the server runs as")
        ap.add_argument("--env-file", default="/etc/overhang-experiment.env",
                            help="the file with OVERHANG_ADMIN_TOKEN=... (default: %(default)s)")
    if command in ("nginx-config", "systemd-unit"):
        ap.add_argument("--out", help="the file to write (default: standard output)")
    if command == "export":
        ap.add_argument("--out", required=True,
                            help="the behaviour log to write (JSON Lines), or with --format psych-ds the dataset's "
                                 "folder (new, empty, or an earlier export, which is replaced)")
        ap.add_argument("--format", default="jsonl", metavar="|".join(("jsonl", "psych-ds")),
                            help="jsonl (default): one behaviour-log file; psych-ds: a Psych-DS dataset folder")
        ap.add_argument("--include-screened-out", action="store_true",
                            help="add the practice attempts of participants screened out in the practice")
        ap.add_argument("--include-simulated", action="store_true",
                            help="add a pilot's simulated participants (source: simulated) to an export of a "
                                 "study of people")
    if command in ("export", "reissue", "withdraw"):
        ap.add_argument("--url", help="a running server to ask (default: read the database directly)")
    if command == "build":
        ap.add_argument("--force", action="store_true", help="build even when web/dist exists")
    return ap


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    from overhang_framework.errors import OverhangError

    commands = tuple(SUMMARIES)
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
    args = parser(command).parse_intermixed_args(argv)  # overrides may come before or after the flags
    for name, what in (("participant", "a participant's id"), ("file", "the backup file")):
        value = getattr(args, name, None)
        if value is not None and "=" in value and not Path(value).exists():
            print(f"error: {command} needs {what} first, then the overrides; got the override {value!r}",
                  file=sys.stderr)
            return 2
    try:
        if command == "export":
            return _export(args)
        if command == "reissue":
            return _reissue(args)
        if command == "withdraw":
            return _withdraw(args)
        if command == "backup":
            return _backup(args)
        if command == "restore":
            return _restore(args)
        if command == "nginx-config":
            from overhang_framework.experiment.deploy import nginx_config

            return _write(nginx_config(args.server_name, args.overrides, args.certificate, args.certificate_key,
                                       args.http_port, args.https_port, args.listen), args.out)
        if command == "systemd-unit":
            from overhang_framework.experiment.deploy import systemd_unit

            return _write(systemd_unit(args.user, args.overrides, env_file=args.env_file), args.out)
        if command == "build":
            from overhang_framework.experiment.web import ensure_built

            print(ensure_built(force=args.force))
            return 0
        return _serve(args.overrides)
    except (OverhangError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except Exception as err:  # a database that refuses the user, is not there, or went away
        from sqlalchemy.exc import SQLAlchemyError

        from overhang_framework.experiment.store import database_reason

        if not isinstance(err, SQLAlchemyError):
            raise
        if command == "serve":  # a database not up yet (at boot): the service is to try again, so not status 2
            print(f"error: cannot reach the database: {database_reason(err)}; exit status {UNAVAILABLE}: try again "
                  "later (the service does)", file=sys.stderr)
            return UNAVAILABLE
        print(f"error: cannot reach the database: {database_reason(err)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())

"""A consistent copy of the study's database, and a study restored from one.

    python -m overhang_framework.experiment backup --out FILE [OVERRIDES...]
    python -m overhang_framework.experiment restore FILE [OVERRIDES...]      # database=URL or run_dir=DIR

SQLite is copied with SQLite's online backup API: one read transaction, so the
copy is the database as it was at one moment while the server goes on writing
(WAL mode lets it). PostgreSQL is copied with ``pg_dump`` (custom format), run
in the snapshot of a transaction that also counts what it holds: the dump and
the counts are the same moment. ``pg_dump`` must be on PATH and not older than
the server (Debian: ``postgresql-client``). The copy lands all at once (written
beside ``--out``, then renamed).

A restore goes into an empty database only: a new SQLite file, or a PostgreSQL
database without the study's tables (``createdb -O overhang overhang_restored``),
through ``pg_restore`` in one transaction.
"""

from __future__ import annotations

import os
import re
import shutil
import sqlite3
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from overhang_framework.errors import ConfigError
from overhang_framework.results import atomic_output

SQLITE_MAGIC = b"SQLite format 3\x00"
PG_DUMP_MAGIC = b"PGDMP"
PG_CLIENT = "Debian: apt-get install postgresql-client"


@dataclass
class Copied:
    """What a backup or a restore holds."""

    kind: str  # "sqlite" or "postgresql"
    participants: int
    placements: int


def is_sqlite(url: str) -> bool:
    return url.startswith("sqlite")


def sqlite_path(url: str) -> Path:
    if not url.startswith("sqlite:///") or url == "sqlite:///:memory:":
        raise ConfigError(f"a SQLite database to copy is a file, sqlite:///PATH, got {url}")
    return Path(url[len("sqlite:///"):])


def libpq(url: str) -> tuple[str, dict]:
    """The libpq address of a SQLAlchemy PostgreSQL URL (for pg_dump, pg_restore) without its password, and
    the environment that passes the password (never on a command line, where ``ps`` shows it)."""
    from sqlalchemy.engine import make_url

    parsed = make_url(url)
    if parsed.get_backend_name() != "postgresql":
        raise ConfigError(f"not a PostgreSQL URL: {parsed.render_as_string(hide_password=True)}")
    env = dict(os.environ)
    if parsed.password:
        env["PGPASSWORD"] = str(parsed.password)
    return parsed.set(drivername="postgresql", password=None).render_as_string(hide_password=False), env


def _tool(name: str) -> str:
    path = shutil.which(name)
    if path is None:
        raise ConfigError(f"{name} is not on PATH: install PostgreSQL's client programs ({PG_CLIENT})")
    return path


def _major(tool: str) -> int:
    text = subprocess.run([tool, "--version"], capture_output=True, text=True).stdout
    found = re.search(r"\)\s*(\d+)", text) or re.search(r"(\d+)", text)
    return int(found.group(1)) if found else 0


def _failed(what: str, done: subprocess.CompletedProcess) -> ConfigError:
    lines = [line.strip() for line in done.stderr.splitlines() if line.strip()]
    reason = next((line for line in lines if "error" in line.lower()), lines[0] if lines else "")
    return ConfigError(f"{what} failed (exit code {done.returncode}): {reason}")


def _counts(connection) -> tuple[int, int]:
    from sqlalchemy import text

    return tuple(int(connection.execute(text(f"SELECT count(*) FROM {table}")).scalar())
                 for table in ("participants", "placements"))


# backing up ---------------------------------------------------------------------------------------------------
def backup(database: str, out: Path | str) -> Copied:
    """Write a consistent copy of ``database`` (a SQLAlchemy URL) to ``out``, atomically."""
    out = Path(out)
    if is_sqlite(database):
        return _backup_sqlite(sqlite_path(database), out)
    return _backup_postgres(database, out)


def _backup_sqlite(path: Path, out: Path) -> Copied:
    if not path.is_file():
        raise ConfigError(f"no database at {path}; give the run_dir or database the server used")
    if out.resolve() == path.resolve():
        raise ConfigError("--out is the database itself; give another file")
    source = sqlite3.connect(path, timeout=30)
    try:
        with atomic_output(out) as tmp:
            copy = sqlite3.connect(tmp)
            try:
                source.backup(copy)  # every page in one step: one read transaction, one moment
                copy.execute("PRAGMA journal_mode=DELETE")  # one self-contained file, no -wal beside it
                participants, placements = _sqlite_counts(copy)
            finally:
                copy.close()
    except sqlite3.DatabaseError as err:
        raise ConfigError(f"cannot copy {path}: {err}") from None
    finally:
        source.close()
    return Copied("sqlite", participants, placements)


def _sqlite_counts(connection: sqlite3.Connection) -> tuple[int, int]:
    try:
        return tuple(connection.execute(f"SELECT count(*) FROM {t}").fetchone()[0]
                     for t in ("participants", "placements"))
    except sqlite3.OperationalError:
        raise ConfigError("the database holds no study (no participants table); give the run_dir or database "
                          "the server used") from None


def _backup_postgres(database: str, out: Path) -> Copied:
    from sqlalchemy import create_engine, text
    from sqlalchemy.exc import SQLAlchemyError

    from overhang_framework.experiment.store import database_reason

    pg_dump = _tool("pg_dump")
    address, env = libpq(database)
    engine = create_engine(database)
    try:
        # one REPEATABLE READ transaction: its snapshot is what the counts read and what pg_dump dumps
        with engine.connect().execution_options(isolation_level="REPEATABLE READ") as connection:
            server = int(connection.execute(text("SHOW server_version_num")).scalar()) // 10000
            client = _major(pg_dump)
            if client < server:
                raise ConfigError(f"pg_dump is version {client} but the server is PostgreSQL {server}: install "
                                  f"the client programs of {server} or later (Debian: apt-get install "
                                  f"postgresql-client-{server})")
            snapshot = connection.execute(text("SELECT pg_export_snapshot()")).scalar()
            try:
                participants, placements = _counts(connection)
            except SQLAlchemyError:
                raise ConfigError("the database holds no study (no participants table); give the database "
                                  "the server used") from None
            with atomic_output(out) as tmp:
                done = subprocess.run([pg_dump, "--format=custom", f"--snapshot={snapshot}", f"--file={tmp}",
                                       f"--dbname={address}"], env=env, capture_output=True, text=True)
                if done.returncode != 0:
                    raise _failed("pg_dump", done)
            connection.rollback()
    except SQLAlchemyError as err:
        raise ConfigError(f"cannot reach the database: {database_reason(err)}") from None
    finally:
        engine.dispose()
    return Copied("postgresql", participants, placements)


# restoring ----------------------------------------------------------------------------------------------------
def backup_kind(path: Path | str) -> str:
    """``sqlite`` or ``postgresql``: what made the backup at ``path``."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"no backup at {path}")
    with open(path, "rb") as fh:
        head = fh.read(len(SQLITE_MAGIC))
    if head.startswith(SQLITE_MAGIC):
        return "sqlite"
    if head.startswith(PG_DUMP_MAGIC):
        return "postgresql"
    raise ConfigError(f"{path} is neither a SQLite database nor a pg_dump archive (custom format); give a file "
                      "that python -m overhang_framework.experiment backup wrote")


def restore(backup_file: Path | str, database: str) -> Copied:
    """Restore ``backup_file`` into the empty ``database`` (a SQLAlchemy URL of the same kind)."""
    from overhang_framework.experiment.store import Store

    kind = backup_kind(backup_file)
    target = "sqlite" if is_sqlite(database) else "postgresql"
    if kind != target:
        wanted = "database=sqlite:///PATH or a run_dir" if kind == "sqlite" else "database=postgresql+psycopg://..."
        raise ConfigError(f"{backup_file} is a {kind} backup and the database is {target}: restore it into a "
                          f"{kind} database ({wanted})")
    if kind == "sqlite":
        _restore_sqlite(Path(backup_file), sqlite_path(database))
    else:
        _restore_postgres(Path(backup_file), database)
    store = Store(database)  # checks the columns this version stores
    try:
        counts = store.count()
    finally:
        store.close()
    return Copied(kind, counts["participants"], counts["placements"])


def _restore_sqlite(backup_file: Path, path: Path) -> None:
    if path.exists():
        raise ConfigError(f"{path} exists; restore into a new file (give another run_dir or database=sqlite:///PATH)")
    source = sqlite3.connect(f"file:{backup_file}?mode=ro", uri=True)
    try:
        with atomic_output(path) as tmp:
            copy = sqlite3.connect(tmp)
            try:
                source.backup(copy)
                _sqlite_counts(copy)
            finally:
                copy.close()
    finally:
        source.close()


def _restore_postgres(backup_file: Path, database: str) -> None:
    from sqlalchemy import create_engine, inspect
    from sqlalchemy.exc import SQLAlchemyError

    from overhang_framework.experiment.store import Base, database_reason

    pg_restore = _tool("pg_restore")
    address, env = libpq(database)
    engine = create_engine(database)
    try:
        held = sorted(set(inspect(engine).get_table_names()) & set(Base.metadata.tables))
    except SQLAlchemyError as err:
        raise ConfigError(f"cannot reach the database: {database_reason(err)}") from None
    finally:
        engine.dispose()
    if held:
        raise ConfigError(f"the database already holds a study (tables {', '.join(held)}); restore into an empty "
                          "database (createdb -O ROLE NAME, then database=postgresql+psycopg://.../NAME)")
    done = subprocess.run([pg_restore, "--no-owner", "--no-privileges", "--single-transaction", "--exit-on-error",
                           f"--dbname={address}", str(backup_file)], env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise _failed("pg_restore", done)


def describe(copied: Copied) -> str:
    from overhang_framework.behaviour.log import count_noun

    return f"{count_noun(copied.participants, 'participant')} and {count_noun(copied.placements, 'placement')}"


def check_backup_target(out: Optional[str]) -> Path:
    from overhang_framework.preflight import check_writable

    path = Path(out).absolute()
    if path.is_dir():
        raise ConfigError(f"--out {out} is a folder; give the backup file's path, e.g. {Path(out) / 'study.backup'}")
    check_writable(path.parent, "--out FILE")
    return path

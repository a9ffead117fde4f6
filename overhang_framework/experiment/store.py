"""The experiment's storage: participants and their placements, in any database SQLAlchemy 2 speaks.

Five tables. ``study`` is one row: the settings the study runs with (what
participants see and how they are scored, :mod:`~overhang_framework.experiment.provenance`),
their hashes, the framework's version and commit, the address participants
open, the recorded changes of any of these, and how many participants withdrew or
declined.
``participants`` holds who took part (the recruitment
platform's ids, a hash of the session token, the condition, the order of the
main trials, when and to which version of the consent text they agreed, when
they were screened out or finished, and their bonus).
``placements`` holds one row per placement, keyed by participant, phase,
trial, attempt and step, with the version, commit and settings it was made
under: a unique key, so a retried request can never store a
placement twice, and two different requests for the same step cannot both be
stored. Each row keeps the response that was sent for it, so a retry gets the
same answer. ``clocks`` holds, under the same key, when the server first
handed each step out: the start of that step's decision time, which a reload
of the page cannot move. ``newcomers`` is one row that every new participant's
transaction updates first, so that server processes assigning conditions at the
same moment take turns (:meth:`Store.add_newcomer`).

Where a participant is (which trial, which step, which tower) is derived from
their placements, never stored apart from them.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import fcntl
import hashlib
import hmac
import json
import secrets
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Optional, Sequence

from sqlalchemy import (JSON, Boolean, DateTime, Float, ForeignKey, Integer, String, UniqueConstraint, create_engine,
                        delete, event, func, select, update)
from sqlalchemy.exc import IntegrityError, SQLAlchemyError
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, sessionmaker


#: The PostgreSQL advisory lock key a serving server holds (:meth:`Store.serving`): "overhang" in ASCII, as a number.
STUDY_LOCK = int.from_bytes(b"overhang", "big") & 0x7FFFFFFFFFFFFFFF


class Base(DeclarativeBase):
    pass


def _now() -> dt.datetime:
    return dt.datetime.now(dt.timezone.utc)


class Participant(Base):
    __tablename__ = "participants"

    id: Mapped[str] = mapped_column(String(200), primary_key=True)
    study_id: Mapped[Optional[str]] = mapped_column(String(200))
    session_id: Mapped[Optional[str]] = mapped_column(String(200))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True, index=True)
    condition: Mapped[str] = mapped_column(String(100))
    time_limit: Mapped[Optional[float]] = mapped_column(Float)  # seconds per placement in the condition, or null
    order: Mapped[list] = mapped_column(JSON)
    created_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=_now)
    completed_at: Mapped[Optional[dt.datetime]] = mapped_column(DateTime(timezone=True))
    screened_out_at: Mapped[Optional[dt.datetime]] = mapped_column(DateTime(timezone=True))
    tokens_issued: Mapped[int] = mapped_column(Integer, default=1)
    total_reward: Mapped[Optional[float]] = mapped_column(Float)
    bonus: Mapped[Optional[float]] = mapped_column(Float)
    consent_version: Mapped[Optional[str]] = mapped_column(String(100))
    consented_at: Mapped[Optional[dt.datetime]] = mapped_column(DateTime(timezone=True))
    # human, or simulated: a pilot's participant (POST /api/sessions with "simulated": true), whatever the study
    source: Mapped[str] = mapped_column(String(20), default="human")


class Study(Base):
    """The study's one row (id 1): its settings and where its records come from (module docstring)."""

    __tablename__ = "study"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    settings: Mapped[dict] = mapped_column(JSON)
    settings_hash: Mapped[str] = mapped_column(String(64))
    tasks_hash: Mapped[str] = mapped_column(String(64))
    framework_version: Mapped[str] = mapped_column(String(50))
    commit: Mapped[Optional[str]] = mapped_column(String(60))
    public_url: Mapped[Optional[str]] = mapped_column(String(500))  # given as public_url=, or null
    address: Mapped[str] = mapped_column(String(500))  # http://host:port the server last listened on
    started_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=_now)
    history: Mapped[list] = mapped_column(JSON, default=list)  # {"at", "what", "changes"}, oldest first
    withdrawn: Mapped[int] = mapped_column(Integer, default=0)
    declined: Mapped[int] = mapped_column(Integer, default=0)  # sessions deleted when consent was refused
    # keyed hashes of the withdrawn participants' ids (HMAC-SHA-256 under ``salt``, a random key of this study):
    # enough to refuse their return, not to tell who they were without the database
    salt: Mapped[str] = mapped_column(String(64))
    withdrawn_keys: Mapped[list] = mapped_column(JSON, default=list)


class PlayedSettings(Base):
    """Settings some placements were played under that are not the study's own: the study's settings with a
    participant's time limit kept from before an allowed change (:func:`overhang_framework.experiment.api.create_app`).
    Keyed by their hash, so every ``settings_hash`` a record carries resolves to its settings."""

    __tablename__ = "played_settings"

    settings_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    settings: Mapped[dict] = mapped_column(JSON)


class Newcomers(Base):
    """One row (id 1) counting the participants assigned a condition; updating it first serialises the
    assignments of every server process (a row lock in PostgreSQL, the write lock in SQLite)."""

    __tablename__ = "newcomers"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    assigned: Mapped[int] = mapped_column(Integer, default=0)


class StepKey:
    """The columns that name one step of one participant: participant, phase, trial, attempt, step."""

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    participant_id: Mapped[str] = mapped_column(ForeignKey("participants.id"), index=True)
    phase: Mapped[str] = mapped_column(String(20))
    trial: Mapped[int] = mapped_column(Integer)
    attempt: Mapped[int] = mapped_column(Integer)
    step: Mapped[int] = mapped_column(Integer)


class Placement(StepKey, Base):
    __tablename__ = "placements"
    __table_args__ = (UniqueConstraint("participant_id", "phase", "trial", "attempt", "step", name="one_per_step"),)

    task_id: Mapped[str] = mapped_column(String(100))
    sequence: Mapped[list] = mapped_column(JSON)
    width: Mapped[float] = mapped_column(Float)
    x: Mapped[Optional[float]] = mapped_column(Float)
    layer: Mapped[Optional[int]] = mapped_column(Integer)
    timed_out: Mapped[bool] = mapped_column(Boolean)
    decision_time: Mapped[float] = mapped_column(Float)
    server_time: Mapped[Optional[float]] = mapped_column(Float)
    late_action: Mapped[Optional[list]] = mapped_column(JSON)
    trajectory: Mapped[Optional[list]] = mapped_column(JSON)
    dwell: Mapped[Optional[list]] = mapped_column(JSON)
    tower_before: Mapped[list] = mapped_column(JSON)
    stable: Mapped[Optional[bool]] = mapped_column(Boolean)
    overhang: Mapped[Optional[float]] = mapped_column(Float)
    reward: Mapped[Optional[float]] = mapped_column(Float)
    trial_over: Mapped[bool] = mapped_column(Boolean)
    passed: Mapped[Optional[bool]] = mapped_column(Boolean)
    framework_version: Mapped[Optional[str]] = mapped_column(String(50))
    commit: Mapped[Optional[str]] = mapped_column(String(60))
    settings_hash: Mapped[Optional[str]] = mapped_column(String(64))
    tasks_hash: Mapped[Optional[str]] = mapped_column(String(64))
    request_hash: Mapped[str] = mapped_column(String(64))
    response: Mapped[dict] = mapped_column(JSON)
    received_at: Mapped[dt.datetime] = mapped_column(DateTime(timezone=True), default=_now)


class Clock(StepKey, Base):
    """When the server first handed a step out (seconds since the epoch, the server's clock)."""

    __tablename__ = "clocks"
    __table_args__ = (UniqueConstraint("participant_id", "phase", "trial", "attempt", "step", name="one_clock_per_step"),)

    issued_at: Mapped[float] = mapped_column(Float)


def _withdrawn_key(salt: str, pid: str) -> str:
    return hmac.new(salt.encode(), pid.encode(), hashlib.sha256).hexdigest()


def utc_iso(when: Optional[dt.datetime]) -> Optional[str]:
    """``when`` in ISO 8601 with its UTC offset (SQLite gives back naive times, stored in UTC), or None."""
    if when is None:
        return None
    return (when if when.tzinfo is not None else when.replace(tzinfo=dt.timezone.utc)).isoformat()


def token_hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def request_hash(body: Any) -> str:
    """A digest of a request body, independent of key order."""
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


#: The columns of :meth:`Store.steps`.
STEP_COLUMNS = ("phase", "trial", "attempt", "step", "width", "x", "layer", "timed_out", "reward", "trial_over",
                "passed", "request_hash")


class Conflict(Exception):
    """A placement for a step that already holds a different one."""


class SettingsChanged(Exception):
    """A server started on a study with settings other than those the study runs with."""

    def __init__(self, changes: list[str]):
        super().__init__("; ".join(changes))
        self.changes = changes


@dataclass
class Stored:
    """A placement row as plain data."""

    participant: str
    phase: str
    trial: int
    attempt: int
    step: int
    row: dict


class Store:
    """Participants and placements in the database at ``url`` (any SQLAlchemy URL); tables are created when
    missing."""

    def __init__(self, url: str):
        kwargs: dict = {}
        if url.startswith("sqlite"):
            kwargs["connect_args"] = {"check_same_thread": False, "timeout": 30}
        self.url = url
        self.engine = create_engine(url, **kwargs)
        if url.startswith("sqlite"):
            event.listen(self.engine, "connect", _sqlite_pragmas)
        Base.metadata.create_all(self.engine)
        _check_columns(self.engine)
        self._session = sessionmaker(self.engine, expire_on_commit=False)
        with self._session() as s:
            if s.get(Newcomers, 1) is None:
                s.add(Newcomers(id=1, assigned=0))
                try:
                    s.commit()
                except IntegrityError:  # another server process made it first
                    s.rollback()

    def close(self) -> None:
        if self.url.startswith("sqlite"):
            # copy what the write-ahead log holds into the database file, without waiting for other readers
            # or writers: a copy of the file alone then holds what was committed
            try:
                with self.engine.connect() as connection:
                    connection.exec_driver_sql("PRAGMA wal_checkpoint(PASSIVE)")
            except Exception:  # noqa: BLE001 - a checkpoint is a courtesy; SQLite makes one later anyway
                pass
        self.engine.dispose()

    @contextlib.contextmanager
    def serving(self, busy: str) -> Iterator[None]:
        """Hold the study for one server (all its processes) while the block runs; a second server on this
        database, from any run_dir or machine, is refused with :class:`~overhang_framework.errors.ConfigError`
        ``busy``. PostgreSQL: a session advisory lock on a connection of its own (released if the server dies);
        SQLite: a lock on a file beside the database."""
        from overhang_framework.errors import ConfigError

        if self.url.startswith("sqlite"):
            path = self.engine.url.database
            if not path or path == ":memory:":
                yield
                return
            with open(f"{path}.serving", "a") as fh:
                try:
                    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    raise ConfigError(busy) from None
                try:
                    yield
                finally:
                    fcntl.flock(fh, fcntl.LOCK_UN)
            return
        from sqlalchemy import text

        with self.engine.connect() as connection:
            held = connection.execute(text("SELECT pg_try_advisory_lock(:key)"), {"key": STUDY_LOCK}).scalar()
            connection.commit()
            if not held:
                raise ConfigError(busy)
            try:
                yield
            finally:
                # the lock goes with its connection anyway: a connection lost meanwhile (a restart of PostgreSQL)
                # must not turn a clean stop into an error
                with contextlib.suppress(SQLAlchemyError):
                    connection.execute(text("SELECT pg_advisory_unlock(:key)"), {"key": STUDY_LOCK})
                    connection.commit()

    def ping(self) -> Optional[str]:
        """None when the database answers a trivial query; else why not, in one line."""
        from sqlalchemy import text
        from sqlalchemy.exc import SQLAlchemyError

        try:
            with self.engine.connect() as connection:
                connection.execute(text("SELECT 1"))
        except SQLAlchemyError as err:
            return database_reason(err)
        return None

    def keep_settings(self, settings_hash: str, settings: dict) -> None:
        """Keep ``settings`` under ``settings_hash`` (:class:`PlayedSettings`), once."""
        with self._session() as s:
            if s.get(PlayedSettings, settings_hash) is None:
                s.add(PlayedSettings(settings_hash=settings_hash, settings=settings))
                try:
                    s.commit()
                except IntegrityError:  # another server process kept them first
                    s.rollback()

    def played_settings(self) -> dict[str, dict]:
        """Every :class:`PlayedSettings`, by hash."""
        with self._session() as s:
            return {r.settings_hash: r.settings for r in s.scalars(select(PlayedSettings))}

    # participants -------------------------------------------------------------------------------------------
    def participant(self, pid: str) -> Optional[Participant]:
        with self._session() as s:
            return s.get(Participant, pid)

    def by_token(self, token: str) -> Optional[Participant]:
        with self._session() as s:
            return s.scalars(select(Participant).where(Participant.token_hash == token_hash(token))).first()

    def add_newcomer(self, conditions: Sequence[str], make: Callable[[dict[str, int]], Participant],
                     source: str = "human") -> Optional[Participant]:
        """Store the participant ``make`` builds from the number of participants of ``source`` (human or simulated:
        a pilot's participants are balanced among themselves, and never unbalance the people) in each of
        ``conditions``; None when one with that id was stored first.

        The counts are read and the participant stored in one transaction that first updates the
        ``newcomers`` row: a second server process assigning a newcomer at the same moment waits
        for this one to commit, then counts this participant too, so the conditions stay balanced.
        """
        with self._session() as s:
            s.execute(update(Newcomers).where(Newcomers.id == 1).values(assigned=Newcomers.assigned + 1))
            participant = make(_condition_counts(s, conditions, source))
            s.add(participant)
            try:
                s.commit()
            except IntegrityError:
                s.rollback()
                return None
        return participant

    def participants(self) -> list[Participant]:
        with self._session() as s:
            return list(s.scalars(select(Participant).order_by(Participant.created_at, Participant.id)))

    def set_token(self, pid: str, token: str) -> Participant:
        """Give a participant a new session token; the old one stops working."""
        with self._session() as s:
            p = s.get(Participant, pid, with_for_update=True)
            p.token_hash = token_hash(token)
            p.tokens_issued = (p.tokens_issued or 1) + 1
            s.commit()
            return p

    def screen_out(self, pid: str) -> Participant:
        """Record that a participant was screened out (once: a second call keeps the first time)."""
        with self._session() as s:
            p = s.get(Participant, pid, with_for_update=True)
            if p.screened_out_at is None:
                p.screened_out_at = _now()
                s.commit()
            return p

    # clocks -------------------------------------------------------------------------------------------------
    def clock(self, pid: str, phase: str, trial: int, attempt: int, step: int) -> Optional[float]:
        """When the step was first handed out, or None when it has not been."""
        with self._session() as s:
            return s.scalar(select(Clock.issued_at).where(
                Clock.participant_id == pid, Clock.phase == phase, Clock.trial == trial, Clock.attempt == attempt,
                Clock.step == step))

    def start_clock(self, pid: str, phase: str, trial: int, attempt: int, step: int, now: float) -> float:
        """Start the step's clock at ``now`` unless it has started; when it started."""
        with self._session() as s:
            s.add(Clock(participant_id=pid, phase=phase, trial=trial, attempt=attempt, step=step, issued_at=now))
            try:
                s.commit()
                return now
            except IntegrityError:
                s.rollback()
        return self.clock(pid, phase, trial, attempt, step)

    def complete(self, pid: str, total_reward: float, bonus: float) -> Participant:
        """Mark a participant complete (once: a second call keeps the first record)."""
        with self._session() as s:
            p = s.get(Participant, pid, with_for_update=True)
            if p.completed_at is None:
                p.completed_at, p.total_reward, p.bonus = _now(), total_reward, bonus
                s.commit()
            return p

    def consent(self, pid: str, version: str) -> Participant:
        """Record that a participant agreed to version ``version`` of the consent text (once: a second call
        keeps the first record)."""
        with self._session() as s:
            p = s.get(Participant, pid, with_for_update=True)
            if p.consented_at is None:
                p.consented_at, p.consent_version = _now(), version
                s.commit()
            return p

    def decline(self, pid: str) -> bool:
        """Delete the session of a participant who did not agree to take part (nothing else is stored of them
        before consent) and count one; False when they had agreed already (then only withdrawal deletes)."""
        with self._session() as s:
            p = s.get(Participant, pid, with_for_update=True)
            if p is None:
                return True
            if p.consented_at is not None:
                return False
            _delete_participant(s, p)
            s.execute(update(Study).where(Study.id == 1).values(declined=Study.declined + 1))
            s.commit()
        return True

    def withdraw(self, pid: str) -> Optional[dict[str, int]]:
        """Delete a participant and everything stored of them, and count one withdrawal; how many rows of each
        kind were deleted, or None when there is no such participant."""
        with self._session() as s:
            p = s.get(Participant, pid, with_for_update=True)
            if p is None:
                return None
            deleted = _delete_participant(s, p)
            study = s.get(Study, 1, with_for_update=True)
            if study is not None:
                study.withdrawn = (study.withdrawn or 0) + 1
                study.withdrawn_keys = [*(study.withdrawn_keys or []), _withdrawn_key(study.salt, pid)]
            s.commit()
        return deleted

    def withdrew(self, pid: str) -> bool:
        """Whether a participant with id ``pid`` withdrew from this study (and was deleted)."""
        study = self.study()
        return study is not None and _withdrawn_key(study.salt, pid) in (study.withdrawn_keys or [])

    # the study ----------------------------------------------------------------------------------------------
    def study(self) -> Optional[Study]:
        with self._session() as s:
            return s.get(Study, 1)

    def begin_study(self, settings: dict, hashes: dict, versions: dict, address: str, public_url: Optional[str],
                    allow_change: bool = False) -> Study:
        """The study's row: made from these when the study is new; otherwise checked against them.

        Settings other than the stored ones raise :class:`SettingsChanged` listing the differences, unless
        ``allow_change``: then they replace the stored ones and the change is recorded in ``history``, as is a
        change of the framework's version or commit, or of the address. A ``public_url`` of None keeps the one
        stored.
        """
        from overhang_framework.experiment.provenance import differences

        with self._session() as s:
            row = s.get(Study, 1, with_for_update=True)
            if row is None:
                s.add(Study(id=1, settings=settings, history=[], withdrawn=0, declined=0, address=address,
                            public_url=public_url, salt=secrets.token_hex(32), withdrawn_keys=[], **hashes,
                            **versions))
                try:
                    s.commit()
                except IntegrityError:  # another server process made it first: check against theirs
                    s.rollback()
                    return self.begin_study(settings, hashes, versions, address, public_url, allow_change)
                return s.get(Study, 1)
            events = []
            changed = differences(row.settings, settings)
            if changed:
                if not allow_change:
                    raise SettingsChanged(changed)
                events.append({"what": "settings", "changes": changed, "settings_hash": hashes["settings_hash"],
                               "previous": {"settings_hash": row.settings_hash, "settings": row.settings}})
                row.settings = settings
                for k, v in hashes.items():
                    setattr(row, k, v)
            moved = differences({k: getattr(row, k) for k in versions}, versions)
            if moved:
                events.append({"what": "version", "changes": moved})
                for k, v in versions.items():
                    setattr(row, k, v)
            where = {"address": address, **({"public_url": public_url} if public_url is not None else {})}
            relocated = differences({k: getattr(row, k) for k in where}, where)
            if relocated:
                events.append({"what": "address", "changes": relocated})
                for k, v in where.items():
                    setattr(row, k, v)
            if events:
                at = _now().isoformat()
                row.history = [*(row.history or []), *({"at": at, **e} for e in events)]
                s.commit()
            return row

    # placements ---------------------------------------------------------------------------------------------
    def placements(self, pid: Optional[str] = None, phase: Optional[str] = None) -> list[Placement]:
        """Placements in the order they were made (of one participant and phase when given)."""
        q = select(Placement)
        if pid is not None:
            q = q.where(Placement.participant_id == pid)
        if phase is not None:
            q = q.where(Placement.phase == phase)
        q = q.order_by(Placement.participant_id, Placement.phase.desc(), Placement.trial, Placement.attempt,
                       Placement.step)
        with self._session() as s:
            return list(s.scalars(q))

    def steps(self, pid: str) -> list:
        """A participant's placements without their large fields (trajectory, dwell, the stored reply): what
        working out their position needs, as rows with attribute access."""
        cols = [getattr(Placement, c) for c in STEP_COLUMNS]
        with self._session() as s:
            return list(s.execute(select(*cols).where(Placement.participant_id == pid)))

    def find(self, pid: str, phase: str, trial: int, attempt: int, step: int) -> Optional[Placement]:
        with self._session() as s:
            return s.scalars(select(Placement).where(
                Placement.participant_id == pid, Placement.phase == phase, Placement.trial == trial,
                Placement.attempt == attempt, Placement.step == step)).first()

    def add_placement(self, placement: Placement) -> Placement:
        """Store ``placement``; when its step is already stored, the stored one if it came from the same
        request, else :class:`Conflict`."""
        with self._session() as s:
            s.add(placement)
            try:
                s.commit()
                return placement
            except IntegrityError:
                s.rollback()
        stored = self.find(placement.participant_id, placement.phase, placement.trial, placement.attempt,
                           placement.step)
        if stored is None:
            raise Conflict(f"{placement.phase} trial {placement.trial} step {placement.step} could not be stored")
        if stored.request_hash != placement.request_hash:
            raise Conflict(f"{placement.phase} trial {placement.trial} step {placement.step} is already stored "
                           "with a different placement")
        return stored

    def count(self) -> dict[str, int]:
        with self._session() as s:
            return {"participants": s.scalar(select(func.count()).select_from(Participant)),
                    "placements": s.scalar(select(func.count()).select_from(Placement))}


def _delete_participant(session, participant: Participant) -> dict[str, int]:
    """Delete ``participant`` with their placements and step clocks in ``session``; how many of each went."""
    deleted = {kind: session.execute(delete(model).where(model.participant_id == participant.id)).rowcount
               for kind, model in (("placements", Placement), ("clocks", Clock))}
    session.delete(participant)
    return deleted


def database_reason(err: Exception) -> str:
    """A database error in one line: the driver's own first line, without SQLAlchemy's background link."""
    text = str(getattr(err, "orig", None) or err).strip()
    return text.splitlines()[0] if text else type(err).__name__


def _condition_counts(session, conditions: Sequence[str], source: str = "human") -> dict[str, int]:
    rows = session.execute(select(Participant.condition, func.count())
                           .where(func.coalesce(Participant.source, "human") == source)
                           .group_by(Participant.condition)).all()
    counts = {c: 0 for c in conditions}
    for condition, n in rows:
        if condition in counts:
            counts[condition] = int(n)
    return counts


def _check_columns(engine) -> None:
    """Stop with one line when the database's tables lack columns this version stores."""
    from sqlalchemy import inspect

    from overhang_framework.errors import ConfigError

    inspector = inspect(engine)
    for table in Base.metadata.sorted_tables:
        have = {c["name"] for c in inspector.get_columns(table.name)}
        missing = [c.name for c in table.columns if c.name not in have]
        if missing:
            raise ConfigError(f"the database's table {table.name} lacks the column(s) {', '.join(missing)}: it was "
                              "made by an earlier version of the experiment; finish that study with the version "
                              "that started it, or give a new database")


def _sqlite_pragmas(connection, _record) -> None:
    cursor = connection.cursor()
    cursor.execute("PRAGMA busy_timeout=30000")
    cursor.execute("PRAGMA journal_mode=WAL")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.close()


def rows_as_dicts(rows: Iterable[Placement]) -> list[dict]:
    cols = [c.name for c in Placement.__table__.columns]
    return [{c: getattr(r, c) for c in cols} for r in rows]

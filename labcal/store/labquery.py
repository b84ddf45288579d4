"""What the lab knows, read from the lab database wherever it is — the one place the commands' reads
go through (runs, a run's log, certificates, device estimates, approvers, settle pools).

A SQLite lab database is the bench's journal itself: read there. A PostgreSQL lab database is the
lab's record: read there, so that every bench sees every bench's runs, certificates, estimates and
approvers, numbered and named alike. A bench that cannot reach it works from what it last had, its
own journal, and says so in one line naming how old that is (when the journal last had everything
sent to the lab: ``sync_targets``); a run's lab number, where the lab has given it one, is kept in
the journal (``sync_runs``), so a run keeps its number offline, and a run the lab has not seen yet
is shown by its provisional label (`run_label`).

Run numbers are the lab's (`labcal.store.sync.lab_number`): given once, by the lab database, when a
run first reaches it, gap-free and the same on every bench, page and API answer. The journal's own
row ids are never shown as a run's number where the lab is a server.

Every query is SQLAlchemy Core over `labcal.store.schema`'s tables, on either backend alike.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

from labcal.config.lab import ServerDatabase
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labdb
from labcal.store.journal import EventRow, db_path
from labcal.store.labdb import lab_database
from labcal.store.sync import target_of

if TYPE_CHECKING:
    import sqlalchemy
    from sqlalchemy import pool
    from sqlalchemy.engine import Connection, Engine

    from labcal.store import schema
else:
    pool = lazy("sqlalchemy.pool")  # start-up without sqlalchemy
    schema = lazy("labcal.store.schema")  # start-up without sqlalchemy
    sqlalchemy = lazy("sqlalchemy")  # start-up without sqlalchemy

T = TypeVar("T")
PROVISIONAL = 8  # hex digits of a run's uuid in its provisional label


def run_label(number: int | None, uuid: str | None) -> str:
    """A run as people name it: its lab number, or until the lab has given it one (a bench that has
    not reached the lab since the run began) its uuid's first digits, marked provisional."""
    if number is not None:
        return str(number)
    return f"{(uuid or '?')[:PROVISIONAL]} (provisional)"


@dataclass(frozen=True)
class Source:
    """Where a read was made: ``shown`` the lab database (or the journal standing in for it), and
    ``stale`` the one line saying the lab could not be reached and how old the bench's view is
    (None: read from the lab itself)."""

    shown: str
    stale: str | None = None
    journal: Path | None = None  # this bench's journal (a server's outbox; the lab file itself)
    target: str | None = None  # the lab server, as the journal's sync tables name it


def _age(utc: str | None) -> str:
    if utc is None:
        return "it has never had everything sent to the lab"
    then = datetime.fromisoformat(utc)
    seconds = max(0, int((datetime.now(UTC) - then).total_seconds()))
    for unit, size in (("day", 86400), ("h", 3600), ("min", 60)):
        if seconds >= size:
            n = seconds // size
            plural = "s" if unit == "day" and n > 1 else ""
            return f"last in step with the lab {n} {unit}{plural} ago ({utc[:19]}Z)"
    return f"last in step with the lab {seconds} s ago ({utc[:19]}Z)"


def _sqlite_engine(path: Path) -> Engine:
    labdb.connect(path).close()  # at this labcal's schema (refused in one line if behind or ahead)
    return sqlalchemy.create_engine(
        f"sqlite:///{path}", poolclass=pool.NullPool, connect_args={"timeout": 10.0}
    )


@contextmanager
def _sqlite(path: Path) -> Iterator[Connection]:
    engine = _sqlite_engine(path)
    try:
        with engine.connect() as conn:
            yield conn
    finally:
        engine.dispose()


@contextmanager
def reading(db: str | Path | None, *, must_exist: bool = True) -> Iterator[tuple[Connection | None, Source]]:
    """A connection to the lab database for reads, and where it is. On a server that cannot be
    reached: this bench's journal instead (None when it has none), with the line saying so."""
    where = lab_database(db)
    if isinstance(where, Path):
        if not where.is_file():
            if must_exist:
                raise LabcalError(f"{where}: no lab database here; {{0}} or $LABCAL_DB names the lab's "
                                  "database", "db")
            yield None, Source(str(where))
            return
        with _sqlite(where) as conn:
            yield conn, Source(str(where), journal=where)
        return
    journal, target = db_path(db), target_of(where)
    try:
        engine = labdb.open_server(where)
    except labdb.Unreachable as exc:
        why = str(exc).partition(" (")[2].partition("); ")[0] or str(exc)
        line = (f"{where}: cannot reach the lab database ({why}); working from this bench's journal "
                f"{journal}: ")
        if not journal.is_file():
            yield None, Source(str(journal), line + "which does not exist yet", None, target)
            return
        with _sqlite(journal) as conn:
            yield conn, Source(str(journal), line + _age(_synced(conn, target)), journal, target)
        return
    try:
        with engine.connect() as conn:
            yield conn, Source(str(where), None, journal if journal.is_file() else None, target)
    finally:
        engine.dispose()


def _synced(conn: Connection, target: str) -> str | None:
    return conn.execute(
        sqlalchemy.select(schema.sync_targets.c.synced_utc).where(schema.sync_targets.c.target == target)
    ).scalar()


def from_lab(db: str | Path | None, read: Callable[[Connection], T], empty: T) -> tuple[T, Source]:
    """``read`` on the lab database (or, when it cannot be reached, on this bench's journal);
    ``empty`` where there is neither."""
    with reading(db, must_exist=False) as (conn, source):
        return (empty if conn is None else read(conn)), source


# --- runs ---------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LabRun:
    """One run as the lab lists it. ``number`` is the lab's (None: not yet numbered, see
    `run_label`); ``local_id`` its row in this bench's journal (None: another bench's run)."""

    number: int | None
    uuid: str | None
    station: str | None
    serial: str | None
    plan: str
    status: str
    reason: str | None
    started_utc: str
    ended_utc: str | None
    points_ok: int
    points_failed: int
    operator: str | None
    run_dir: str
    local_id: int | None
    metadata: str | None = None  # the run's journaled metadata (JSON): its checklist, its serial's note

    @property
    def label(self) -> str:
        return run_label(self.number, self.uuid)


def _run_query() -> Any:
    """Every run with its points counted (measured, and journaled in all), in the lab's order."""
    ok = sqlalchemy.func.sum(sqlalchemy.case((schema.points.c.status == "ok", 1), else_=0))
    counts = (sqlalchemy.select(schema.points.c.run_id, sqlalchemy.func.count().label("done"), ok.label("ok"))
              .group_by(schema.points.c.run_id).subquery())
    return (
        sqlalchemy.select(
            schema.runs.c.id,
            schema.runs.c.uuid,
            schema.runs.c.station,
            schema.runs.c.instrument_serial,
            schema.runs.c.plan_name,
            schema.runs.c.status,
            schema.runs.c.reason,
            schema.runs.c.started_utc,
            schema.runs.c.ended_utc,
            sqlalchemy.func.coalesce(counts.c.ok, 0).label("ok"),
            sqlalchemy.func.coalesce(counts.c.done, 0).label("done"),
            schema.runs.c.operator,
            schema.runs.c.run_dir,
            schema.runs.c.metadata,
        )
        .outerjoin(counts, counts.c.run_id == schema.runs.c.id)
        .order_by(schema.runs.c.id)
    )


def _run_rows(conn: Connection, serial: str | None, statuses: tuple[str, ...]) -> list[Any]:
    query = _run_query()
    if serial is not None:
        query = query.where(schema.runs.c.instrument_serial == serial)
    if statuses:
        query = query.where(schema.runs.c.status.in_(statuses))
    return list(conn.execute(query))


def _numbers(conn: Connection, target: str) -> dict[int, int]:
    """This journal's runs as the lab numbered them: {journal row id: lab number}."""
    return dict(conn.execute(sqlalchemy.select(schema.sync_runs.c.run_id, schema.sync_runs.c.lab_run_id)
                             .where(schema.sync_runs.c.target == target)).all())


def _lab_run(row: Any, number: int | None, local_id: int | None) -> LabRun:
    return LabRun(number, row.uuid, row.station, row.instrument_serial, row.plan_name, row.status, row.reason,
                  row.started_utc, row.ended_utc, int(row.ok), int(row.done) - int(row.ok), row.operator,
                  row.run_dir, local_id, row.metadata)


def lab_runs(db: str | Path | None, serial: str | None = None, statuses: tuple[str, ...] = ()
             ) -> tuple[list[LabRun], Source]:
    """The lab's runs in the order the lab numbered them, then this bench's runs it has not seen yet
    (numbered None). On a server, this bench's runs carry their journal row (for their lock)."""
    with reading(db, must_exist=False) as (conn, source):
        if conn is None:
            return [], source
        if source.target is None:  # a SQLite lab database: its own rows are the lab's numbers
            return [_lab_run(r, r.id, r.id) for r in _run_rows(conn, serial, statuses)], source
        if source.stale is not None:  # the journal, standing in for the lab it cannot reach
            numbers = _numbers(conn, source.target)
            found = [_lab_run(r, numbers.get(r.id), r.id) for r in _run_rows(conn, serial, statuses)]
            return sorted(found, key=_order), source
        lab = _run_rows(conn, serial, statuses)
        local = _journal_runs(source, serial, statuses)
        mine = {r.uuid: r.id for r in local}
        found = [_lab_run(r, r.id, mine.get(r.uuid)) for r in lab]
        known = {r.uuid for r in lab}
        found += [_lab_run(r, None, r.id) for r in local if r.uuid not in known]
        return found, source


def _order(run: LabRun) -> tuple[int, int]:
    """Numbered runs in the lab's order, then those not numbered yet in the journal's."""
    return (0, run.number) if run.number is not None else (1, run.local_id or 0)


def _journal_runs(source: Source, serial: str | None, statuses: tuple[str, ...]) -> list[Any]:
    if source.journal is None:
        return []
    engine = _sqlite_engine(source.journal)
    try:
        with engine.connect() as conn:
            return _run_rows(conn, serial, statuses)
    finally:
        engine.dispose()


@dataclass(frozen=True)
class RunEvents:
    run: LabRun
    events: list[EventRow]


def _events(conn: Connection, run_id: int) -> list[EventRow]:
    rows = conn.execute(
        sqlalchemy.select(
            schema.events.c.utc,
            schema.events.c.station_time,
            schema.events.c.kind,
            schema.events.c.message,
            schema.events.c.data,
        )
        .where(schema.events.c.run_id == run_id)
        .order_by(schema.events.c.id)
    )
    return [EventRow.read(*row) for row in rows]


def run_events(db: str | Path | None, number: int | None = None, uuid: str | None = None
               ) -> tuple[RunEvents, Source]:
    """One run and its journaled events, by its lab number or (a run not numbered yet, or named by
    its folder) its uuid; one line when the lab holds no such run."""
    with reading(db) as (conn, source):
        assert conn is not None  # reading(must_exist=True) raises instead
        if source.target is not None and source.stale is not None:  # the journal, for the lab
            numbers = _numbers(conn, source.target)
            mine = {lab: own for own, lab in numbers.items()}.get(number) if number is not None else None
            row = _one(
                conn, schema.runs.c.id == mine if number is not None else schema.runs.c.uuid.like(f"{uuid}%")
            )
            found = None if row is None else _lab_run(row, numbers.get(row.id), row.id)
        else:
            row = _one(
                conn,
                schema.runs.c.id == number if number is not None else schema.runs.c.uuid.like(f"{uuid}%"),
            )
            found = None if row is None else _lab_run(row, row.id, row.id if source.target is None else None)
        if found is None and uuid and source.journal is not None and source.target is not None:
            return _journal_run(source, uuid)  # a run of this bench the lab has not seen yet
        if found is None:
            what = f"run {number}" if number is not None else f"run {uuid}"
            raise LabcalError(f"{source.shown}: no {what} there; labcal runs lists them")
        return RunEvents(found, _events(conn, row.id)), source


def _journal_run(source: Source, uuid: str) -> tuple[RunEvents, Source]:
    assert source.journal is not None
    engine = _sqlite_engine(source.journal)
    try:
        with engine.connect() as conn:
            row = _one(conn, schema.runs.c.uuid.like(f"{uuid}%"))
            if row is None:
                raise LabcalError(f"{source.shown}: no run {uuid} there nor in {source.journal}; labcal runs "
                                  "lists them")
            return RunEvents(_lab_run(row, None, row.id), _events(conn, row.id)), source
    finally:
        engine.dispose()


def _one(conn: Connection, where: Any) -> Any:
    rows = list(conn.execute(_run_query().where(where)))
    if len(rows) > 1:
        raise LabcalError(f"{len(rows)} runs match; give more of the uuid")
    return rows[0] if rows else None


def lab_number_of(journal: Path, run_id: int, db: str | Path | None = None) -> str:
    """The label of this bench's run ``run_id`` as the lab knows it (a notification, a log line):
    its lab number where the journal has heard it, else its provisional label; on a SQLite lab
    database its own id."""
    where = lab_database(db)
    try:
        with closing(sqlite3.connect(f"file:{journal}?mode=ro", uri=True, timeout=5.0)) as conn:
            if isinstance(where, Path):
                return str(run_id)
            row = conn.execute("SELECT r.uuid, s.lab_run_id FROM runs r LEFT JOIN sync_runs s "
                               "ON s.run_id = r.id AND s.target = ? WHERE r.id = ?",
                               (target_of(where), run_id)).fetchone()
    except sqlite3.Error:
        return str(run_id) if isinstance(where, Path) else "?"
    return "?" if row is None else run_label(row[1], row[0])


def is_server(db: str | Path | None) -> bool:
    return isinstance(lab_database(db), ServerDatabase)


# --- the lab's records: certificates, device estimates, approvers, settle pools -------------------
@dataclass(frozen=True)
class Rows:
    """A read of one of the lab's record tables: its rows, and where they were read."""

    rows: list[tuple]
    source: Source
    exists: bool = True  # False: no database to read (a SQLite lab file not made yet)


def records(db: str | Path | None, table: str, columns: tuple[str, ...], where: dict[str, Any] | None = None,
            order: tuple[str, ...] = (), *, must_exist: bool = True) -> Rows:
    """``columns`` of ``table``'s rows whose columns equal ``where``'s values, ordered by ``order``.
    A SQLite lab database that does not exist raises (``must_exist``) or holds no rows."""
    t = schema.METADATA.tables[table]
    query = sqlalchemy.select(*(t.c[c] for c in columns)).where(
        *(t.c[k] == v for k, v in (where or {}).items())
    )
    query = query.order_by(*(t.c[c] for c in order))
    with reading(db, must_exist=must_exist) as (conn, source):
        return Rows([] if conn is None else [tuple(r) for r in conn.execute(query)], source, conn is not None)


def distinct(db: str | Path | None, table: str, column: str) -> list[str]:
    """Every value of ``column`` in ``table``, sorted (what a refusal names as known)."""
    t = schema.METADATA.tables[table]
    with reading(db, must_exist=False) as (conn, _):
        if conn is None:
            return []
        return [
            str(v)
            for v in conn.execute(sqlalchemy.select(t.c[column]).distinct().order_by(t.c[column])).scalars()
        ]


def journal_run(db: str | Path | None, number: int) -> int:
    """This bench's journal row of the lab's run ``number`` (a run measured here: its readings and
    folder are this bench's to export and report). On a SQLite lab database the number is the row;
    on a server the journal's ``sync_runs`` says which, and a run of another bench is one line
    naming that bench."""
    where = lab_database(db)
    if isinstance(where, Path):
        return number
    journal = db_path(db)
    if journal.is_file():
        with _sqlite(journal) as conn:
            found = conn.execute(
                sqlalchemy.select(schema.sync_runs.c.run_id).where(
                    schema.sync_runs.c.target == target_of(where), schema.sync_runs.c.lab_run_id == number
                )
            ).scalar()
        if found is not None:
            return int(found)
    with reading(db, must_exist=False) as (conn, source):
        station = None if conn is None or source.stale else \
            conn.execute(sqlalchemy.select(schema.runs.c.station).where(schema.runs.c.id == number)).first()
    if station is not None:
        raise LabcalError(f"run {number} was measured at {station[0] or 'another bench'}: its folder is that "
                          "bench's (run the command there)")
    raise LabcalError(f"no run {number} of this bench in {journal} nor in {where}; labcal runs lists them")

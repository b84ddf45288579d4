"""Every journaled record reaches the lab's PostgreSQL database exactly once.

With a server as the lab database, each station journals in a SQLite file of its own
(`labcal.config.lab.LabConfig.journal`): a reading is on the station's disk, committed, before the
next move, whatever the network does. `Sender.push` sends what the journal holds and the server
does not yet: runs (found by their uuid, and numbered by the lab the first time any bench sends
them: `lab_number`), their points (key: the lab's run number and the point's seq), events (key: the
lab's run number and the event's id in the journal, ``events.origin_id``), and the lab's other
records (`RECORDS`: certificates, device estimates, approvers, settle pools, each under its own key,
sent again whenever it changes: a certificate approved or re-issued under its id, a revocation, a
pool that grew). Every insert is ``ON CONFLICT DO NOTHING`` or an upsert, so sending a record twice
(the server committed, the journal's note of it did not) stores it once. The journal keeps how far
it has sent to each server (``sync_cursors``: the last rowid of points and events; ``sync_runs``:
each run's lab number and the status last sent; ``sync_sent``: each record's state last sent),
written only after the server has committed. `Sender.pull` brings the other way what the lab holds
of every bench's records, so that a bench that loses the lab works from what it last had.

During a run, `sending` runs a `Sender` on a thread of its own, which reads the journal through its
own connection (WAL: it never blocks the run's writer) twice a second, so a run never waits for the
server. An outage is said once (on the console and as a journal event of the run); the thread
retries with a growing pause (0.5 s to 10 s) and catches up when the server is back. At the end of
the run it sends what it can for a few seconds and says what is left for ``labcal sync``.
"""

from __future__ import annotations

import sqlite3
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import closing, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.config.lab import ServerDatabase, load_lab_config
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labdb
from labcal.store.chain import append_audit
from labcal.store.journal import Journal, db_path, utc_now
from labcal.store.labdb import lab_database
from labcal.store.roles import BENCH_CLOSES_RUNS

if TYPE_CHECKING:
    import sqlalchemy
    from sqlalchemy import exc as sqlalchemy_exc
    from sqlalchemy.dialects import postgresql
    from sqlalchemy.engine import Connection, Engine

    from labcal.store import lab_certificates, schema
else:
    lab_certificates = lazy("labcal.store.lab_certificates")  # start-up without scipy, numpy, pydantic, …
    # SQLAlchemy's tables only here, where a server is written: a run on a SQLite lab database (the journal
    # itself) imports neither them nor SQLAlchemy
    postgresql = lazy("sqlalchemy.dialects.postgresql")
    schema = lazy("labcal.store.schema")  # start-up without sqlalchemy
    sqlalchemy = lazy("sqlalchemy")  # start-up without sqlalchemy
    sqlalchemy_exc = lazy("sqlalchemy.exc")  # start-up without sqlalchemy

EVENT_COLUMNS = ("utc", "station_time", "kind", "message", "data", "link", "digest")
BATCH = 500  # rows per statement: a catch-up after a long outage goes in bounded transactions
POLL_S = 0.5  # how often the sender looks at the journal during a run
BACKOFF_MAX_S = 10.0
FLUSH_S = 5.0  # what the end of a run waits for the server, at most
IN_STEP_S = 60.0  # how often a sender with nothing to send notes that the journal is in step


@dataclass(frozen=True)
class Record:
    """A table of the lab's records other than runs, sent whole and again whenever it changes: its
    key, and the columns whose values change when the record does (its state, kept per lab database
    in the journal's ``sync_sent`` once the lab has committed it)."""

    table: str
    key: tuple[str, ...]
    state: tuple[str, ...]


# A certificate re-stored under its id (approved, re-issued) has a new digest; an estimate stored
# again from the same run a new storing time; an approver revoked a revocation time; a settle pool a
# new update time.
RECORDS = (
    Record("certificates", ("certificate_id",), ("sha256", "issued_utc")),
    Record("device_estimates", ("device_id", "source"), ("stored_utc",)),
    Record("approvers", ("key_id",), ("revoked_utc",)),
    Record("settle_pools", ("pool_key",), ("updated_utc",)),
)
NAMES = ("runs", "points", "events", *(r.table for r in RECORDS), "audit")
SEP = "char(31)"  # between a composite key's parts (never in a device id, run uuid or date)
UNIT = "\x1f"  # the same character, as Python writes it (`_text_of`)


def _text_of(values: tuple | list) -> str:
    """Several values as one text, as `_joined` makes it in SQLite (NULL: empty)."""
    return UNIT.join("" if v is None else str(v) for v in values)


def and_all(table: Any, columns: tuple[str, ...], values: list[str]) -> Any:
    """The SQL condition that a row's ``columns`` equal ``values`` (a key split at `UNIT`)."""
    return sqlalchemy.and_(*(table.c[c] == v for c, v in zip(columns, values, strict=True)))


def _joined(columns: tuple[str, ...]) -> str:
    """SQLite text of several columns, one value: what `sync_sent` keeps of a key or a state."""
    return f" || {SEP} || ".join(f"coalesce(CAST(t.{c} AS TEXT), '')" for c in columns)


@dataclass
class Sent:
    """What one push sent: rows offered to the server per table, rows it did not have yet, and the
    records it refused this bench's role (``refused``, with PostgreSQL's first reason: an approved
    certificate, an approver; they stay in the journal, never offered twice in one push)."""

    offered: dict[str, int] = field(default_factory=lambda: dict.fromkeys(NAMES, 0))
    stored: dict[str, int] = field(default_factory=lambda: dict.fromkeys(NAMES, 0))
    refused: dict[str, int] = field(default_factory=dict)
    why: str | None = None

    def add(self, other: Sent) -> None:
        for name in self.offered:
            self.offered[name] += other.offered[name]
            self.stored[name] += other.stored[name]
        for name, n in other.refused.items():
            self.refused[name] = self.refused.get(name, 0) + n
        self.why = self.why or other.why

    @property
    def total(self) -> int:
        return sum(self.offered.values())

    def __str__(self) -> str:
        return ", ".join(f"{self.offered[n]} {n}" for n in self.offered)


def target_of(server: ServerDatabase) -> str:
    """The name a journal's cursors give a lab database: its URL without a password."""
    return str(server)


class Sender:
    """Sends a station's journal to one lab database (see the module's docstring)."""

    def __init__(self, journal: Path, server: ServerDatabase, station: str | None = None,
                 engine: Engine | None = None):
        self.journal = journal
        self.server = server
        self.target = target_of(server)
        self.station = station or load_lab_config().station()
        self.engine = engine or labdb.server_engine(server)
        self._schema_checked = False
        self._in_step = -IN_STEP_S - 1.0  # when the journal last noted it was in step with the lab

    def close(self) -> None:
        self.engine.dispose()

    def _local(self) -> sqlite3.Connection:
        return labdb.connect(self.journal)

    def pending(self) -> dict[str, int]:
        """Records of the journal not yet sent to this lab database, per table."""
        with closing(self._local()) as db:
            marks = self._cursors(db)
            out = {"runs": len(self._runs_to_send(db))}
            for name, key in (("points", "rowid"), ("events", "id")):
                out[name] = db.execute(f"SELECT count(*) FROM {name} WHERE {key} > ?",
                                       (marks.get(name, 0),)).fetchone()[0]
            for record in RECORDS:
                out[record.table] = len(self._records_to_send(db, record, None))
            out["audit"] = db.execute("SELECT count(*) FROM audit WHERE id > ?", (marks.get("audit", 0),)
                                      ).fetchone()[0]
            return out

    def _records_to_send(self, db: sqlite3.Connection, record: Record, limit: int | None,
                         passed: frozenset[str] = frozenset()) -> list[tuple]:
        """A record table's rows whose state this lab database has not committed, but for the keys
        ``passed`` over (refused earlier in this push): (key, state, row)."""
        columns = [c.name for c in schema.METADATA.tables[record.table].columns if c.name != "id"]
        key, state = _joined(record.key), _joined(record.state)
        rows = db.execute(
            f"SELECT {key}, {state}, {', '.join('t.' + c for c in columns)} FROM {record.table} t "
            f"LEFT JOIN sync_sent s ON s.target = ? AND s.name = ? AND s.key = {key} "
            f"WHERE s.state IS NULL OR s.state != {state} ORDER BY t.rowid",
            (self.target, record.table)).fetchall()
        found = [(row[0], row[1], dict(zip(columns, row[2:], strict=True))) for row in rows
                 if row[0] not in passed]
        return found if limit is None else found[:limit]

    def _cursors(self, db: sqlite3.Connection) -> dict[str, int]:
        return dict(db.execute("SELECT name, position FROM sync_cursors WHERE target=?", (self.target,)))

    def _runs_to_send(self, db: sqlite3.Connection) -> list[tuple]:
        """Runs the server has not seen, or whose status it has not seen: (local id, state, lab id)."""
        rows = db.execute(
            "SELECT r.id, r.status, r.reason, r.ended_utc, s.sent, s.lab_run_id FROM runs r "
            "LEFT JOIN sync_runs s ON s.run_id = r.id AND s.target = ? ORDER BY r.id", (self.target,))
        return [(run_id, state, lab_id) for run_id, status, reason, ended, sent, lab_id in rows
                if (state := f"{status}|{reason or ''}|{ended or ''}") != sent]

    def push(self) -> Sent:
        """Send everything pending, in batches, each committed on the server before the journal's
        cursor moves. Raises the server's error (SQLAlchemy's) when it cannot be reached."""
        if not self._schema_checked:  # an empty database created, one behind or ahead refused
            labdb.open_server(self.server).dispose()
            self._schema_checked = True
        sent = Sent()
        passed: dict[str, set[str]] = {name: set() for name in NAMES}
        with closing(self._local()) as db:
            while True:
                step = self._push_once(db, passed)
                sent.add(step)
                if step.total == 0:
                    # everything the journal holds is in the lab: what a bench that cannot reach
                    # it later names as the age of its own view (noted at most once a minute while
                    # nothing changes: a run's sender pushes twice a second)
                    if sent.total or time.monotonic() - self._in_step > IN_STEP_S:
                        db.execute("INSERT INTO sync_targets (target, synced_utc) VALUES (?, ?) ON CONFLICT "
                                   "(target) DO UPDATE SET synced_utc=excluded.synced_utc",
                                   (self.target, _utc()))
                        self._in_step = time.monotonic()
                    return sent

    def pull(self) -> dict[str, int]:
        """The lab's records (every bench's certificates, device estimates, approvers and settle
        pools) copied into this journal where it lacks them or holds a copy the lab has since changed
        (and this bench has not: a change of its own not yet sent is never overwritten), so that a
        bench that later cannot reach the lab still works from what it last had, and a run starts
        from the lab's settle pool. Returns the rows copied per table."""
        if not self._schema_checked:
            labdb.open_server(self.server).dispose()
            self._schema_checked = True
        with closing(self._local()) as db, self.engine.connect() as server:
            pulled = {record.table: self._pull_record(db, server, record) for record in RECORDS}
            pulled["approved certificate files"] = self._pull_approved(db, server)
        return pulled

    def _pull_approved(self, db: sqlite3.Connection, server: Connection) -> int:
        """The files of certificates the lab server approved (`labcal.store.lab_certificates`) written
        into the folders of this bench's runs; how many files were written."""
        approved = set(
            server.execute(sqlalchemy.select(schema.certificate_files.c.run_uuid).distinct()).scalars()
        )
        written = 0
        for uuid, run_dir in db.execute("SELECT uuid, run_dir FROM runs WHERE status = 'complete'"):
            if uuid in approved and Path(run_dir).is_dir():
                written += len(
                    lab_certificates.write_files(Path(run_dir), lab_certificates.files_of(server, uuid))
                )
        return written

    def _pull_record(self, db: sqlite3.Connection, server: Connection, record: Record) -> int:
        table = schema.METADATA.tables[record.table]
        n = len(record.key)
        lab = {_text_of(row[:n]): _text_of(row[n:])
               for row in server.execute(sqlalchemy.select(*(table.c[c] for c in record.key + record.state)))}
        wanted = list(self._taken(db, record, lab))
        columns = [c.name for c in table.columns if c.name != "id"]
        rows: list[tuple] = []
        for part in range(0, len(wanted), BATCH):
            match = [and_all(table, record.key, k.split(UNIT)) for k in wanted[part:part + BATCH]]
            query = sqlalchemy.select(*(table.c[c] for c in columns)).where(sqlalchemy.or_(*match))
            rows += [tuple(r) for r in server.execute(query)]
        if not rows:
            return 0
        at = [columns.index(c) for c in record.key + record.state]
        keyed = [(_text_of([r[i] for i in at[:n]]), _text_of([r[i] for i in at[n:]]), r) for r in rows]
        # the journal's write lock taken, each record is judged again: another process of this bench
        # (`labcal report` re-issuing a draft, an approval) may have changed it since it was read, and
        # a change of its own not yet sent is never overwritten
        db.execute("BEGIN IMMEDIATE")
        try:
            still = self._taken(db, record, {k: v for k, v, _ in keyed})
            taken = [(k, v, r) for k, v, r in keyed if k in still]
            db.executemany(f"INSERT OR REPLACE INTO {record.table} ({', '.join(columns)}) VALUES "
                           f"({', '.join('?' * len(columns))})", [r for _, _, r in taken])
            db.executemany(SENT, [(self.target, record.table, k, v) for k, v, _ in taken])
            db.execute("COMMIT")
        except BaseException:
            if db.in_transaction:
                db.execute("ROLLBACK")
            raise
        return len(taken)

    def _taken(self, db: sqlite3.Connection, record: Record, lab: dict[str, str]) -> set[str]:
        """The keys of the records (``lab``: key → the lab's state) whose lab copy the journal takes: it
        lacks the record, or holds it as it was last sent or received (no change of this bench's own
        waiting to be sent) and the lab's copy has changed since."""
        key, state = _joined(record.key), _joined(record.state)
        mine = dict(db.execute(f"SELECT {key}, {state} FROM {record.table} t"))
        sent = dict(db.execute("SELECT key, state FROM sync_sent WHERE target = ? AND name = ?",
                               (self.target, record.table)))
        return {k for k, v in lab.items() if k not in mine or (mine[k] == sent.get(k) and mine[k] != v)}

    def _push_once(self, db: sqlite3.Connection, passed: dict[str, set[str]]) -> Sent:
        point_columns = tuple(c.name for c in schema.points.columns if c.name != "run_id")
        run_columns = tuple(c.name for c in schema.runs.columns if c.name not in ("id", "station"))

        sent = Sent()
        marks = self._cursors(db)
        runs = self._runs_to_send(db)[:BATCH]
        lab_ids = dict(db.execute("SELECT run_id, lab_run_id FROM sync_runs WHERE target=?", (self.target,)))
        moved: dict[str, int] = {}
        run_rows = []
        with self.engine.begin() as server:
            for run_id, state, _ in runs:
                row = db.execute(f"SELECT {', '.join(run_columns)}, station FROM runs WHERE id=?",
                                 (run_id,)).fetchone()
                values = dict(zip(run_columns, row[:-1], strict=True))
                # as journaled (`Journal.start_run`); a run journaled before runs named their
                # station was journaled here, at this station
                values["station"] = row[-1] or self.station
                lab_id, new = lab_number(server, values)
                lab_ids[run_id] = lab_id
                run_rows.append((self.target, run_id, lab_id, state))
                sent.stored["runs"] += new
            sent.offered["runs"] = len(run_rows)
            moved_points, sent.offered["points"], sent.stored["points"] = self._send_rows(
                server, db, "points", "rowid", marks.get("points", 0), point_columns, lab_ids,
                lambda rows: postgresql.insert(schema.points).values(rows).on_conflict_do_nothing(
                    index_elements=["run_id", "seq"]))
            moved_events, sent.offered["events"], sent.stored["events"] = self._send_rows(
                server, db, "events", "id", marks.get("events", 0), EVENT_COLUMNS, lab_ids,
                lambda rows: postgresql.insert(schema.events).values(rows).on_conflict_do_nothing(
                    index_elements=["run_id", "origin_id"]), origin=True)
            records = []
            for record in RECORDS:
                pending = self._records_to_send(db, record, BATCH, frozenset(passed[record.table]))
                accepted, sent.stored[record.table] = self._send_allowed(server, record, pending, sent,
                                                                         passed[record.table])
                sent.offered[record.table] = len(accepted)
                records += [(self.target, record.table, key, state) for key, state, _ in accepted]
            moved_audit, sent.offered["audit"], sent.stored["audit"] = self._send_audit(
                server, db, marks.get("audit", 0), sent, passed["audit"])
        for name, position in (("points", moved_points), ("events", moved_events), ("audit", moved_audit)):
            if position is not None:
                moved[name] = position
        if run_rows or moved or records:  # the server has committed: now the journal may say so
            db.execute("BEGIN IMMEDIATE")
            try:
                db.executemany("INSERT INTO sync_runs (target, run_id, lab_run_id, sent) VALUES (?,?,?,?) "
                               "ON CONFLICT (target, run_id) DO UPDATE SET lab_run_id=excluded.lab_run_id, "
                               "sent=excluded.sent", run_rows)
                db.executemany("INSERT INTO sync_cursors (target, name, position) VALUES (?,?,?) "
                               "ON CONFLICT (target, name) DO UPDATE SET position=excluded.position",
                               [(self.target, n, p) for n, p in moved.items()])
                db.executemany(SENT, records)
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
        return sent

    @staticmethod
    def _send_allowed(server: Connection, record: Record, pending: list[tuple], sent: Sent,
                      passed: set[str]) -> tuple[list[tuple], int]:
        """``pending`` records sent, each batch in a savepoint; where PostgreSQL refuses this bench's
        role the batch (an approver, an approved certificate: `labcal.store.roles`), each record is
        sent alone and only the refused ones are passed over (noted in ``sent`` and ``passed``),
        never the rest nor the push. Returns the records stored and how many rows changed."""
        if not pending:
            return [], 0
        try:
            with server.begin_nested():
                return pending, send_records(server, record, [row for _, _, row in pending])
        except Exception as exc:
            if not is_refusal(exc):
                raise
        accepted, stored = [], 0
        for item in pending:
            try:
                with server.begin_nested():
                    stored += send_records(server, record, [item[2]])
                accepted.append(item)
            except Exception as exc:
                if not is_refusal(exc):
                    raise
                passed.add(item[0])
                sent.refused[record.table] = sent.refused.get(record.table, 0) + 1
                sent.why = sent.why or labdb._first_line(getattr(exc, "orig", None) or exc)
        return accepted, stored

    @staticmethod
    def _send_audit(server: Connection, db: sqlite3.Connection, after: int, sent: Sent, passed: set[str]
                    ) -> tuple[int | None, int, int]:
        """The journal's audit rows after ``after`` (an approver registered or revoked at this bench)
        appended to the lab's audit trail, each chained after the lab's newest row and named by the
        digest it has in the journal (``origin``, unique: a row sent again is not appended again):
        (the new cursor or None, offered, appended). A role that may not write the audit trail (a
        bench's: it may not change the approvers either) has them passed over, once per push."""
        rows = [] if passed else db.execute(
            "SELECT id, utc, kind, account, actor, client, detail, digest FROM audit WHERE id > ? "
            "ORDER BY id LIMIT ?", (after, BATCH)).fetchall()
        if not rows:
            return None, 0, 0
        try:
            with server.begin_nested():
                appended = sum(append_audit(server, utc, kind, account, actor, client, detail, origin=digest)
                               is not None for _, utc, kind, account, actor, client, detail, digest in rows)
        except Exception as exc:
            if not is_refusal(exc):
                raise
            passed.update(str(row[0]) for row in rows)
            sent.refused["audit"] = sent.refused.get("audit", 0) + len(rows)
            sent.why = sent.why or labdb._first_line(getattr(exc, "orig", None) or exc)
            return None, 0, 0
        return rows[-1][0], len(rows), appended

    def _send_rows(self, server: Connection, db: sqlite3.Connection, table: str, key: str, after: int,
                   columns: tuple[str, ...], lab_ids: dict[int, int] | None,
                   statement: Callable[[list[dict]], object], origin: bool = False
                   ) -> tuple[int | None, int, int]:
        """One batch of ``table``'s rows after ``after``: (the new cursor or None, offered, stored).
        A row whose run the server does not know yet (started after this pass read the runs) ends
        the batch before it: the next pass sends its run first."""
        run_column = "run_id, " if lab_ids is not None else ""
        rows = db.execute(f"SELECT {key}, {run_column}{', '.join(columns)} FROM {table} WHERE {key} > ? "
                          f"ORDER BY {key} LIMIT ?", (after, BATCH)).fetchall()
        values: list[dict] = []
        last = None
        for row in rows:
            record = dict(zip(columns, row[2:] if lab_ids is not None else row[1:], strict=True))
            if lab_ids is not None:
                if row[1] not in lab_ids:
                    break
                record["run_id"] = lab_ids[row[1]]
            if origin:
                record["origin_id"] = row[0]
            values.append(record)
            last = row[0]
        if not values:
            return None, 0, 0
        # SQLAlchemy reports an INSERT's rowcount only when asked to keep it
        result = server.execute(statement(values).execution_options(  # type: ignore[attr-defined]
            preserve_rowcount=True))
        stored = result.rowcount if result.rowcount is not None and result.rowcount >= 0 else len(values)
        return last, len(values), stored


RUN_NUMBER_LOCK = 0x6C616272  # "labr": serialises numbering the lab's runs (one transaction at a time)


def lab_number(server: Connection, values: dict) -> tuple[int, bool]:
    """The lab's number of a run (``values``: its journaled columns), given the first time any bench
    sends it and never again: a run the lab knows (by its uuid) keeps its number and has its status
    updated; a new one gets the next number, one more than the highest, under a lock held until the
    sending transaction commits, so the lab's runs are numbered 1, 2, 3 … in the order they reached
    it, without a gap (a database sequence would leave one at every rolled-back or conflicting insert).
    Returns the number, and whether the run is new to the lab."""
    def known() -> int | None:
        return server.execute(
            sqlalchemy.select(schema.runs.c.id).where(schema.runs.c.uuid == values["uuid"])
        ).scalar()

    status = {name: values[name] for name in BENCH_CLOSES_RUNS}  # what a bench's role may update of its run
    number = known()
    if number is None:
        server.execute(sqlalchemy.text("SELECT pg_advisory_xact_lock(:key)"), {"key": RUN_NUMBER_LOCK})
        number = known()  # sent meanwhile by another process of this bench (a run's sender, labcal sync)
    if number is not None:
        server.execute(sqlalchemy.update(schema.runs).where(schema.runs.c.id == number).values(**status))
        return number, False
    number = int(
        server.execute(
            sqlalchemy.select(sqlalchemy.func.coalesce(sqlalchemy.func.max(schema.runs.c.id), 0) + 1)
        ).scalar_one()
    )
    server.execute(schema.runs.insert().values(id=number, **values))
    # the column's own sequence follows, so that nothing else inserting a run takes a number twice
    server.execute(sqlalchemy.text("SELECT setval(pg_get_serial_sequence('runs', 'id'), :n)"), {"n": number})
    return number, True


def send_records(server: Connection, record: Record, rows: list[dict]) -> int:
    """Records into the lab database, each stored once under its key; one sent again because it
    changed replaces the lab's copy (a certificate approved or re-issued under its id, an estimate
    stored again, a pool that grew) unless the lab's is newer, and an approver's revocation is kept.
    Returns how many rows the lab database changed."""
    if not rows:
        return 0
    table = schema.METADATA.tables[record.table]
    statement = postgresql.insert(table).values(rows)
    if record.table == "approvers":
        # a name active twice (two benches registered two keys for it offline) is refused by the
        # lab's unique index: the first registration stands, as it would have on one database
        kept = statement.on_conflict_do_nothing().execution_options(preserve_rowcount=True)
        stored = _count(server.execute(kept), len(rows))
        for row in rows:
            if row["revoked_utc"] is not None:
                stored += _count(
                    server.execute(
                        sqlalchemy.update(table)
                        .where(table.c.key_id == row["key_id"], table.c.revoked_utc.is_(None))
                        .values(revoked_utc=row["revoked_utc"])
                    ),
                    1,
                )
        return stored
    # a certificate whose digest differs, but never a draft over an approved one (the lab's record of
    # the approval, whichever role sends it); an estimate or a pool stored later than the lab's copy
    if record.table == "certificates":
        def approved(document: Any) -> Any:
            return document.cast(postgresql.JSONB)["approval"].is_not(None)

        newer = sqlalchemy.and_(
            table.c.sha256 != statement.excluded.sha256,
            sqlalchemy.or_(~approved(table.c.document), approved(statement.excluded.document)),
        )
    else:
        newer = table.c[record.state[0]] < statement.excluded[record.state[0]]
    changed = {c.name: statement.excluded[c.name] for c in table.columns if c.name not in record.key}
    upsert = statement.on_conflict_do_update(index_elements=list(record.key), set_=changed, where=newer)
    return _count(server.execute(upsert.execution_options(preserve_rowcount=True)), len(rows))


def _count(result: object, at_most: int) -> int:
    """Rows a statement changed (where the driver cannot say: every row it was given)."""
    count = getattr(result, "rowcount", None)
    return count if isinstance(count, int) and count >= 0 else at_most


def is_refusal(exc: BaseException) -> bool:
    """The lab's server refused this bench's role a table (SQLSTATE 42501, insufficient privilege):
    what a bench may write is the administrator's grant (`labcal.store.roles`), not retried."""
    original = getattr(exc, "orig", None) or exc
    return getattr(original, "sqlstate", None) == "42501"


def is_outage(exc: BaseException) -> bool:
    """A server that cannot be reached (or went away mid-transaction): retried, not fatal."""
    return isinstance(exc, sqlalchemy_exc.OperationalError | labdb.Unreachable) or (
        isinstance(exc, sqlalchemy_exc.DBAPIError) and exc.connection_invalidated)


class Background:
    """A `Sender` on a thread of its own during a run (see the module's docstring)."""

    def __init__(self, sender: Sender, say: Callable[[str], None], run_event: Callable[[str], None]):
        self.sender = sender
        self.say = say
        self.run_event = run_event
        self.sent = Sent()
        self.down_since: float | None = None
        self.outages = 0
        self._stop = threading.Event()
        self._wake = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="labcal-sync", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def wake(self) -> None:
        """A record was journaled: send it now rather than at the next poll."""
        self._wake.set()

    def _attempt(self) -> bool:
        try:
            self.sent.add(self.sender.push())
        except Exception as exc:
            if not is_outage(exc):
                raise
            if self.down_since is None:
                self.down_since = time.monotonic()
                self.outages += 1
                if self.outages == 1:
                    why = labdb._first_line(getattr(exc, "orig", None) or exc)
                    line = (f"the lab database {self.sender.server} is unreachable ({why}); the run goes "
                            "on measuring, and its records are sent when it is back (or with labcal sync)")
                    self.say(line)
                    self.run_event(line)
            return False
        if self.down_since is not None:
            self.down_since = None
        return True

    def _loop(self) -> None:
        pause = POLL_S
        while not self._stop.is_set():
            try:
                pause = POLL_S if self._attempt() else min(pause * 2, BACKOFF_MAX_S)
            except Exception as exc:  # never stops the run: said once, and the run goes on
                self.say(f"sending to the lab database stopped ({labdb._first_line(exc)}); the journal "
                         "keeps every record: run labcal sync")
                return
            self._wake.wait(pause)
            self._wake.clear()

    def finish(self, within_s: float = FLUSH_S) -> dict[str, int]:
        """Stop the thread, send what can be sent within ``within_s``, and return what is left."""
        deadline = time.monotonic() + within_s
        self._stop.set()
        self._wake.set()
        self._thread.join(within_s)  # its last push, if one is under way (each connect: at most 5 s)
        while time.monotonic() < deadline:
            was_down = self.down_since is not None
            try:
                if self._attempt() or was_down:  # a server away for a while: one last try, no waiting
                    break
            except Exception:  # noqa: BLE001 - said below as what is left
                break
            time.sleep(0.2)
        try:
            return self.sender.pending()
        finally:
            self.sender.close()


def _run_event(journal: Path) -> Callable[[str], None]:
    """A journal event on the newest running run (the one this process measures)."""
    def record(message: str) -> None:
        try:  # through the journal's writer: the event takes its place in the run's chain
            with Journal(journal) as writer:
                row = writer.db.execute("SELECT max(id) FROM runs WHERE status='running'").fetchone()
                if row and row[0] is not None:
                    writer.event(row[0], "lab_database", message)
        except (LabcalError, sqlite3.Error):
            pass  # the console has said it; the journal's own writer is what matters
    return record


def ready(db: str | Path | None) -> None:
    """Before a run moves anything: the journal current (created if new), and a server that can be
    reached at this labcal's schema (created if empty). A server behind or ahead refuses the run
    in one line; one that cannot be reached does not (the run never waits for it): the run's
    sender says so, once."""
    labdb.connect(db_path(db)).close()
    check_server(db)
    receive(db)


def receive(db: str | Path | None) -> dict[str, int]:
    """The lab's records this bench lacks copied into its journal (`Sender.pull`): before a run, so
    that it starts from the lab's settle pool and device history. A server that cannot be reached is
    not waited for (the run starts from what the journal last had)."""
    where = lab_database(db)
    journal = db_path(db)
    if isinstance(where, Path) or not journal.is_file():
        return {}
    try:
        sender = Sender(journal, where)
    except labdb.Unreachable:
        return {}
    try:
        return sender.pull()
    except Exception as exc:
        if not (is_outage(exc) or is_refusal(exc)):
            raise
        return {}
    finally:
        sender.close()


def check_server(db: str | Path | None) -> None:
    """A lab server that can be reached is at this labcal's schema (created if empty; behind or
    ahead: refused in one line); one that cannot be reached is not waited for."""
    where = lab_database(db)
    if isinstance(where, Path):
        return
    try:
        labdb.open_server(where).dispose()
    except labdb.Unreachable:
        pass


@contextmanager
def sending(db: str | Path | None, journal: Path, say: Callable[[str], None]) -> Iterator[Background | None]:
    """During a run: its records sent to the lab's server as they are written (nothing to do when the
    lab database is the journal itself, a SQLite file). At the end, what is left is said."""
    where = lab_database(db)
    if isinstance(where, Path):
        yield None
        return
    background = Background(Sender(journal, where), say, _run_event(journal))
    background.start()
    try:
        yield background
    finally:
        left = background.finish()
        if any(left.values()):
            say(f"not yet in the lab database {where}: " + ", ".join(f"{n} {k}" for k, n in left.items())
                + "; they stay in the journal " f"{journal}: run labcal sync when the server is back")


def send_now(db: str | Path | None) -> str | None:
    """What this bench has just recorded (an approver registered or revoked, a certificate approved)
    sent to the lab's server at once, so that every bench sees it now; None when sent (or when the
    lab database is the journal itself), else the one line saying it waits for ``labcal sync``."""
    where = lab_database(db)
    journal = db_path(db)
    if isinstance(where, Path) or not journal.is_file():
        return None
    try:
        sender = Sender(journal, where)
    except LabcalError as exc:
        return f"{exc}; the journal {journal} keeps it for labcal sync"
    try:
        sent = sender.push()
    except Exception as exc:
        why = labdb._first_line(getattr(exc, "orig", None) or exc)
        if is_refusal(exc):
            return refused_line(where, why, journal)
        if not is_outage(exc):
            raise
        return (f"the lab database {where} is unreachable ({why}); the journal {journal} keeps it for "
                "labcal sync")
    finally:
        sender.close()
    return None if not sent.refused else refused_line(where, sent.why, journal)


def refused_line(where: ServerDatabase, why: str | None, journal: Path) -> str:
    """What a bench is told of a change the lab refuses its role (an approver registered or revoked,
    a certificate approved at the bench: the administrator's and the lab server's to write)."""
    return (f"the lab database {where} refuses this bench's role that change ({why}): the lab's "
            f"administrator makes it there (an approval: the lab server); the journal {journal} keeps it")


# what a journal notes of a record it sent to, or received from, a lab database: its state there
SENT = ("INSERT INTO sync_sent (target, name, key, state) VALUES (?,?,?,?) "
        "ON CONFLICT (target, name, key) DO UPDATE SET state=excluded.state")


def _utc() -> str:
    return utc_now()

"""Every journaled record reaches the lab's PostgreSQL database exactly once (issue 24).

With a server as the lab database, each station journals in a SQLite file of its own
(`labcal.config.lab.LabConfig.journal`): a reading is on the station's disk, committed, before the
next move, whatever the network does. `Sender.push` sends what the journal holds and the server
does not yet: runs (found by their uuid: the server numbers runs of every station, so a station's
run id is not the lab's), their points (key: the lab's run id and the point's seq), events (key:
the lab's run id and the event's id in the journal, ``events.origin_id``) and certificates (key:
their id). Every insert is ``ON CONFLICT DO NOTHING`` (a run's status an upsert), so sending a record
twice (the server committed, the cursor's update did not) stores it once. The journal keeps how far
it has sent to each server (``sync_cursors``: the last rowid of each table; ``sync_runs``: each
run's lab id and the status last sent), written only after the server has committed.

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
from typing import TYPE_CHECKING

from labcal.config.lab import ServerDatabase, load_lab_config
from labcal.errors import LabcalError
from labcal.run import labdb
from labcal.run.labdb import lab_database

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection, Engine

EVENT_COLUMNS = ("utc", "station_time", "kind", "message", "data", "link", "digest")
BATCH = 500  # rows per statement: a catch-up after a long outage goes in bounded transactions
POLL_S = 0.5  # how often the sender looks at the journal during a run
BACKOFF_MAX_S = 10.0
FLUSH_S = 5.0  # what the end of a run waits for the server, at most


@dataclass
class Sent:
    """What one push sent: rows offered to the server per table, and rows it did not have yet."""

    offered: dict[str, int] = field(default_factory=lambda: dict.fromkeys(("runs", "points", "events",
                                                                            "certificates"), 0))
    stored: dict[str, int] = field(default_factory=lambda: dict.fromkeys(("runs", "points", "events",
                                                                           "certificates"), 0))

    def add(self, other: Sent) -> None:
        for name in self.offered:
            self.offered[name] += other.offered[name]
            self.stored[name] += other.stored[name]

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

    def close(self) -> None:
        self.engine.dispose()

    def _local(self) -> sqlite3.Connection:
        return labdb.connect(self.journal)

    def pending(self) -> dict[str, int]:
        """Records of the journal not yet sent to this lab database, per table."""
        with closing(self._local()) as db:
            marks = self._cursors(db)
            out = {"runs": len(self._runs_to_send(db))}
            for name, key in (("points", "rowid"), ("events", "id"), ("certificates", "rowid")):
                out[name] = db.execute(f"SELECT count(*) FROM {name} WHERE {key} > ?",
                                       (marks.get(name, 0),)).fetchone()[0]
            return out

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
        with closing(self._local()) as db:
            while True:
                step = self._push_once(db)
                sent.add(step)
                if step.total == 0:
                    return sent

    def _push_once(self, db: sqlite3.Connection) -> Sent:
        # SQLAlchemy's tables only here, where a server is written: a run on a SQLite lab database
        # (the journal itself) imports neither them nor SQLAlchemy
        from sqlalchemy.dialects.postgresql import insert

        from labcal.run import schema

        point_columns = tuple(c.name for c in schema.points.columns if c.name != "run_id")
        run_columns = tuple(c.name for c in schema.runs.columns if c.name not in ("id", "station"))
        certificate_columns = tuple(c.name for c in schema.certificates.columns)

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
                statement = insert(schema.runs).values(**values).on_conflict_do_update(
                    index_elements=["uuid"],
                    set_={"status": values["status"], "reason": values["reason"],
                          "ended_utc": values["ended_utc"], "points_total": values["points_total"]})
                lab_id = server.execute(statement.returning(schema.runs.c.id)).scalar_one()
                lab_ids[run_id] = lab_id
                run_rows.append((self.target, run_id, lab_id, state))
            sent.offered["runs"] = sent.stored["runs"] = len(run_rows)
            moved_points, sent.offered["points"], sent.stored["points"] = self._send_rows(
                server, db, "points", "rowid", marks.get("points", 0), point_columns, lab_ids,
                lambda rows: insert(schema.points).values(rows).on_conflict_do_nothing(
                    index_elements=["run_id", "seq"]))
            moved_events, sent.offered["events"], sent.stored["events"] = self._send_rows(
                server, db, "events", "id", marks.get("events", 0), EVENT_COLUMNS, lab_ids,
                lambda rows: insert(schema.events).values(rows).on_conflict_do_nothing(
                    index_elements=["run_id", "origin_id"]), origin=True)
            moved_certs, sent.offered["certificates"], sent.stored["certificates"] = self._send_rows(
                server, db, "certificates", "rowid", marks.get("certificates", 0), certificate_columns,
                None, lambda rows: insert(schema.certificates).values(rows).on_conflict_do_nothing(
                    index_elements=["certificate_id"]))
        for name, position in (("points", moved_points), ("events", moved_events),
                               ("certificates", moved_certs)):
            if position is not None:
                moved[name] = position
        if run_rows or moved:  # the server has committed: now the journal may say so
            db.execute("BEGIN IMMEDIATE")
            try:
                db.executemany("INSERT INTO sync_runs (target, run_id, lab_run_id, sent) VALUES (?,?,?,?) "
                               "ON CONFLICT (target, run_id) DO UPDATE SET lab_run_id=excluded.lab_run_id, "
                               "sent=excluded.sent", run_rows)
                db.executemany("INSERT INTO sync_cursors (target, name, position) VALUES (?,?,?) "
                               "ON CONFLICT (target, name) DO UPDATE SET position=excluded.position",
                               [(self.target, n, p) for n, p in moved.items()])
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
        return sent

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
        result = server.execute(statement(values))  # type: ignore[call-overload]
        stored = result.rowcount if result.rowcount is not None and result.rowcount >= 0 else len(values)
        return last, len(values), stored


def is_outage(exc: BaseException) -> bool:
    """A server that cannot be reached (or went away mid-transaction): retried, not fatal."""
    from sqlalchemy.exc import DBAPIError, OperationalError

    return isinstance(exc, OperationalError | labdb.Unreachable) or (
        isinstance(exc, DBAPIError) and exc.connection_invalidated)


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
        from labcal.run.journal import Journal

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
    from labcal.run.journal import db_path

    labdb.connect(db_path(db)).close()
    check_server(db)


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

"""The journal's chain of digests: every record of a run names, by SHA-256, the record before it.

A run's records — its manifest first, then its points and events in the order the journal wrote
them — form one chain. Record n carries ``link`` = n (the manifest is 0, held by ``runs.digest``) and
``digest`` = SHA-256 of its canonical form (`canonical`), which includes the digest of record n-1.
An edit to any field of any record, a record deleted, or one inserted, changes that record's digest
or breaks the sequence of links; and an editor who recomputes every digest after the edit changes
the chain's head, which a certificate states and its approval signs. So the journal is
tamper-evident, not tamper-proof: the signature on the head is what a forger cannot redo.

The canonical form is defined once, here, for the writer (`labcal.store.journal.Journal`) and for
every verifier, on either backend: a record's values are taken by their column's type (a REAL read
back from SQLite or a double precision from PostgreSQL is the same float; an int written into a
REAL column reads back as a float), floats in their shortest round-trip form (Python's ``repr``,
NaN as ``NaN``), the samples by their SHA-256, the manifest's plan and station texts by theirs.
Nothing local to one database enters it — not a run's id nor an event's id, which differ between a
station's journal and the lab database — so a chain computed at the bench verifies in the lab.

A run journaled before the chain existed has no manifest digest; it is said to be "journaled before
digests; not tamper-evident", neither passed nor failed.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping, Sequence
from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.config.lab import load_lab_config
from labcal.lazy import lazy
from labcal.store import labdb

if TYPE_CHECKING:
    import sqlalchemy
    from sqlalchemy import exc

    from labcal.store import schema
else:
    exc = lazy("sqlalchemy.exc")  # start-up without sqlalchemy
    schema = lazy("labcal.store.schema")  # start-up without sqlalchemy
    sqlalchemy = lazy("sqlalchemy")  # start-up without sqlalchemy

FORM = "labcal.journal-chain/1"
UNCHAINED = "journaled before digests; not tamper-evident"

# (column, type) of each record kind, in no particular order (the canonical form sorts keys)
RUN_FIELDS: tuple[tuple[str, type], ...] = (
    ("uuid", str), ("plan_name", str), ("plan_text", bytes), ("station_text", bytes),
    ("software_version", str), ("instrument_serial", str), ("device_id", str), ("operator", str),
    ("settings", str), ("metadata", str), ("started_utc", str), ("station", str))
POINT_FIELDS: tuple[tuple[str, type], ...] = (
    ("seq", int), ("replicate", int), ("y_deg", float), ("u_deg", float), ("pitch_deg", float),
    ("roll_deg", float), ("pitch_read", float), ("roll_read", float), ("attempt", int), ("status", str),
    ("t_start", float), ("t_end", float), ("n_samples", int), ("vx", float), ("vy", float), ("vz", float),
    ("sd_vx", float), ("sd_vy", float), ("sd_vz", float), ("temp_c", float), ("settle_s", float),
    ("settle_verdict", str), ("utc", str), ("samples", bytes))
EVENT_FIELDS: tuple[tuple[str, type], ...] = (
    ("utc", str), ("station_time", float), ("kind", str), ("message", str), ("data", str))
FIELDS = {"run": RUN_FIELDS, "point": POINT_FIELDS, "event": EVENT_FIELDS}


def _value(value: object, kind: type) -> object:
    if value is None:
        return None
    if kind is float:
        return float(value)  # type: ignore[arg-type]
    if kind is int:
        return int(value)  # type: ignore[call-overload]
    if kind is bytes:  # a blob or a long text: named by its SHA-256
        data = value.encode("utf-8") if isinstance(value, str) else bytes(value)  # type: ignore[call-overload]
        return hashlib.sha256(data).hexdigest()
    return str(value)


def canonical(kind: str, run_uuid: str, link: int, previous: str, values: Mapping[str, object]) -> bytes:
    """A record's canonical form: UTF-8 JSON, keys sorted, no spaces, of the form's name, the run's
    uuid, the record's kind and link, the previous record's digest ("" for the manifest) and the
    record's fields, each by its column's type (see the module's docstring)."""
    fields = {name: _value(values.get(name), typ) for name, typ in FIELDS[kind]}
    doc = {"form": FORM, "run": run_uuid, "record": kind, "link": link, "previous": previous,
           "fields": fields}
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=True).encode("utf-8")


def digest(kind: str, run_uuid: str, link: int, previous: str, values: Mapping[str, object]) -> str:
    """SHA-256 (hex) of the record's canonical form: the record's digest, the next one's ``previous``."""
    return hashlib.sha256(canonical(kind, run_uuid, link, previous, values)).hexdigest()


def manifest_digest(values: Mapping[str, object]) -> str:
    """The digest of a run's manifest (link 0, nothing before it), kept in ``runs.digest``."""
    return digest("run", str(values["uuid"]), 0, "", values)


@dataclass(frozen=True)
class Record:
    """One record of a run's chain as a database holds it."""

    kind: str  # "point" or "event"
    link: int | None
    digest: str | None
    values: Mapping[str, object]

    @property
    def label(self) -> str:
        if self.kind == "point":
            return f"point {self.values.get('seq')}"
        return f"event {self.values.get('kind')!r} of {self.values.get('utc')}"


@dataclass(frozen=True)
class ChainCheck:
    """What recomputing a run's chain found: ``problem`` None and ``digests`` its digests (link 0 the
    manifest's) when every record holds; ``chained`` False for a run journaled before digests."""

    run: str  # how the run is named in the messages ("run 3 (uuid …)")
    run_uuid: str
    chained: bool
    digests: tuple[str, ...] = ()
    problem: str | None = None

    @property
    def intact(self) -> bool:
        return self.chained and self.problem is None

    @property
    def records(self) -> int:
        """Records after the manifest (points and events)."""
        return max(len(self.digests) - 1, 0)

    @property
    def head(self) -> str | None:
        return self.digests[-1] if self.digests else None

    def statement(self, records: int | None = None) -> dict[str, Any] | None:
        """What a certificate states of the chain: the run's uuid, how many records it covers and the
        digest of the last of them (``records``: the first that many; None: all). None when the
        chain does not hold, is shorter, or the run was journaled before digests."""
        n = self.records if records is None else records
        if not self.intact or n > self.records or n < 0:
            return None
        return {"run_uuid": self.run_uuid, "records": n, "head": self.digests[n]}

    def against(self, stated: Mapping[str, Any]) -> str | None:
        """Why this chain is not the one a certificate states (None: it is), in one clause."""
        if not self.chained:
            return f"{self.run} was {UNCHAINED}, yet the certificate states a chain of its journal"
        if self.problem is not None:
            return self.problem
        n, head = int(stated["records"]), str(stated["head"])
        if n > self.records:
            return (f"{self.run} holds {self.records} records of the {n} the certificate's chain covers: "
                    "records are missing from the journal")
        if self.digests[n] != head:
            return (f"the journal's chain of {self.run} at record {n} is {self.digests[n][:16]}…, not the "
                    f"head {head[:16]}… the certificate states: the journal was changed after it was issued")
        return None

    def describe(self) -> str:
        """One clause for the console."""
        if not self.chained:
            return f"{self.run}: {UNCHAINED}"
        if self.problem is not None:
            return self.problem
        head = (self.head or "")[:16]
        return f"the journal's chain of {self.run} holds ({self.records} records, head {head}…)"


def check(run: str, run_values: Mapping[str, object], manifest: str | None,
          records: Iterable[Record]) -> ChainCheck:
    """Recompute a run's chain from its records as stored and name the first that differs.

    Each record is checked against the digest stored on the record before it, so the record named
    is the first whose stored digest its own content (and its predecessor's digest) does not give:
    an edited field, a digest rewritten, a record missing (its link skipped) or without a digest."""
    run_uuid = str(run_values.get("uuid") or "")
    if manifest is None:
        return ChainCheck(run, run_uuid, chained=False)
    recomputed = manifest_digest(run_values)
    if recomputed != manifest:
        return ChainCheck(run, run_uuid, True, problem=(
            f"the manifest of {run} differs from the journal's chain: its digest {recomputed[:16]}… ≠ "
            f"{manifest[:16]}… journaled"))
    ordered = sorted(records, key=lambda r: (r.link is None, r.link or 0))
    superseded = _superseded(ordered)
    digests = [manifest]
    for record in ordered:
        expected_link = len(digests)
        if record.link is None or record.digest is None:
            return ChainCheck(run, run_uuid, True, tuple(digests), (
                f"{record.label} of {run} carries no digest in a chained run: it was added outside "
                "the journal"))
        if record.link != expected_link:
            return ChainCheck(run, run_uuid, True, tuple(digests), (
                f"record {expected_link} of {run}'s chain is missing (the next is {record.label}, record "
                f"{record.link}): a record was deleted from the journal"))
        values = record.values
        if record.kind == "point" and values.get("status") == SUPERSEDED and values.get("seq") in superseded:
            values = {**values, "status": "ok"}  # journaled ok; a chained event says it was measured again
        mine = digest(record.kind, run_uuid, record.link, digests[-1], values)
        if mine != record.digest:
            return ChainCheck(run, run_uuid, True, tuple(digests), (
                f"{record.label} of {run} differs from the journal's chain: its digest {mine[:16]}… ≠ "
                f"{record.digest[:16]}… journaled"))
        digests.append(record.digest)
    return ChainCheck(run, run_uuid, True, tuple(digests))


SUPERSEDED = "superseded"


def _superseded(records: Iterable[Record]) -> set[int]:
    """The points a ``remeasured`` event says were measured again. The one change a journal makes to
    a record after writing it is to mark such a point superseded (`Journal.supersede`); its digest is
    of the point as journaled (status ok), and the event that names it is itself in the chain, so a
    point marked superseded without one, or an event forged to name one, fails the check."""
    found = set()
    for record in records:
        if record.kind == "event" and record.values.get("kind") == "remeasured" and record.values.get("data"):
            try:
                found.add(int(json.loads(str(record.values["data"]))["seq"]))
            except (ValueError, KeyError, TypeError):
                continue
    return found


# --- reading a run's records -----------------------------------------------------------------------
RUN_COLUMNS = tuple(name for name, _ in RUN_FIELDS)
POINT_COLUMNS = tuple(name for name, _ in POINT_FIELDS)
EVENT_COLUMNS = tuple(name for name, _ in EVENT_FIELDS)


def _records(kind: str, columns: Sequence[str], rows: Iterable[Sequence[object]]) -> list[Record]:
    return [Record(kind, row[0], row[1], dict(zip(columns, row[2:], strict=True)))  # type: ignore[arg-type]
            for row in rows]


def _sql(run_param: str) -> tuple[str, str, str]:
    return (f"SELECT {', '.join(RUN_COLUMNS)}, digest FROM runs WHERE id = {run_param}",
            f"SELECT link, digest, {', '.join(POINT_COLUMNS)} FROM points WHERE run_id = {run_param}",
            f"SELECT link, digest, {', '.join(EVENT_COLUMNS)} FROM events WHERE run_id = {run_param}")


def check_sqlite(db: Any, run_id: int, run: str | None = None) -> ChainCheck:
    """The chain of run ``run_id`` of a SQLite journal or lab file (an open sqlite3 connection)."""
    runs_sql, points_sql, events_sql = _sql("?")
    row = db.execute(runs_sql, (run_id,)).fetchone()
    if row is None:
        raise LookupError(run_id)
    values = dict(zip(RUN_COLUMNS, row[:-1], strict=True))
    records = (_records("point", POINT_COLUMNS, db.execute(points_sql, (run_id,)))
               + _records("event", EVENT_COLUMNS, db.execute(events_sql, (run_id,))))
    return check(run or f"run {run_id}", values, row[-1], records)


def check_server(connection: Any, run_id: int, run: str | None = None) -> ChainCheck:
    """The chain of run ``run_id`` of the lab's server (an open SQLAlchemy connection)."""
    runs_sql, points_sql, events_sql = _sql(":run")
    row = connection.execute(sqlalchemy.text(runs_sql), {"run": run_id}).fetchone()
    if row is None:
        raise LookupError(run_id)
    values = dict(zip(RUN_COLUMNS, row[:-1], strict=True))
    records = _records(
        "point", POINT_COLUMNS, connection.execute(sqlalchemy.text(points_sql), {"run": run_id})
    ) + _records("event", EVENT_COLUMNS, connection.execute(sqlalchemy.text(events_sql), {"run": run_id}))
    return check(run or f"run {run_id}", values, row[-1], records)


def copies(db: str | Path | None, run_uuid: str) -> list[tuple[str, ChainCheck]]:
    """The run's chain recomputed in every database this station knows that holds it, as (where,
    check): the lab's server, when the lab database is one and can be reached, and the station's
    journal (the lab database itself when that is a SQLite file). Nothing is created or changed."""
    found: list[tuple[str, ChainCheck]] = []
    where = labdb.lab_database(db)
    server = None if isinstance(where, Path) else where
    if server is not None:
        try:
            engine = labdb.open_server(server)
        except labdb.Unreachable:
            engine = None
        if engine is not None:
            try:
                with engine.connect() as connection:
                    row = connection.execute(sqlalchemy.text("SELECT id FROM runs WHERE uuid = :u"),
                                             {"u": run_uuid}).first()
                    if row is not None:
                        lab_run = f"run {row[0]} of the lab"
                        found.append((str(server), check_server(connection, row[0], lab_run)))
            finally:
                engine.dispose()
    journal = where if isinstance(where, Path) else load_lab_config().journal()  # as `journal.db_path`
    if journal.is_file():
        with closing(labdb.connect(journal)) as con:
            row = con.execute("SELECT id FROM runs WHERE uuid = ?", (run_uuid,)).fetchone()
            if row is not None:
                found.append((str(journal), check_sqlite(con, row[0])))
    return found


# --- the audit trail's chain (`labcal.app.audit`) ------------------------------------------------
AUDIT_TRIES = 20  # appends raced by other writers after the same row before giving up


def audit_digest(prev: str, utc: str, kind: str, account: str | None, actor: str | None, client: str | None,
                 detail: str | None) -> str:
    """SHA-256 (hex) of an audit row: the previous row's digest and this row's fields, as canonical
    JSON (a list, no spaces, non-ASCII as it is)."""
    fields = [prev, utc, kind, account, actor, client, detail]
    return hashlib.sha256(json.dumps(fields, separators=(",", ":"), ensure_ascii=False).encode()).hexdigest()


def append_audit(connection: Any, utc: str, kind: str, account: str | None, actor: str | None,
                 client: str | None, detail: str | None, origin: str | None = None) -> str | None:
    """Append one row to the audit trail after its newest (in the caller's transaction, each try in a
    savepoint): its digest, or None when a row of that ``origin`` is there already (a bench's row
    copied once). ``prev`` is unique, so two writers cannot both follow one row: the one that loses
    appends again after the other's. Raises `RuntimeError` after `AUDIT_TRIES` lost races."""
    for _ in range(AUDIT_TRIES):
        try:
            with connection.begin_nested():
                if (
                    origin is not None
                    and connection.execute(
                        sqlalchemy.select(schema.audit.c.id).where(schema.audit.c.origin == origin)
                    ).first()
                    is not None
                ):
                    return None
                last = connection.execute(
                    sqlalchemy.select(schema.audit.c.digest)
                    .order_by(sqlalchemy.desc(schema.audit.c.id))
                    .limit(1)
                ).first()
                prev = "" if last is None else last[0]
                digest = audit_digest(prev, utc, kind, account, actor, client, detail)
                connection.execute(schema.audit.insert().values(
                    utc=utc, kind=kind, account=account, actor=actor, client=client, detail=detail, prev=prev,
                    digest=digest, origin=origin))
            return digest
        except exc.IntegrityError:  # another writer appended after the same row, or the same origin meanwhile
            continue
    raise RuntimeError("the audit trail is being written by too many at once")

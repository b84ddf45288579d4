"""The run journal: every reading on disk, in SQLite, before the next move begins.

One database per lab (--db, else $LABCAL_DB, else the lab file's `database`, see
`labcal.config.lab`) holds every run: a manifest
first, then one transaction per point with its raw samples, and the events of the run (prompts
and answers, faults, retries, pauses). WAL mode with synchronous=FULL: a committed point
survives a killed process and a power cut. readings.csv and fit.json are exports of it.

The tables are `labcal.store.labdb`'s, which versions and migrates the file on open; every
statement here names its columns, so a column added by a later schema breaks no read or write.
"""

from __future__ import annotations

import hashlib
import json
import sqlite3
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.readings import Readings
from labcal.config.lab import load_lab_config
from labcal.config.plans import parse_plan
from labcal.errors import LabcalError
from labcal.store import chain, labdb
from labcal.store.labdb import lab_database


def db_path(option: str | Path | None = None) -> Path:
    """The SQLite file this station journals in: the lab database itself when it is a SQLite file
    (no copy, nothing to send), else the station's local journal (`LabConfig.journal`), whose
    records `labcal.store.sync` sends to the lab's server."""
    found = lab_database(option)
    return found if isinstance(found, Path) else load_lab_config().journal()


def sha256(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def utc_now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


@dataclass(frozen=True)
class Manifest:
    """What a run is: written before the first move."""

    run_dir: str
    plan_name: str
    plan_text: str
    station_text: str
    software_version: str
    settings: dict
    metadata: dict
    instrument_serial: str | None = None
    device_id: str | None = None
    operator: str | None = None
    station: str | None = None  # the station's name in the lab (None: `station_name`)
    points_total: int | None = None  # steps of the run's schedule (None: counted from the plan)


def station_name() -> str:
    """This station's name in the lab database, by the lab file's rule (`LabConfig.station`):
    $LABCAL_STATION, else the lab file's ``station``, else the computer's name.

    Not the station file's name nor its description: a station file describes wiring (drivers,
    ports, gearing) and several benches may share one, or one bench change files when a device is
    swapped, while the lab names the bench — the computer that drives it, unless told otherwise."""
    return load_lab_config().station()


def schedule_length(plan_text: str) -> int | None:
    """Every step of the run's schedule (replicates × mounts × points), or None for a plan this
    labcal cannot read (a run journaled by another version)."""
    try:
        return parse_plan(plan_text, "the run's plan").n_points
    except (LabcalError, ValueError):
        return None


@dataclass(frozen=True)
class PointRecord:
    """One measured (or failed) point of the schedule."""

    seq: int
    replicate: int
    y_deg: float
    u_deg: float
    pitch_deg: float
    roll_deg: float
    pitch_read: float | None
    roll_read: float | None
    attempt: int
    status: str  # "ok" or "failed"
    t_start: float
    t_end: float
    n_samples: int
    vx: float | None
    vy: float | None
    vz: float | None
    sd_vx: float | None
    sd_vy: float | None
    sd_vz: float | None
    temp_c: float | None
    settle_s: float | None
    settle_verdict: str


@dataclass(frozen=True)
class EventRow:
    """One row of a run's events table, its data decoded: what every reader of a run's events gets,
    from the station's journal and from the lab database alike (`Journal.events`,
    `labcal.store.labquery`, `labcal.store.lab_certificates`, `labcal.store.lab_view`). The kinds and
    what each one's data holds are `labcal.run.events`' (`RunEvent.journal_entry`)."""

    utc: str
    station_time: float | None  # rig seconds since the run began; None for what was not the run's
    kind: str
    message: str
    data: Any = None  # the event's JSON data: an object for every event labcal journals, or None

    @classmethod
    def read(cls, utc: str, station_time: float | None, kind: str, message: str, data: str | None
             ) -> EventRow:
        """A row as the table holds it (``data``: its JSON text)."""
        return cls(utc, station_time, kind, message, json.loads(data) if data else None)

    @property
    def values(self) -> dict[str, Any]:
        """``data`` where it is an object, else empty: what a reader of named fields takes."""
        return self.data if isinstance(self.data, dict) else {}

    def to_json(self) -> dict[str, Any]:
        """The row as `labcal log --json` writes it: its five fields under their column names."""
        return asdict(self)


@dataclass(frozen=True)
class RunRow:
    id: int
    run_dir: str
    plan_name: str
    plan_text: str
    plan_hash: str
    station_text: str
    station_hash: str
    software_version: str
    settings: dict
    # the stored document, key for key in its stored order: run.json copies it and the journal hashes
    # run.json's bytes; readers parse it (`labcal.config.run_metadata.parse_run_metadata`)
    metadata: dict
    started_utc: str
    ended_utc: str | None
    status: str
    reason: str | None
    instrument_serial: str | None
    operator: str | None
    uuid: str | None  # None only for a run of a database older than run identities (migrated: set)


@dataclass(frozen=True)
class RunSummary:
    """One line of `labcal runs`: what a run is and how far it got."""

    id: int
    run_dir: str
    plan_name: str
    instrument_serial: str | None
    operator: str | None
    status: str
    reason: str | None
    started_utc: str
    ended_utc: str | None
    points_ok: int
    points_failed: int


class JournalError(LabcalError):
    """The journal's database refused a read or a write (a full disk, a read-only, locked or damaged
    file): one line naming the file and what to do (`labcal.store.labdb.failure`)."""


class Journal:
    def __init__(self, path: str | Path, durable: bool = True):
        self.path = Path(path)
        self.db = labdb.connect(self.path)  # the schema, its version and its migrations live there
        if not durable:
            self.relax()

    def relax(self) -> None:
        """synchronous=NORMAL, for a dry run on the simulated rig: a commit no longer waits for its
        fsync (WAL still survives a killed process; only a power cut may lose the last points,
        which a dry run can make again). A calibration on hardware stays durable per point."""
        self.db.execute("PRAGMA synchronous=NORMAL")

    def close(self) -> None:
        self.db.close()

    @contextmanager
    def refusals(self) -> Iterator[None]:
        """Raise what the database refuses inside the block as `JournalError`, so that a caller that
        may go on without the write (the run machinery) catches one error type, not the driver's."""
        try:
            yield
        except sqlite3.Error as exc:
            raise JournalError(str(labdb.failure(self.path, exc))) from exc

    def __enter__(self) -> Journal:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _transaction(self, statements: list[tuple[str, tuple]] | Callable[[], list[tuple[str, tuple]]]
                     ) -> int | None:
        """Run statements atomically; a crash leaves all of them or none. A callable makes them
        under the write lock (what they write depends on what the journal holds)."""
        last = None
        try:
            self.db.execute("BEGIN IMMEDIATE")
            for sql, args in (statements() if callable(statements) else statements):
                last = self.db.execute(sql, args).lastrowid
            self.db.execute("COMMIT")
        except BaseException as exc:
            if self.db.in_transaction:  # a full disk has rolled it back already: say that, not this
                try:
                    self.db.execute("ROLLBACK")
                except sqlite3.Error:
                    pass
            if isinstance(exc, sqlite3.IntegrityError):
                raise
            if isinstance(exc, sqlite3.Error):
                raise labdb.failure(self.path, exc) from None
            raise
        return last

    # --- writing ---------------------------------------------------------------------------------
    def start_run(self, m: Manifest) -> int:
        """Journal a new run. It names its station and its number of steps here, in the journal
        itself, so that the lab's view (`labcal serve`) shows them on a SQLite lab database as on a
        server, where `labcal.store.sync` copies them. Its manifest's digest begins the run's chain
        (`labcal.store.chain`)."""
        values = {"uuid": str(uuid.uuid4()), "plan_name": m.plan_name, "plan_text": m.plan_text,
                  "station_text": m.station_text, "software_version": m.software_version,
                  "instrument_serial": m.instrument_serial, "device_id": m.device_id, "operator": m.operator,
                  "settings": json.dumps(m.settings), "metadata": json.dumps(m.metadata),
                  "started_utc": utc_now(), "station": m.station or station_name()}
        run_id = self._transaction([(
            "INSERT INTO runs (run_dir, plan_name, plan_text, plan_hash, station_text, station_hash,"
            " software_version, instrument_serial, device_id, operator, settings, metadata,"
            " started_utc, status, uuid, station, points_total, digest)"
            " VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,'running',?,?,?,?)",
            (m.run_dir, m.plan_name, m.plan_text, sha256(m.plan_text), m.station_text,
             sha256(m.station_text), m.software_version, m.instrument_serial, m.device_id, m.operator,
             values["settings"], values["metadata"], values["started_utc"], values["uuid"], values["station"],
             m.points_total if m.points_total is not None else schedule_length(m.plan_text),
             chain.manifest_digest(values)),
        )])
        assert run_id is not None  # an INSERT into a rowid table always sets lastrowid
        return run_id

    def _link(self, run_id: int, kind: str, values: dict[str, object]) -> tuple[int | None, str | None]:
        """The next record's link and digest in its run's chain, read inside the writing transaction
        (another connection may have appended to the run: the sender's outage event); (None, None)
        for a run journaled before digests, which stays unchained."""
        run = self.db.execute("SELECT uuid, digest FROM runs WHERE id=?", (run_id,)).fetchone()
        if run is None or run[1] is None:
            return None, None
        head = self.db.execute(
            "SELECT link, digest FROM (SELECT link, digest FROM points WHERE run_id=:r AND link IS NOT NULL"
            " ORDER BY link DESC LIMIT 1) UNION ALL SELECT link, digest FROM (SELECT link, digest FROM events"
            " WHERE run_id=:r AND link IS NOT NULL ORDER BY link DESC LIMIT 1) ORDER BY link DESC LIMIT 1",
            {"r": run_id}).fetchone()
        link, previous = (1, run[1]) if head is None else (head[0] + 1, head[1])
        return link, chain.digest(kind, run[0], link, previous, values)

    def record_point(self, run_id: int, point: PointRecord, samples: NDArray | None,
                     utc: str | None = None) -> None:
        """The point and its raw samples in one transaction (``utc``: when it was measured; now),
        chained to the run's previous record."""
        names = [f.name for f in fields(PointRecord)]
        values: dict[str, object] = {n: getattr(point, n) for n in names}
        values["utc"] = utc or utc_now()
        values["samples"] = None if samples is None else np.ascontiguousarray(samples, dtype="<f8").tobytes()
        columns = [*names, "utc", "samples"]

        def statements() -> list[tuple[str, tuple]]:
            link, digest = self._link(run_id, "point", values)
            return [(f"INSERT INTO points (run_id, {', '.join(columns)}, link, digest) VALUES "
                     f"(?, {', '.join('?' * len(columns))}, ?, ?)",
                     (run_id, *(values[c] for c in columns), link, digest))]
        self._transaction(statements)

    def supersede(self, run_id: int, seq: int) -> None:
        """A point measured again in its own right (a check of the run's readings named it): its
        reading stays, marked superseded, and no fit or export uses it."""
        self._transaction([("UPDATE points SET status='superseded' WHERE run_id=? AND seq=?", (run_id, seq))])

    def event(self, run_id: int, kind: str, message: str, data: dict | None = None,
              station_time: float | None = None, utc: str | None = None) -> None:
        """One event of the run, chained to its previous record."""
        values: dict[str, object] = {"utc": utc or utc_now(), "station_time": station_time, "kind": kind,
                                     "message": message, "data": None if data is None else json.dumps(data)}

        def statements() -> list[tuple[str, tuple]]:
            link, digest = self._link(run_id, "event", values)
            return [("INSERT INTO events (run_id, utc, station_time, kind, message, data, link, digest) "
                     "VALUES (?,?,?,?,?,?,?,?)",
                     (run_id, values["utc"], values["station_time"], kind, message, values["data"], link,
                      digest))]
        self._transaction(statements)

    def finish(self, run_id: int, status: str, reason: str | None = None,
               exports: dict[str, str] | None = None) -> None:
        """The run's status, and the SHA-256 of the exports just written for it, in one transaction:
        a run is marked complete only together with the hashes of the files that show it."""
        self._transaction([("UPDATE runs SET status=?, reason=?, ended_utc=? WHERE id=?",
                            (status, reason, utc_now(), run_id)),
                           *self._export_rows(run_id, exports or {})])

    def exported(self, run_id: int, exports: dict[str, str]) -> None:
        """Remember the hashes of exports rewritten for a run (status unchanged)."""
        if exports:
            self._transaction(self._export_rows(run_id, exports))

    @staticmethod
    def _export_rows(run_id: int, exports: dict[str, str]) -> list[tuple[str, tuple]]:
        return [("INSERT OR REPLACE INTO run_exports (run_id, name, sha256) VALUES (?,?,?)",
                 (run_id, name, digest)) for name, digest in exports.items()]

    def set_run_dir(self, run_id: int, run_dir: str) -> None:
        """Where the run's folder now is (`labcal export DIR` rebuilt it there, or `labcal resume DIR`
        went on with it there)."""
        self._transaction([("UPDATE runs SET run_dir=? WHERE id=?", (run_dir, run_id))])

    def reopen(self, run_id: int) -> None:
        self._transaction([("UPDATE runs SET status='running', reason=NULL, ended_utc=NULL WHERE id=?",
                            (run_id,))])

    # --- reading ---------------------------------------------------------------------------------
    def run(self, run_id: int) -> RunRow:
        cols = [f.name for f in fields(RunRow)]
        row = self.db.execute(f"SELECT {', '.join(cols)} FROM runs WHERE id=?", (run_id,)).fetchone()
        if row is None:
            raise LabcalError(f"{self.path}: no run {run_id} in this journal")
        values = dict(zip(cols, row, strict=True))
        for key in ("settings", "metadata"):
            values[key] = json.loads(values[key])
        return RunRow(**values)

    def runs(self, serial: str | None = None, statuses: tuple[str, ...] = ()) -> list[RunSummary]:
        """Every run of the lab, oldest first, optionally of one instrument and in some statuses,
        with its committed points counted (ok and failed)."""
        sql = ("SELECT r.id, r.run_dir, r.plan_name, r.instrument_serial, r.operator, r.status, r.reason,"
               " r.started_utc, r.ended_utc,"
               " (SELECT COUNT(*) FROM points p WHERE p.run_id = r.id AND p.status = 'ok'),"
               " (SELECT COUNT(*) FROM points p WHERE p.run_id = r.id AND p.status != 'ok')"
               " FROM runs r WHERE 1=1")
        args: list[object] = []
        if serial is not None:
            sql, args = sql + " AND r.instrument_serial = ?", [*args, serial]
        if statuses:
            sql += f" AND r.status IN ({', '.join('?' * len(statuses))})"
            args += list(statuses)
        return [RunSummary(*row) for row in self.db.execute(sql + " ORDER BY r.id", args).fetchall()]

    def points(self, run_id: int, status: str | None = None) -> list[PointRecord]:
        names = [f.name for f in fields(PointRecord)]
        sql = f"SELECT {', '.join(names)} FROM points WHERE run_id=?"
        args: tuple = (run_id,)
        if status:
            sql, args = sql + " AND status=?", (run_id, status)
        rows = self.db.execute(sql + " ORDER BY seq", args).fetchall()
        return [PointRecord(**dict(zip(names, r, strict=True))) for r in rows]

    def samples(self, run_id: int, seq: int) -> NDArray:
        row = self.db.execute("SELECT samples FROM points WHERE run_id=? AND seq=?", (run_id, seq)).fetchone()
        if row is None or row[0] is None:
            return np.empty((0, 4))
        return np.frombuffer(row[0], dtype="<f8").reshape(-1, 4)

    def export_hashes(self, run_id: int) -> dict[str, str]:
        """The SHA-256 of each file labcal last wrote into the run's folder."""
        rows = self.db.execute("SELECT name, sha256 FROM run_exports WHERE run_id=?", (run_id,)).fetchall()
        return dict(rows)

    def rig_time(self, run_id: int) -> float:
        """Rig time since the run began when it was last heard of: its last point or event. A resumed
        segment's clock starts here, so that time runs on, never back, across resumes."""
        row = self.db.execute("SELECT max(coalesce((SELECT max(t_end) FROM points WHERE run_id=?), 0.0),"
                              " coalesce((SELECT max(station_time) FROM events WHERE run_id=?), 0.0))",
                              (run_id, run_id)).fetchone()
        return float(row[0] or 0.0)

    def events(self, run_id: int) -> list[EventRow]:
        rows = self.db.execute("SELECT utc, station_time, kind, message, data FROM events WHERE run_id=? "
                               "ORDER BY id", (run_id,)).fetchall()
        return [EventRow.read(*row) for row in rows]

    def readings(self, run_id: int) -> Readings:
        """The committed good points as Readings (the export behind readings.csv and the fit)."""
        return readings_of(self.points(run_id, status="ok"), f"run {run_id}")


def readings_of(pts: list[PointRecord], run: str) -> Readings:
    """Committed good points as Readings, wherever they were read (a journal, the lab's copy)."""
    if not pts:
        raise LabcalError(f"{run} has no readings yet")
    temps = [p.temp_c for p in pts]
    return Readings(
        replicate=np.array([p.replicate for p in pts]),
        y_deg=np.array([p.y_deg for p in pts]), u_deg=np.array([p.u_deg for p in pts]),
        pitch_deg=np.array([p.pitch_deg for p in pts]), roll_deg=np.array([p.roll_deg for p in pts]),
        volts=np.array([[p.vx, p.vy, p.vz] for p in pts], dtype=float),  # NULL: NaN, an absent sensor
        temp_c=None if any(t is None for t in temps) else np.array(temps),
        window_sd=np.array([[p.sd_vx, p.sd_vy, p.sd_vz] for p in pts], dtype=float),
        window_n=np.array([p.n_samples for p in pts], dtype=float),
    )


"""The lab database's own copy of a run, and the files of the certificate the lab server approved
from it — what an approval on a PostgreSQL lab database reads and writes.

The lab database is the record: the server approves the run an approver named from the runs, points
and events rows the lab holds, never from a folder (whose run.json could name any journal). `lab_record`
builds the same `RunRecord` that `labcal.store.record.load_run` builds from a journal, with the lab's
chain of digests recomputed (`labcal.store.chain.check_server`); the signed certificate, its DCC and the
report are kept in ``certificate_files`` in the same transaction, and a bench writes them into its run
folder from there (`files_of`, `write_files`).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import fields
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.config.files import write_atomic
from labcal.errors import LabcalError
from labcal.store.chain import check_server
from labcal.store.exports import station_description
from labcal.store.journal import RunRow, readings_of
from labcal.store.lab_points import ok_points
from labcal.store.record import RunRecord, run_record
from labcal.store.rundir import identity

if TYPE_CHECKING:
    from sqlalchemy.engine import Connection, Engine

# What a server's approval keeps, in the order a bench writes them (the certificate, which says the
# run is approved, last: a bench killed while writing leaves a draft, never a half-approved folder)
FILES = ("certificate.dcc.xml", "report.html", "report.pdf", "certificate.json")


def lab_label(run_id: int) -> str:
    return f"run {run_id} of the lab"


def lock_run(connection: Connection, run_id: int) -> None:
    """Serialise approvals of one run across every server process: a transaction-scoped advisory lock
    (the server's role may not lock the runs row itself, which it may not update)."""
    from sqlalchemy import text

    connection.execute(text("SELECT pg_advisory_xact_lock(:k)"), {"k": 0x1ABCA1 * 1_000_000 + run_id})


def lab_record(connection: Connection, run_id: int, directory: Path) -> RunRecord:
    """Run ``run_id`` as the lab database holds it, as a `RunRecord` whose documents go to
    ``directory``; an unknown or unfinished run is one line."""
    from sqlalchemy import select

    from labcal.store.schema import events, runs

    columns = [f.name for f in fields(RunRow)]
    found = connection.execute(select(*(runs.c[c] for c in columns)).where(runs.c.id == run_id)).first()
    label = lab_label(run_id)
    if found is None:
        raise LabcalError(f"no {label}")
    values = dict(zip(columns, found, strict=True))
    values["settings"], values["metadata"] = json.loads(values["settings"]), json.loads(values["metadata"])
    row = RunRow(**values)
    if row.status != "complete":
        why = f" ({row.reason})" if row.reason else ""
        raise LabcalError(f"{label} is {row.status}{why}; only a complete run gets a certificate")
    said = connection.execute(select(events.c.utc, events.c.station_time, events.c.kind, events.c.message,
                                     events.c.data).where(events.c.run_id == run_id).order_by(events.c.id))
    logged = tuple({"utc": u, "station_time": t, "kind": k, "message": m,
                    "data": json.loads(d) if d else None} for u, t, k, m, d in said)
    # a point measured again in its own right: the lab's copy keeps it as sent (measured), and the
    # run's chained `remeasured` event says which reading replaced it, as the journal's mark does
    superseded = {int(e["data"]["seq"]) for e in logged
                  if e["kind"] == "remeasured" and isinstance(e["data"], dict) and "seq" in e["data"]}
    good = [p for p in ok_points(connection, run_id) if p.seq not in superseded]
    chain = check_server(connection, run_id, label)
    # what run.json says of the run (`labcal.store.exports`), which the lab keeps no copy of
    info = {"labcal_version": row.software_version, **identity(row), "plan": row.plan_name,
            "station": station_description(row), "settings": row.settings,
            **{k: v for k, v in row.metadata.items() if k != "station"}}
    return run_record(directory, row, info, good, readings_of(good, label), logged, chain, [], label,
                      "the lab's copy")


def draft_document(connection: Connection, serial: str | None, run_uuid: str, lock: bool = False
                   ) -> str | None:
    """The newest certificate the lab holds for the run (the draft its bench issued and synced), as
    JSON text; None when no bench has sent one. ``lock``: its rows locked until the caller's
    transaction ends (an approval), so that a draft the bench re-issues meanwhile is either the one
    read here or arrives after the approval, never lost between the two."""
    from sqlalchemy import select

    from labcal.store.schema import certificates

    # by the run it states, not its serial: a serial stripped or given at issue need not be the run's
    query = (select(certificates.c.document).where(certificates.c.document.contains(run_uuid))
             .order_by(certificates.c.issued_utc.desc()))
    rows = connection.execute(query.with_for_update() if lock else query).scalars()
    for document in rows:
        journal = ((json.loads(document).get("data") or {}).get("journal") or {})
        if journal.get("run_uuid") == run_uuid:
            return str(document)
    return None


def approved_by(connection: Connection, run_id: int) -> dict | None:
    """Who approved the run's certificate and when, as the lab knows it (its ``approval``: by, role,
    approved_utc, …): the server's approval kept in ``certificate_files``, else a bench's approved
    certificate synced to ``certificates``; None while only a draft (or nothing) is there."""
    from sqlalchemy import select

    from labcal.store.schema import certificate_files, runs

    found = connection.execute(select(runs.c.uuid, runs.c.instrument_serial)
                               .where(runs.c.id == run_id)).first()
    if found is None or found.uuid is None:
        return None
    content = connection.execute(select(certificate_files.c.content).where(
        certificate_files.c.run_uuid == found.uuid, certificate_files.c.name == "certificate.json")
        .order_by(certificate_files.c.stored_utc.desc())).scalars().first()
    if content is not None:
        return json.loads(bytes(content)).get("approval")
    document = draft_document(connection, found.instrument_serial, found.uuid)
    return None if document is None else json.loads(document).get("approval")


def store_files(connection: Connection, certificate_id: str, run_uuid: str, files: dict[str, bytes]) -> None:
    """Keep an approved certificate's files in the lab database (in the caller's transaction)."""
    from sqlalchemy import insert

    from labcal.store.schema import certificate_files

    now = datetime.now(UTC).isoformat()
    connection.execute(insert(certificate_files), [
        {"certificate_id": certificate_id, "run_uuid": run_uuid, "name": name,
         "sha256": hashlib.sha256(content).hexdigest(), "content": content, "stored_utc": now}
        for name, content in files.items()])


def replace_draft(connection: Connection, certificate_id: str, serial: str, calibrated_utc: str,
                  issued_utc: str, sha256: str, document: str) -> None:
    """The approved certificate in place of its draft in the lab's certificates (in the caller's
    transaction): every bench's history then shows it approved, and each bench's journal receives it
    on its next sync, as a bench's own approval reaches the lab."""
    from sqlalchemy.dialects.postgresql import insert

    from labcal.store.schema import certificates

    values = {"certificate_id": certificate_id, "serial": serial, "calibrated_utc": calibrated_utc,
              "issued_utc": issued_utc, "sha256": sha256, "document": document}
    statement = insert(certificates).values(**values)
    connection.execute(statement.on_conflict_do_update(
        index_elements=[certificates.c.certificate_id],
        set_={k: statement.excluded[k] for k in values if k != "certificate_id"}))


def files_of(connection: Connection, run_uuid: str) -> dict[str, bytes]:
    """The approved certificate's files the lab keeps for the run (empty: none approved there), each
    checked against the digest stored with it."""
    from sqlalchemy import select

    from labcal.store.schema import certificate_files

    found: dict[str, bytes] = {}
    for name, sha, content in connection.execute(select(
            certificate_files.c.name, certificate_files.c.sha256, certificate_files.c.content)
            .where(certificate_files.c.run_uuid == run_uuid).order_by(certificate_files.c.stored_utc)):
        data = bytes(content)
        if hashlib.sha256(data).hexdigest() != sha:
            raise LabcalError(f"the lab's {name} of run {run_uuid} does not match its stored digest")
        found[name] = data
    return found


def approved_files(engine: Engine, run_id: int) -> dict[str, bytes]:
    """`files_of` the lab's run ``run_id`` (empty: no such run, or none approved there)."""
    from sqlalchemy import select

    from labcal.store.schema import runs

    with engine.connect() as connection:
        uuid = connection.execute(select(runs.c.uuid).where(runs.c.id == run_id)).scalar()
        return {} if uuid is None else files_of(connection, uuid)


def file_names(connection: Connection, run_uuid: str) -> list[str]:
    """The names of the approved certificate's files the lab keeps for the run, sorted."""
    from sqlalchemy import select

    from labcal.store.schema import certificate_files

    return sorted(connection.execute(select(certificate_files.c.name)
                                     .where(certificate_files.c.run_uuid == run_uuid)).scalars())


def write_files(run_dir: Path, files: dict[str, bytes]) -> list[str]:
    """Write the approved files into a run's folder (atomically each, the certificate last); the
    names written (a file already identical is left alone)."""
    written = []
    for name in sorted((n for n in files if n in FILES), key=FILES.index):  # no other name lands there
        path = run_dir / name
        if path.is_file() and path.read_bytes() == files[name]:
            continue
        write_atomic(path, files[name])
        written.append(name)
    return written

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
from collections.abc import Collection, Iterable
from dataclasses import fields
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

import sqlalchemy
from sqlalchemy import func, insert, select

from labcal.config.files import write_atomic
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.chain import check_server
from labcal.store.exports import station_description
from labcal.store.journal import EventRow, RunRow, readings_of
from labcal.store.lab_points import ok_points
from labcal.store.record import RunRecord, run_record
from labcal.store.rundir import identity
from labcal.store.schema import certificate_files, certificates, events, runs

if TYPE_CHECKING:
    from sqlalchemy.dialects import postgresql
    from sqlalchemy.engine import Connection, Engine
else:
    postgresql = lazy("sqlalchemy.dialects.postgresql")  # start-up without sqlalchemy

# What a server's approval keeps, in the order a bench writes them (the certificate, which says the
# run is approved, last: a bench killed while writing leaves a draft, never a half-approved folder)
FILES = ("certificate.dcc.xml", "report.html", "report.pdf", "certificate.json")


def lab_label(run_id: int) -> str:
    return f"run {run_id} of the lab"


def lock_run(connection: Connection, run_id: int) -> None:
    """Serialise approvals of one run across every server process: a transaction-scoped advisory lock
    (the server's role may not lock the runs row itself, which it may not update)."""
    connection.execute(
        sqlalchemy.text("SELECT pg_advisory_xact_lock(:k)"), {"k": 0x1ABCA1 * 1_000_000 + run_id}
    )


def lab_record(connection: Connection, run_id: int, directory: Path) -> RunRecord:
    """Run ``run_id`` as the lab database holds it, as a `RunRecord` whose documents go to
    ``directory``; an unknown or unfinished run is one line."""
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
    logged = tuple(EventRow.read(*row) for row in said)
    # a point measured again in its own right: the lab's copy keeps it as sent (measured), and the
    # run's chained `remeasured` event says which reading replaced it, as the journal's mark does
    superseded = {int(e.values["seq"]) for e in logged if e.kind == "remeasured" and "seq" in e.values}
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
    # by the run it states, not its serial: a serial stripped or given at issue need not be the run's
    query = (select(certificates.c.document).where(certificates.c.document.contains(run_uuid))
             .order_by(certificates.c.issued_utc.desc()))
    rows = connection.execute(query.with_for_update() if lock else query).scalars()
    for document in rows:
        journal = ((json.loads(document).get("data") or {}).get("journal") or {})
        if journal.get("run_uuid") == run_uuid:
            return str(document)
    return None


def _number(document: dict) -> str:
    """A certificate's number with its revision, as `labcal.documents.certificate.Certificate.number`
    prints it (what a later revision's ``replaces`` names)."""
    name = document.get("lab_number") or document.get("certificate_id")
    return f"{name} rev. {document.get('revision') or 1}"


def _in_force(rows: Iterable[tuple[str, str]], run_uuids: Collection[str]) -> dict[str, dict]:
    """Of the certificates ``rows`` (issued_utc, document), the revision in force for each of the runs
    ``run_uuids`` that has one, as its parsed JSON (read, not verified): the newest issue that no
    other revision of the run replaces."""
    by_run: dict[str, list[tuple[tuple[str, int], dict]]] = {}
    for issued, text in rows:
        try:
            document = json.loads(text)
            run_uuid = ((document.get("data") or {}).get("journal") or {}).get("run_uuid")
        except (ValueError, AttributeError):
            continue
        if isinstance(run_uuid, str) and run_uuid in run_uuids:
            order = (str(issued), int(document.get("revision") or 1))
            by_run.setdefault(run_uuid, []).append((order, document))
    found = {}
    for run_uuid, held in by_run.items():
        replaced = {d.get("replaces") for _, d in held if d.get("replaces")}
        live = [(k, d) for k, d in held if _number(d) not in replaced] or held
        found[run_uuid] = max(live, key=lambda kd: kd[0])[1]
    return found


def _approvals(connection: Connection, in_force: dict[str, dict]) -> dict[str, dict]:
    """Who approved each run's certificate in force (its ``approval``), for the runs whose certificate
    in force is approved: the server's signed copy in ``certificate_files`` where it kept one (one
    statement for all of them), else the document's own (a bench's approval, synced)."""
    ids = {str(d.get("certificate_id")): run_uuid for run_uuid, d in in_force.items()}
    found = {run_uuid: d["approval"] for run_uuid, d in in_force.items() if d.get("approval")}
    if ids:
        for cid, content in connection.execute(select(certificate_files.c.certificate_id,
                                                      certificate_files.c.content).where(
                certificate_files.c.certificate_id.in_(ids), certificate_files.c.name == "certificate.json")):
            approval = json.loads(bytes(content)).get("approval")
            if approval:
                found[ids[cid]] = approval
    return found


def in_force(connection: Connection, run_uuid: str) -> dict | None:
    """The run's certificate in force (`_in_force`) as the lab holds it; None: none issued."""
    # by the run it states, not its serial: a serial stripped or given at issue need not be the run's
    rows = connection.execute(select(certificates.c.issued_utc, certificates.c.document)
                              .where(certificates.c.document.contains(run_uuid))).all()
    return _in_force(rows, {run_uuid}).get(run_uuid)


def replaced_document(connection: Connection, run_uuid: str, number: str) -> bytes | None:
    """The run's certificate numbered ``number`` (a revision's ``replaces``) as the lab keeps it: the
    server's signed copy where it approved that revision, else the lab's certificates row; None: the
    lab holds no such revision of the run."""
    for text in connection.execute(select(certificates.c.document)
                                   .where(certificates.c.document.contains(run_uuid))).scalars():
        document = _in_force([("", text)], {run_uuid}).get(run_uuid)
        if document is None or _number(document) != number:
            continue
        kept = connection.execute(select(certificate_files.c.content).where(
            certificate_files.c.certificate_id == str(document.get("certificate_id")),
            certificate_files.c.name == "certificate.json")).scalar()
        return bytes(kept) if kept is not None else str(text).encode("utf-8")
    return None


def approved_by(connection: Connection, run_id: int) -> dict | None:
    """Who approved the run's certificate in force and when, as the lab knows it (its ``approval``:
    by, role, approved_utc, …); None while that revision is a draft (or nothing is there). A later
    revision of an approved certificate is a draft again until it is approved itself."""
    uuid = connection.execute(select(runs.c.uuid).where(runs.c.id == run_id)).scalar()
    if uuid is None:
        return None
    document = in_force(connection, str(uuid))
    return None if document is None else _approvals(connection, {str(uuid): document}).get(str(uuid))


def approved_runs(connection: Connection, run_uuids: Collection[str]) -> dict[str, dict]:
    """`approved_by` for many runs at once, by uuid (only the approved ones): two statements whatever
    their number — the lab's certificates read once, not searched once per run."""
    wanted = set(run_uuids)
    if not wanted:
        return {}
    rows = connection.execute(select(certificates.c.issued_utc, certificates.c.document)).all()
    return _approvals(connection, _in_force(rows, wanted))


def store_files(connection: Connection, certificate_id: str, run_uuid: str, files: dict[str, bytes]) -> None:
    """Keep an approved certificate's files in the lab database (in the caller's transaction)."""
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
    values = {"certificate_id": certificate_id, "serial": serial, "calibrated_utc": calibrated_utc,
              "issued_utc": issued_utc, "sha256": sha256, "document": document}
    statement = postgresql.insert(certificates).values(**values)
    connection.execute(statement.on_conflict_do_update(
        index_elements=[certificates.c.certificate_id],
        set_={k: statement.excluded[k] for k in values if k != "certificate_id"}))


def files_of(connection: Connection, run_uuid: str) -> dict[str, bytes]:
    """The files the lab keeps of the run's certificate in force, approved by the server (empty: that
    revision is not, or there is none), each checked against the digest stored with it."""
    document = in_force(connection, run_uuid)
    if document is None:
        return {}
    found: dict[str, bytes] = {}
    for name, sha, content in connection.execute(select(
            certificate_files.c.name, certificate_files.c.sha256, certificate_files.c.content)
            .where(certificate_files.c.certificate_id == str(document.get("certificate_id")))):
        data = bytes(content)
        if hashlib.sha256(data).hexdigest() != sha:
            raise LabcalError(f"the lab's {name} of run {run_uuid} does not match its stored digest")
        found[name] = data
    return found


def approved_files(engine: Engine, run_id: int) -> dict[str, bytes]:
    """`files_of` the lab's run ``run_id`` (empty: no such run, or none approved there)."""
    with engine.connect() as connection:
        uuid = connection.execute(select(runs.c.uuid).where(runs.c.id == run_id)).scalar()
        return {} if uuid is None else files_of(connection, uuid)


def file_names(connection: Connection, run_uuid: str) -> list[str]:
    """The names of the files the lab keeps of the run's certificate in force, approved by the
    server, sorted."""
    document = in_force(connection, run_uuid)
    return [] if document is None else sorted(connection.execute(select(certificate_files.c.name).where(
        certificate_files.c.certificate_id == str(document.get("certificate_id")))).scalars())


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


def run_documents(connection: Connection, run_uuid: str) -> list[tuple[str, str | bytes]]:
    """Every certificate document the lab holds that may be the run's (certificate id, document): the
    certificates rows naming its uuid, and the server's signed copies kept for it; unverified."""
    rows = connection.execute(select(certificates.c.certificate_id, certificates.c.document)
                              .where(certificates.c.document.contains(run_uuid))).all()
    stored = connection.execute(select(certificate_files.c.certificate_id, certificate_files.c.content).where(
        certificate_files.c.run_uuid == run_uuid, certificate_files.c.name == "certificate.json")).all()
    return [*((c, d) for c, d in rows), *((c, bytes(d)) for c, d in stored)]


def serial_documents(connection: Connection, serial: str) -> list[tuple[str, str]]:
    """Every certificate (id, document) the lab holds under ``serial``, whatever its case (a
    certificate issued as acc-0042 before the register held ACC-0042 is its too); unverified."""
    query = (select(certificates.c.certificate_id, certificates.c.document)
             .where(func.lower(certificates.c.serial) == serial.lower()))
    return [(c, d) for c, d in connection.execute(query)]


def certificate_text(connection: Connection, certificate_id: str) -> str | None:
    """The lab's certificates row's document of ``certificate_id`` (None: none)."""
    return connection.execute(select(certificates.c.document)
                              .where(certificates.c.certificate_id == certificate_id)).scalar()


def kept_names(connection: Connection, certificate_id: str) -> set[str]:
    """The names of the files the server kept of certificate ``certificate_id`` when it approved it."""
    return set(connection.execute(select(certificate_files.c.name)
                                  .where(certificate_files.c.certificate_id == certificate_id)).scalars())


def kept_file(connection: Connection, certificate_id: str, name: str) -> bytes | None:
    """The file ``name`` the server kept of certificate ``certificate_id``, where its stored digest
    holds (None: none kept, or not intact)."""
    stored = connection.execute(select(certificate_files.c.content, certificate_files.c.sha256).where(
        certificate_files.c.certificate_id == certificate_id, certificate_files.c.name == name)).first()
    if stored is None or hashlib.sha256(bytes(stored.content)).hexdigest() != stored.sha256:
        return None
    return bytes(stored.content)

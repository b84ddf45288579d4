"""Who may write what in a PostgreSQL lab database: each bench a role of its own, the server another.

Two group roles, made by `labcal db upgrade` (idempotently, with every grant and policy below):

- ``labcal_bench``, the group of every bench's role (`grant_station`). It reads the lab's record
  (runs, points, events, certificates, device estimates, settle pools) and appends to it only what
  its own station measured: row-level security lets it insert a run only under its own station's
  name (``station_roles`` maps its role to that name) and points and events only into its own
  station's runs, and update only its own runs' status (a run's end); it appends and re-issues only its
  own station's draft certificates, never an approved one. It cannot update or delete a point or an
  event, and it has no privilege at all on users, approvers, approvals or any table not
  named here — a table added later is closed to it until a grant says otherwise.
- ``labcal_server``, the lab server's: it reads everything (it signs users in and checks approvers)
  and alone writes the approvals (the approved certificates).

The database's owner (the lab's administrator, who runs `labcal db upgrade` and `labcal db
grant-station`) keeps every privilege; row-level security does not bind a table's owner.

A bench role's password, where the server's authentication asks for one, never travels in clear:
the role is given a SCRAM-SHA-256 verifier computed here (RFC 5802 §3, RFC 7677), so the password
is in neither the server's statement log nor the URL the command prints.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import re
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.config.lab import ServerDatabase
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labdb

if TYPE_CHECKING:
    import sqlalchemy
    from sqlalchemy import engine as sqlalchemy_engine
    from sqlalchemy import exc as sqlalchemy_exc
    from sqlalchemy.engine import Connection
else:
    sqlalchemy = lazy("sqlalchemy")  # start-up without sqlalchemy
    sqlalchemy_engine = lazy("sqlalchemy.engine")  # start-up without sqlalchemy
    sqlalchemy_exc = lazy("sqlalchemy.exc")  # start-up without sqlalchemy

BENCH = "labcal_bench"
SERVER = "labcal_server"
BENCH_PREFIX = "labcal_bench_"

# What each group may do, table by table (a table this labcal's schema lacks is passed over)
# The approvers register is read by every bench (`certificate verify` and `attitude --cert` check a
# signature against it): names, roles and public keys, nothing secret; only the administrator writes it.
# The files of a certificate the server approved are read by the bench that measured the run.
BENCH_READS = ("alembic_version", "runs", "points", "events", "certificates", "certificate_files",
               "run_exports", "device_estimates", "settle_pools", "station_roles", "approvers", "instruments",
               "standards", "standard_overrides", "certificate_numbers")
# a bench numbers the certificates of its runs in the lab's one gap-free sequence (a run's number, once)
BENCH_APPENDS = ("runs", "points", "events", "certificates", "device_estimates", "settle_pools",
                 "certificate_numbers")
# What a bench sends again when it changes (the sync's records): its own station's draft certificate
# re-issued (row-level security: `OWN_DRAFT`), a device estimate stored again, a settle pool that grew.
# Row-level security does not yet tie the estimates and pools to the station.
BENCH_REPLACES = ("certificates", "device_estimates", "settle_pools")
BENCH_CLOSES_RUNS = ("status", "reason", "ended_utc", "points_total")  # what a sync updates of its run
SERVER_WRITES = ("certificates", "approvals", "certificate_files")
SERVER_APPENDS = ("audit",)  # its audit trail: sign-ins, failures, lockouts, refusals, approvals
# serial keys a bench's inserts draw from
SEQUENCES = (("runs", "id"), ("events", "id"), ("certificate_numbers", "id"))
OWN_STATION = "(SELECT s.station FROM station_roles s WHERE s.role = current_user)"
# A certificate row is judged by its document alone (the columns beside it are copies a bench could
# set apart from it): a draft carries no "approval"; its run is the one its journal chain names.
# A draft of a run journaled before digests names no run, so it belongs to no station: the lab's
# administrator, not a bench's role, sends it.
OWN_DRAFT = ("((document::jsonb -> 'approval') IS NULL AND EXISTS (SELECT 1 FROM runs r WHERE "
             f"r.uuid = document::jsonb #>> '{{data,journal,run_uuid}}' AND r.station = {OWN_STATION}))")

POLICIES: tuple[tuple[str, str, str], ...] = (  # (table, name, definition after "ON table")
    ("runs", "labcal_read", f"FOR SELECT TO {BENCH}, {SERVER} USING (true)"),
    ("runs", "labcal_bench_append", f"FOR INSERT TO {BENCH} WITH CHECK (station = {OWN_STATION})"),
    ("runs", "labcal_bench_close",
     f"FOR UPDATE TO {BENCH} USING (station = {OWN_STATION}) WITH CHECK (station = {OWN_STATION})"),
    ("points", "labcal_read", f"FOR SELECT TO {BENCH}, {SERVER} USING (true)"),
    ("points", "labcal_bench_append", f"FOR INSERT TO {BENCH} WITH CHECK (EXISTS (SELECT 1 FROM runs r "
                                      f"WHERE r.id = points.run_id AND r.station = {OWN_STATION}))"),
    ("events", "labcal_read", f"FOR SELECT TO {BENCH}, {SERVER} USING (true)"),
    ("events", "labcal_bench_append", f"FOR INSERT TO {BENCH} WITH CHECK (EXISTS (SELECT 1 FROM runs r "
                                      f"WHERE r.id = events.run_id AND r.station = {OWN_STATION}))"),
    # a bench appends and re-issues its own station's drafts; an approved certificate, whoever's run
    # it is, is the server's alone (an upsert over one is refused, a plain UPDATE finds no row)
    ("certificates", "labcal_read", f"FOR SELECT TO {BENCH}, {SERVER} USING (true)"),
    ("certificates", "labcal_bench_append", f"FOR INSERT TO {BENCH} WITH CHECK {OWN_DRAFT}"),
    ("certificates", "labcal_bench_redraft",
     f"FOR UPDATE TO {BENCH} USING {OWN_DRAFT} WITH CHECK {OWN_DRAFT}"),
    ("certificates", "labcal_server_approve", f"FOR ALL TO {SERVER} USING (true) WITH CHECK (true)"),
)


def _tables(connection: Connection) -> set[str]:
    return set(sqlalchemy.inspect(connection).get_table_names())


def grants(tables: set[str]) -> list[str]:
    """The statements that set the two groups' privileges to exactly these (all revoked first)."""
    def present(names: tuple[str, ...]) -> str:
        return ", ".join(n for n in names if n in tables)

    statements = [f"REVOKE ALL ON {', '.join(sorted(tables))} FROM {BENCH}, {SERVER}",
                  f"GRANT USAGE ON SCHEMA public TO {BENCH}, {SERVER}",
                  f"GRANT SELECT ON {present(BENCH_READS)} TO {BENCH}",
                  f"GRANT INSERT ON {present(BENCH_APPENDS)} TO {BENCH}",
                  f"GRANT UPDATE ({', '.join(BENCH_CLOSES_RUNS)}) ON runs TO {BENCH}",
                  f"GRANT UPDATE ON {present(BENCH_REPLACES)} TO {BENCH}",
                  f"GRANT SELECT ON {', '.join(sorted(tables))} TO {SERVER}",
                  f"GRANT INSERT, UPDATE ON {present(SERVER_WRITES)} TO {SERVER}"]
    if "audit" in tables:
        statements += [f"GRANT INSERT ON {present(SERVER_APPENDS)} TO {SERVER}",
                       f"GRANT USAGE ON SEQUENCE audit_id_seq TO {SERVER}"]
    if "users" in tables:  # who the server signed for, and when they could (`certificate verify`): no hashes
        statements.append(f"GRANT SELECT (id, name, role, created_utc, disabled_utc) ON users TO {BENCH}")
    statements += [f"GRANT USAGE ON SEQUENCE {sequence} TO {BENCH}" for sequence in
                   (f"{table}_{column}_seq" for table, column in SEQUENCES)]
    # the lab's run number is max + 1 under a lock, and the column's sequence is moved past it
    # (`labcal.store.sync.lab_number`): setval needs UPDATE on the sequence
    statements.append(f"GRANT UPDATE ON SEQUENCE runs_id_seq TO {BENCH}")
    for table in sorted({t for t, _, _ in POLICIES}):
        statements.append(f"ALTER TABLE {table} ENABLE ROW LEVEL SECURITY")
    for table, name, definition in POLICIES:
        statements += [f"DROP POLICY IF EXISTS {name} ON {table}",
                       f"CREATE POLICY {name} ON {table} {definition}"]
    return statements


def create_role(name: str, attributes: str) -> str:
    """CREATE ROLE, unless it exists (roles belong to the whole server, shared by its databases).
    ``name`` is one of this module's identifiers (letters, digits, underscores), never a quoted one."""
    return (f"DO $$ BEGIN IF NOT EXISTS (SELECT FROM pg_roles WHERE rolname = '{name}') "
            f"THEN CREATE ROLE {name} {attributes}; END IF; END $$")


def setup(connection: Connection) -> None:
    """The group roles, their grants and the row-level security policies, as this module's docstring
    says (idempotent: run by every `labcal db upgrade` on a server, inside its transaction)."""
    for group in (BENCH, SERVER):
        connection.exec_driver_sql(create_role(group, "NOLOGIN"))
    database = connection.execute(sqlalchemy.text("SELECT current_database()")).scalar_one()
    connection.exec_driver_sql(f'GRANT CONNECT ON DATABASE "{database}" TO {BENCH}, {SERVER}')
    for statement in grants(_tables(connection)):
        connection.exec_driver_sql(statement)


def set_up(server: ServerDatabase) -> str:
    """`setup` on the lab's server, under the lock its schema is upgraded under (`labcal db upgrade`,
    once the schema is current), in one line: set up, or why not (a user who may upgrade the schema
    but not create roles is told what is left undone, and nothing of it is done)."""
    engine = labdb.server_engine(server)
    try:
        with engine.begin() as connection:
            connection.execute(sqlalchemy.text("SELECT pg_advisory_xact_lock(:key)"), {"key": labdb.PG_LOCK})
            setup(connection)
    except sqlalchemy_exc.DBAPIError as exc:
        if exc.connection_invalidated or labdb._is_connection_error(exc):
            raise labdb.unreachable(server, exc) from None
        return (f"the roles {BENCH} and {SERVER} and their policies are not set up "
                f"({labdb._first_line(getattr(exc, 'orig', None) or exc)}); run labcal db upgrade as the lab "
                "database's administrator")
    finally:
        engine.dispose()
    return f"the roles {BENCH} and {SERVER} and their grants and policies are set up"


def role_name(name: str, prefix: str = BENCH_PREFIX) -> str:
    """The role of a bench (``labcal_bench_``) or a server: the prefix and the name in lower-case
    letters, digits and underscores (PostgreSQL's unquoted identifiers), at most 63 bytes."""
    slug = re.sub(r"[^a-z0-9_]+", "_", name.strip().lower()).strip("_")
    if not slug:
        raise LabcalError(f"{name!r}: give a name of letters or digits (a station's as its bench's "
                          "LABCAL_STATION or lab file says)")
    return (prefix + slug)[:63]


def scram_verifier(password: str, salt: bytes | None = None, iterations: int = 4096) -> str:
    """What PostgreSQL keeps of a SCRAM-SHA-256 password (RFC 5802 §3): the salted password's
    StoredKey and ServerKey, never the password itself."""
    salt = os.urandom(16) if salt is None else salt
    salted = hashlib.pbkdf2_hmac("sha256", password.encode("utf-8"), salt, iterations)
    client_key = hmac.new(salted, b"Client Key", "sha256").digest()
    stored_key = hashlib.sha256(client_key).digest()
    server_key = hmac.new(salted, b"Server Key", "sha256").digest()
    b64 = lambda data: base64.b64encode(data).decode("ascii")  # noqa: E731
    return f"SCRAM-SHA-256${iterations}:{b64(salt)}${b64(stored_key)}:{b64(server_key)}"


def bench_url(admin: ServerDatabase, role: str) -> str:
    """The URL a bench sets as LABCAL_DB: the administrator's, with the bench's role and no password."""
    scheme, _, rest = admin.url.partition("://")
    _, _, where = rest.rpartition("@")
    return f"{scheme}://{role}@{where}"


def pgpass_line(admin: ServerDatabase, role: str, password: str) -> str:
    """The bench's password as libpq's password file holds it (PGPASSFILE): host:port:db:user:password."""
    url = sqlalchemy_engine.make_url(admin.sqlalchemy_url)
    escape = lambda value: str(value).replace("\\", "\\\\").replace(":", "\\:")  # noqa: E731
    return ":".join(escape(v) for v in (url.host or "localhost", url.port or 5432, url.database or "*",
                                        role, password)) + "\n"


@dataclass(frozen=True)
class Granted:
    station: str  # the station's name (a server's: the name given)
    role: str
    url: str  # for the bench's (or the server's) LABCAL_DB, without a password
    password_file: Path | None  # where its password was written (owner-only), if one was made
    password_set: bool


def write_owner_only(path: Path, text: str) -> None:
    """A new file only its owner may read (never overwriting one)."""
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise LabcalError(f"{path}: already exists; a password file is never overwritten (choose another)") \
            from None
    except OSError as exc:
        raise LabcalError(f"{path}: cannot write the password file ({exc.strerror})") from None
    with os.fdopen(fd, "w", encoding="utf-8") as out:
        out.write(text)


def grant_station(admin: ServerDatabase, station: str, password: str | None = None,
                  password_file: Path | None = None) -> Granted:
    """Create (or bring up to date) the role of ``station``'s bench, as the lab's administrator: LOGIN,
    a member of ``labcal_bench``, mapped to the station; with ``password`` (given) or a new one
    written to ``password_file`` in libpq's password-file form; with neither, no password (for a
    server that authenticates benches otherwise: certificates, peer, or a trusted network)."""
    return _grant(admin, station, BENCH, role_name(station), password, password_file)


def grant_server(admin: ServerDatabase, name: str, password: str | None = None,
                 password_file: Path | None = None) -> Granted:
    """The lab server's role (``labcal_server_NAME``, a member of ``labcal_server``), as `grant_station`
    makes a bench's: it reads the whole lab database and alone writes the approvals."""
    return _grant(admin, name, SERVER, role_name(name, SERVER + "_"), password, password_file)


def _grant(admin: ServerDatabase, name: str, group: str, role: str, password: str | None,
           password_file: Path | None) -> Granted:
    if password_file is not None and password is None:
        password = secrets.token_urlsafe(24)
        if password_file.exists():
            raise LabcalError(f"{password_file}: already exists; a password file is never overwritten "
                              "(choose another)")
    labdb.upgrade(admin)  # the schema current, the groups and their policies in place
    note = set_up(admin)
    if "not set up" in note:
        raise LabcalError(f"{admin}: {note}")
    engine = labdb.server_engine(admin)
    try:
        with engine.begin() as connection:
            other = connection.execute(sqlalchemy.text("SELECT station FROM station_roles WHERE role = :r"),
                                       {"r": role}).scalar_one_or_none()
            if other is not None and other != name:
                raise LabcalError(f"{name!r}: its role {role} already belongs to the station {other!r}; "
                                  "give the station a name that differs in letters or digits")
            connection.exec_driver_sql(create_role(role, "LOGIN"))
            connection.exec_driver_sql(f"ALTER ROLE {role} LOGIN NOSUPERUSER NOCREATEDB NOCREATEROLE "
                                       "NOBYPASSRLS")
            connection.exec_driver_sql(f"GRANT {group} TO {role}")
            if password is not None:  # the verifier is base64 with $ and :, never a quote
                connection.exec_driver_sql(f"ALTER ROLE {role} PASSWORD '{scram_verifier(password)}'")
            if group == BENCH:
                connection.execute(
                    sqlalchemy.text(
                        "INSERT INTO station_roles (role, station) VALUES (:r, :s) "
                        "ON CONFLICT (role) DO UPDATE SET station = excluded.station"
                    ),
                    {"r": role, "s": name},
                )
    except sqlalchemy_exc.SQLAlchemyError as exc:
        raise LabcalError(
            f"{admin}: cannot grant {name!r} a role "
            f"({labdb._first_line(getattr(exc, 'orig', None) or exc)}); run this as the lab "
            "database's administrator (its owner, allowed to create roles)"
        ) from None
    finally:
        engine.dispose()
    if password_file is not None and password is not None:
        write_owner_only(password_file, pgpass_line(admin, role, password))
    return Granted(name, role, bench_url(admin, role), password_file, password is not None)

"""The lab database's schema, once, for SQLite and PostgreSQL alike (SQLAlchemy Core).

`METADATA` is the schema at the newest revision; `labcal/store/migrations/` (Alembic) is its history,
revision by revision, and is what creates and upgrades a database of either backend: a new database
and an upgraded one cannot differ, because both are made by the same steps. A test checks that the
migrations arrive at exactly `METADATA` (tables, columns, types, indexes), so neither can drift.

Column names are the journal's (`vx`, `vy`, `vz`, `sd_vx`, …) on both backends: the readings a
PostgreSQL query returns are named as in readings.csv and in the station's own journal.
"""

from __future__ import annotations

from sqlalchemy import (
    Column,
    Float,
    ForeignKey,
    Index,
    Integer,
    LargeBinary,
    MetaData,
    PrimaryKeyConstraint,
    Table,
    Text,
    UniqueConstraint,
    text,
)

METADATA = MetaData()

runs = Table(
    "runs", METADATA,
    Column("id", Integer, primary_key=True),
    Column("run_dir", Text, nullable=False),
    Column("plan_name", Text, nullable=False),
    Column("plan_text", Text, nullable=False),
    Column("plan_hash", Text, nullable=False),
    Column("station_text", Text, nullable=False),
    Column("station_hash", Text, nullable=False),
    Column("software_version", Text, nullable=False),
    Column("instrument_serial", Text),
    Column("device_id", Text),
    Column("operator", Text),
    Column("settings", Text, nullable=False),
    Column("metadata", Text, nullable=False),
    Column("started_utc", Text, nullable=False),
    Column("status", Text, nullable=False),
    Column("reason", Text),
    Column("ended_utc", Text),
    Column("uuid", Text),
    # revision 0006: the lab as a whole
    Column("station", Text),  # the station's name (its lab-wide identity), for the lab's view
    Column("points_total", Integer),  # every point of the run's schedule, for "N / TOTAL"
    # revision 0008: the digest of the run's manifest, link 0 of its chain (`labcal.store.chain`)
    Column("digest", Text),
    Index("runs_by_uuid", "uuid", unique=True),
)

points = Table(
    "points", METADATA,
    Column("run_id", Integer, ForeignKey("runs.id"), nullable=False),
    Column("seq", Integer, nullable=False),
    Column("replicate", Integer, nullable=False),
    Column("y_deg", Float, nullable=False),
    Column("u_deg", Float, nullable=False),
    Column("pitch_deg", Float, nullable=False),
    Column("roll_deg", Float, nullable=False),
    Column("pitch_read", Float),
    Column("roll_read", Float),
    Column("attempt", Integer, nullable=False),
    Column("status", Text, nullable=False),
    Column("t_start", Float),
    Column("t_end", Float),
    Column("utc", Text, nullable=False),
    Column("n_samples", Integer, nullable=False),
    Column("vx", Float), Column("vy", Float), Column("vz", Float),
    Column("sd_vx", Float), Column("sd_vy", Float), Column("sd_vz", Float),
    Column("temp_c", Float),
    Column("settle_s", Float),
    Column("settle_verdict", Text),
    Column("samples", LargeBinary),
    Column("link", Integer),  # revision 0008: its place in the run's chain, and its chained digest
    Column("digest", Text),
    PrimaryKeyConstraint("run_id", "seq"),
    Index("points_by_link", "run_id", "link", unique=True),
)

events = Table(
    "events", METADATA,
    Column("id", Integer, primary_key=True),
    Column("run_id", Integer, ForeignKey("runs.id"), nullable=False),
    Column("utc", Text, nullable=False),
    Column("station_time", Float),
    Column("kind", Text, nullable=False),
    Column("message", Text, nullable=False),
    Column("data", Text),
    Column("origin_id", Integer),  # revision 0007: its id in the station's journal (NULL there)
    Column("link", Integer),  # revision 0008: its place in the run's chain, and its chained digest
    Column("digest", Text),
    Index("events_by_run", "run_id", "id"),
    Index("events_by_origin", "run_id", "origin_id", unique=True),
    Index("events_by_link", "run_id", "link", unique=True),
)

certificates = Table(
    "certificates", METADATA,
    Column("certificate_id", Text, primary_key=True),
    Column("serial", Text, nullable=False),
    Column("calibrated_utc", Text, nullable=False),
    Column("issued_utc", Text, nullable=False),
    Column("sha256", Text, nullable=False),
    Column("document", Text, nullable=False),
    Index("certificates_by_serial", "serial", "calibrated_utc"),
)

run_exports = Table(
    "run_exports", METADATA,
    Column("run_id", Integer, ForeignKey("runs.id"), nullable=False),
    Column("name", Text, nullable=False),
    Column("sha256", Text, nullable=False),
    PrimaryKeyConstraint("run_id", "name"),
)

device_estimates = Table(
    "device_estimates", METADATA,
    Column("device_id", Text, nullable=False),
    Column("source", Text, nullable=False),
    Column("calibrated_utc", Text, nullable=False),
    Column("stored_utc", Text, nullable=False),
    Column("document", Text, nullable=False),
    PrimaryKeyConstraint("device_id", "source"),
    Index("device_estimates_by_date", "device_id", "calibrated_utc"),
)

# A revoked row stays (it names who signed the certificates of the past); a name is active at most
# once and a key is registered once, ever: a key never signs under two names, a revoked key never
# comes back.
approvers = Table(
    "approvers", METADATA,
    Column("id", Integer, primary_key=True),
    Column("name", Text, nullable=False),
    Column("role", Text, nullable=False),
    Column("public_key", Text, nullable=False),
    Column("key_id", Text, nullable=False, unique=True),
    Column("added_utc", Text, nullable=False),
    Column("revoked_utc", Text),
    Index("approvers_active_name", "name", unique=True,
          sqlite_where=text("revoked_utc IS NULL"), postgresql_where=text("revoked_utc IS NULL")),
)

settle_pools = Table(
    "settle_pools", METADATA,
    Column("pool_key", Text, primary_key=True),
    Column("identity", Text, nullable=False),
    Column("records", Integer, nullable=False),
    Column("sources", Text, nullable=False),
    Column("mismatch", Text, nullable=False),
    Column("sums", LargeBinary, nullable=False),
    Column("updated_utc", Text, nullable=False),
)

# Revision 0006: the lab server's users. Passwords and API tokens are kept only as hashes
# (argon2 for the password; SHA-256 of a 256-bit random token, which needs no slow hash to resist
# guessing); `role` is technician, approver or viewer. A disabled user stays, like a revoked approver.
users = Table(
    "users", METADATA,
    Column("id", Integer, primary_key=True),
    Column("name", Text, nullable=False, unique=True),
    Column("role", Text, nullable=False),
    Column("password_hash", Text, nullable=False),
    Column("token_hash", Text, nullable=False, unique=True),
    Column("created_utc", Text, nullable=False),
    Column("disabled_utc", Text),
    Column("token_utc", Text),  # revision 0010: when the API token was issued (NULL: when added)
)

# Revision 0007: in a station's journal, how far its records have been sent to each lab database
# (`labcal.store.sync`): ``target`` names the database, ``name`` the table (points, events,
# certificates), ``position`` the last rowid sent; and each run's id in that database, with what
# was last sent of its status ("status|reason|ended_utc|points_total|station").
sync_cursors = Table(
    "sync_cursors", METADATA,
    Column("target", Text, nullable=False),
    Column("name", Text, nullable=False),
    Column("position", Integer, nullable=False),
    PrimaryKeyConstraint("target", "name"),
)

sync_runs = Table(
    "sync_runs", METADATA,
    Column("target", Text, nullable=False),
    Column("run_id", Integer, ForeignKey("runs.id"), nullable=False),
    Column("lab_run_id", Integer, nullable=False),
    Column("sent", Text, nullable=False),
    PrimaryKeyConstraint("target", "run_id"),
)

# Revision 0008: on a PostgreSQL lab database, the station each bench's role may append runs for
# (`labcal db grant-station`); row-level security keys on it. Empty on SQLite.
station_roles = Table(
    "station_roles", METADATA,
    Column("role", Text, primary_key=True),
    Column("station", Text, nullable=False),
)

# Revision 0009: in a station's journal, the state of each record (certificates, device estimates,
# approvers, settle pools) last sent to each lab database (``key``: the record's key, ``state``: the
# columns that change when it does), and when everything had last been sent there (``synced_utc``):
# how old a bench's own view is when it cannot reach the lab.
sync_sent = Table(
    "sync_sent", METADATA,
    Column("target", Text, nullable=False),
    Column("name", Text, nullable=False),
    Column("key", Text, nullable=False),
    Column("state", Text, nullable=False),
    PrimaryKeyConstraint("target", "name", "key"),
)

sync_targets = Table(
    "sync_targets", METADATA,
    Column("target", Text, primary_key=True),
    Column("synced_utc", Text, nullable=False),
)

# Revision 0010: the lab server's audit trail (`labcal.app.audit`): sign-ins, failures, lockouts,
# refusals, approvals and changes to users and approvers; who (``actor``) did what (``kind``) to
# which ``account``, when and from where (``client``). ``digest`` is the SHA-256 of the row and of
# ``prev``, the previous row's digest (unique: one successor per row), so an edit breaks the chain.
audit = Table(
    "audit", METADATA,
    Column("id", Integer, primary_key=True),
    Column("utc", Text, nullable=False),
    Column("kind", Text, nullable=False),
    Column("account", Text),
    Column("actor", Text),
    Column("client", Text),
    Column("detail", Text),
    Column("prev", Text, nullable=False, unique=True),
    Column("digest", Text, nullable=False),
    # revision 0013: a row copied from a bench's journal (an approver changed there) names its digest
    # in that journal: unique, so that a sync appends it once
    Column("origin", Text),
    Index("audit_by_account", "account", "id"),
    Index("audit_by_origin", "origin", unique=True),
)

# Revision 0011: the instrument register (`labcal.store.instruments`). ``serial_key`` is the serial
# case-folded (unique), so a serial differing only in case is the same instrument; ``serial`` keeps the
# register's spelling, which a run takes. ``interval_days`` NULL: no calibration interval set yet.
instruments = Table(
    "instruments", METADATA,
    Column("id", Integer, primary_key=True),
    Column("serial", Text, nullable=False),
    Column("serial_key", Text, nullable=False, unique=True),
    Column("model", Text, nullable=False, server_default=""),
    Column("manufacturer", Text, nullable=False, server_default=""),
    Column("customer", Text, nullable=False, server_default=""),
    Column("owner", Text, nullable=False, server_default=""),
    Column("location", Text, nullable=False, server_default=""),
    Column("interval_days", Integer),
    Column("status", Text, nullable=False, server_default="active"),
    Column("notes", Text, nullable=False, server_default=""),
    Column("created_utc", Text, nullable=False),
    Column("updated_utc", Text, nullable=False),
)

# Revision 0012: the files of a certificate the lab server approved on a PostgreSQL lab database (the
# signed certificate.json, its DCC, the report's PDF and HTML), written by the server's role alone in
# the approval's transaction; the bench that measured the run receives them on its next sync.
certificate_files = Table(
    "certificate_files", METADATA,
    Column("certificate_id", Text, nullable=False),
    Column("run_uuid", Text, nullable=False),
    Column("name", Text, nullable=False),
    Column("sha256", Text, nullable=False),
    Column("content", LargeBinary, nullable=False),
    Column("stored_utc", Text, nullable=False),
    PrimaryKeyConstraint("certificate_id", "name"),
    Index("certificate_files_by_run", "run_uuid", "name"),  # revision 0015: one set per revision, not per run
)

# Revision 0014: the lab's reference standards (`labcal.store.standards`), found by serial whatever its case
# as instruments are; dates are ISO (YYYY-MM-DD); ``bench`` is the station (its name in the lab database)
# that uses the standard, empty for none. An override is an approver's signed permission to run on an
# overdue standard, against the due date it was overdue by, until ``valid_until``; appended only.
standards = Table(
    "standards", METADATA,
    Column("id", Integer, primary_key=True),
    Column("serial", Text, nullable=False),
    Column("serial_key", Text, nullable=False, unique=True),
    Column("kind", Text, nullable=False),
    Column("model", Text, nullable=False, server_default=""),
    Column("manufacturer", Text, nullable=False, server_default=""),
    Column("certificate", Text, nullable=False),
    Column("issued_by", Text, nullable=False, server_default=""),
    Column("calibrated_on", Text, nullable=False),
    Column("due_on", Text, nullable=False),
    Column("bench", Text, nullable=False, server_default=""),
    Column("status", Text, nullable=False, server_default="active"),
    Column("notes", Text, nullable=False, server_default=""),
    Column("created_utc", Text, nullable=False),
    Column("updated_utc", Text, nullable=False),
)
standard_overrides = Table(
    "standard_overrides", METADATA,
    Column("id", Integer, primary_key=True),
    Column("standard_key", Text, nullable=False),
    Column("due_on", Text, nullable=False),
    Column("valid_until", Text, nullable=False),
    Column("reason", Text, nullable=False),
    Column("approver", Text, nullable=False),
    Column("role", Text, nullable=False),
    Column("key_id", Text, nullable=False),
    Column("signature", Text, nullable=False),
    Column("recorded_utc", Text, nullable=False),
    Index("standard_overrides_by_standard", "standard_key", "due_on"),
)

# The lab's own certificate numbers (`labcal.store.certificate_numbers`): one per run, gap-free within
# a scope (the calibration's year, or 0 for one sequence).
certificate_numbers = Table(
    "certificate_numbers", METADATA,
    Column("id", Integer, primary_key=True),
    Column("scope", Integer, nullable=False),
    Column("seq", Integer, nullable=False),
    Column("number", Text, nullable=False, unique=True),
    Column("run_uuid", Text, nullable=False, unique=True),
    Column("assigned_utc", Text, nullable=False),
    UniqueConstraint("scope", "seq", name="certificate_numbers_in_scope"),
)

__all__ = ["METADATA", "approvers", "audit", "certificate_files", "certificate_numbers", "certificates",
           "device_estimates", "events", "instruments", "points", "run_exports", "runs", "settle_pools",
           "standard_overrides", "standards", "station_roles", "sync_cursors", "sync_runs", "sync_sent",
           "sync_targets", "users"]

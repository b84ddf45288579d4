CREATE TABLE alembic_version (
	version_num VARCHAR(32) NOT NULL, 
	CONSTRAINT alembic_version_pkc PRIMARY KEY (version_num)
);
INSERT INTO "alembic_version" VALUES('0015');
CREATE TABLE approvers (
	id INTEGER NOT NULL, 
	name TEXT NOT NULL, 
	role TEXT NOT NULL, 
	public_key TEXT NOT NULL, 
	key_id TEXT NOT NULL, 
	added_utc TEXT NOT NULL, 
	revoked_utc TEXT, 
	PRIMARY KEY (id), 
	UNIQUE (key_id)
);
CREATE TABLE audit (
	id INTEGER NOT NULL, 
	utc TEXT NOT NULL, 
	kind TEXT NOT NULL, 
	account TEXT, 
	actor TEXT, 
	client TEXT, 
	detail TEXT, 
	prev TEXT NOT NULL, 
	digest TEXT NOT NULL, origin TEXT, 
	PRIMARY KEY (id), 
	UNIQUE (prev)
);
CREATE TABLE certificate_files (
	certificate_id TEXT NOT NULL, 
	run_uuid TEXT NOT NULL, 
	name TEXT NOT NULL, 
	sha256 TEXT NOT NULL, 
	content BLOB NOT NULL, 
	stored_utc TEXT NOT NULL, 
	PRIMARY KEY (certificate_id, name)
);
CREATE TABLE certificate_numbers (
	id INTEGER NOT NULL, 
	scope INTEGER NOT NULL, 
	seq INTEGER NOT NULL, 
	number TEXT NOT NULL, 
	run_uuid TEXT NOT NULL, 
	assigned_utc TEXT NOT NULL, 
	PRIMARY KEY (id), 
	CONSTRAINT certificate_numbers_in_scope UNIQUE (scope, seq), 
	UNIQUE (number), 
	UNIQUE (run_uuid)
);
CREATE TABLE certificates (
	certificate_id TEXT NOT NULL, 
	serial TEXT NOT NULL, 
	calibrated_utc TEXT NOT NULL, 
	issued_utc TEXT NOT NULL, 
	sha256 TEXT NOT NULL, 
	document TEXT NOT NULL, 
	PRIMARY KEY (certificate_id)
);
CREATE TABLE device_estimates (
	device_id TEXT NOT NULL, 
	source TEXT NOT NULL, 
	calibrated_utc TEXT NOT NULL, 
	stored_utc TEXT NOT NULL, 
	document TEXT NOT NULL, 
	PRIMARY KEY (device_id, source)
);
CREATE TABLE events (
	id INTEGER NOT NULL, 
	run_id INTEGER NOT NULL, 
	utc TEXT NOT NULL, 
	station_time FLOAT, 
	kind TEXT NOT NULL, 
	message TEXT NOT NULL, 
	data TEXT, origin_id INTEGER, link INTEGER, digest TEXT, 
	PRIMARY KEY (id), 
	FOREIGN KEY(run_id) REFERENCES runs (id)
);
CREATE TABLE instruments (
	id INTEGER NOT NULL, 
	serial TEXT NOT NULL, 
	serial_key TEXT NOT NULL, 
	model TEXT DEFAULT '' NOT NULL, 
	manufacturer TEXT DEFAULT '' NOT NULL, 
	customer TEXT DEFAULT '' NOT NULL, 
	owner TEXT DEFAULT '' NOT NULL, 
	location TEXT DEFAULT '' NOT NULL, 
	interval_days INTEGER, 
	status TEXT DEFAULT 'active' NOT NULL, 
	notes TEXT DEFAULT '' NOT NULL, 
	created_utc TEXT NOT NULL, 
	updated_utc TEXT NOT NULL, 
	PRIMARY KEY (id), 
	UNIQUE (serial_key)
);
CREATE TABLE points (
	run_id INTEGER NOT NULL, 
	seq INTEGER NOT NULL, 
	replicate INTEGER NOT NULL, 
	y_deg FLOAT NOT NULL, 
	u_deg FLOAT NOT NULL, 
	pitch_deg FLOAT NOT NULL, 
	roll_deg FLOAT NOT NULL, 
	pitch_read FLOAT, 
	roll_read FLOAT, 
	attempt INTEGER NOT NULL, 
	status TEXT NOT NULL, 
	t_start FLOAT, 
	t_end FLOAT, 
	utc TEXT NOT NULL, 
	n_samples INTEGER NOT NULL, 
	vx FLOAT, 
	vy FLOAT, 
	vz FLOAT, 
	sd_vx FLOAT, 
	sd_vy FLOAT, 
	sd_vz FLOAT, 
	temp_c FLOAT, 
	settle_s FLOAT, 
	settle_verdict TEXT, 
	samples BLOB, link INTEGER, digest TEXT, 
	PRIMARY KEY (run_id, seq), 
	FOREIGN KEY(run_id) REFERENCES runs (id)
);
CREATE TABLE run_exports (
	run_id INTEGER NOT NULL, 
	name TEXT NOT NULL, 
	sha256 TEXT NOT NULL, 
	PRIMARY KEY (run_id, name), 
	FOREIGN KEY(run_id) REFERENCES runs (id)
);
CREATE TABLE runs (
	id INTEGER NOT NULL, 
	run_dir TEXT NOT NULL, 
	plan_name TEXT NOT NULL, 
	plan_text TEXT NOT NULL, 
	plan_hash TEXT NOT NULL, 
	station_text TEXT NOT NULL, 
	station_hash TEXT NOT NULL, 
	software_version TEXT NOT NULL, 
	instrument_serial TEXT, 
	device_id TEXT, 
	operator TEXT, 
	settings TEXT NOT NULL, 
	metadata TEXT NOT NULL, 
	started_utc TEXT NOT NULL, 
	status TEXT NOT NULL, 
	reason TEXT, 
	ended_utc TEXT, uuid TEXT, station TEXT, points_total INTEGER, digest TEXT, 
	PRIMARY KEY (id)
);
CREATE TABLE settle_pools (
	pool_key TEXT NOT NULL, 
	identity TEXT NOT NULL, 
	records INTEGER NOT NULL, 
	sources TEXT NOT NULL, 
	mismatch TEXT NOT NULL, 
	sums BLOB NOT NULL, 
	updated_utc TEXT NOT NULL, 
	PRIMARY KEY (pool_key)
);
CREATE TABLE standard_overrides (
	id INTEGER NOT NULL, 
	standard_key TEXT NOT NULL, 
	due_on TEXT NOT NULL, 
	valid_until TEXT NOT NULL, 
	reason TEXT NOT NULL, 
	approver TEXT NOT NULL, 
	role TEXT NOT NULL, 
	key_id TEXT NOT NULL, 
	signature TEXT NOT NULL, 
	recorded_utc TEXT NOT NULL, 
	PRIMARY KEY (id)
);
CREATE TABLE standards (
	id INTEGER NOT NULL, 
	serial TEXT NOT NULL, 
	serial_key TEXT NOT NULL, 
	kind TEXT NOT NULL, 
	model TEXT DEFAULT '' NOT NULL, 
	manufacturer TEXT DEFAULT '' NOT NULL, 
	certificate TEXT NOT NULL, 
	issued_by TEXT DEFAULT '' NOT NULL, 
	calibrated_on TEXT NOT NULL, 
	due_on TEXT NOT NULL, 
	bench TEXT DEFAULT '' NOT NULL, 
	status TEXT DEFAULT 'active' NOT NULL, 
	notes TEXT DEFAULT '' NOT NULL, 
	created_utc TEXT NOT NULL, 
	updated_utc TEXT NOT NULL, 
	PRIMARY KEY (id), 
	UNIQUE (serial_key)
);
CREATE TABLE station_roles (
	role TEXT NOT NULL, 
	station TEXT NOT NULL, 
	PRIMARY KEY (role)
);
CREATE TABLE sync_cursors (
	target TEXT NOT NULL, 
	name TEXT NOT NULL, 
	position INTEGER NOT NULL, 
	PRIMARY KEY (target, name)
);
CREATE TABLE sync_runs (
	target TEXT NOT NULL, 
	run_id INTEGER NOT NULL, 
	lab_run_id INTEGER NOT NULL, 
	sent TEXT NOT NULL, 
	PRIMARY KEY (target, run_id), 
	FOREIGN KEY(run_id) REFERENCES runs (id)
);
CREATE TABLE sync_sent (
	target TEXT NOT NULL, 
	name TEXT NOT NULL, 
	"key" TEXT NOT NULL, 
	state TEXT NOT NULL, 
	PRIMARY KEY (target, name, "key")
);
CREATE TABLE sync_targets (
	target TEXT NOT NULL, 
	synced_utc TEXT NOT NULL, 
	PRIMARY KEY (target)
);
CREATE TABLE users (
	id INTEGER NOT NULL, 
	name TEXT NOT NULL, 
	role TEXT NOT NULL, 
	password_hash TEXT NOT NULL, 
	token_hash TEXT NOT NULL, 
	created_utc TEXT NOT NULL, 
	disabled_utc TEXT, token_utc TEXT, 
	PRIMARY KEY (id), 
	UNIQUE (name), 
	UNIQUE (token_hash)
);
CREATE INDEX certificates_by_serial ON certificates (serial, calibrated_utc);
CREATE INDEX events_by_run ON events (run_id, id);
CREATE UNIQUE INDEX runs_by_uuid ON runs (uuid);
CREATE INDEX device_estimates_by_date ON device_estimates (device_id, calibrated_utc);
CREATE UNIQUE INDEX approvers_active_name ON approvers (name) WHERE revoked_utc IS NULL;
CREATE UNIQUE INDEX events_by_origin ON events (run_id, origin_id);
CREATE UNIQUE INDEX points_by_link ON points (run_id, link);
CREATE UNIQUE INDEX events_by_link ON events (run_id, link);
CREATE INDEX audit_by_account ON audit (account, id);
CREATE UNIQUE INDEX audit_by_origin ON audit (origin);
CREATE INDEX standard_overrides_by_standard ON standard_overrides (standard_key, due_on);
CREATE INDEX certificate_files_by_run ON certificate_files (run_uuid, name);

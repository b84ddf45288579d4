"""Each bench of a PostgreSQL lab connects as a role of its own (`labcal db grant-station`): against a
real PostgreSQL server (tests/services.py), a bench role runs and syncs a calibration end to end, and
PostgreSQL itself refuses it everything else — users, approvers, any table not granted, editing or
deleting a point or an event, and a run, a point or an event of another station.

The test cluster trusts every local connection (initdb -A trust), so a role connects without its
password; the password's verifier is checked against RFC 7677's published exchange instead.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import io
import stat
from pathlib import Path

import psycopg
import pytest
from cli import here_at_bench as here

# What a bench may do, as the lab's roles page states it: read these, and nothing else at all
BENCH_READS = {"alembic_version", "runs", "points", "events", "certificates", "run_exports",
               "device_estimates", "settle_pools", "station_roles", "approvers", "instruments",
               "certificate_files", "standards", "standard_overrides", "certificate_numbers"}


def grant(env: pytest.MonkeyPatch, folder: Path, admin: str, station: str, *extra: str) -> str:
    code, out, err = here(env, folder, "db", "grant-station", station, "--db", admin, *extra, db=admin)
    assert code == 0, err
    return out.strip().splitlines()[-1]


def denied(url: str, sql: str, args: tuple = ()) -> str:
    """PostgreSQL's refusal of ``sql`` as the role of ``url`` (fails the test if it is allowed)."""
    with psycopg.connect(url) as conn, pytest.raises(psycopg.errors.InsufficientPrivilege) as refused:
        conn.execute(sql, args)
    return str(refused.value).splitlines()[0]


@pytest.fixture(scope="module")
def lab(tmp_path_factory, postgres_cluster):
    """A lab database set up by its administrator, and bench-1's role, which has run and synced one
    simulated calibration: (admin URL, bench-1's URL, the lab's run id of bench-1's run). The tests
    that share it change nothing in it (PostgreSQL refuses them)."""
    tmp_path = tmp_path_factory.mktemp("roles")
    postgres_url = postgres_cluster.url(postgres_cluster.create_database())
    with pytest.MonkeyPatch.context() as env:
        code, _, err = here(env, tmp_path, "db", "upgrade", "--db", postgres_url, db=postgres_url)
        assert code == 0, err
        code, out, _ = here(env, tmp_path, "db", "upgrade", "--db", postgres_url, db=postgres_url)
        assert code == 0 and "grants and policies are set up" in " ".join(out.split())  # idempotent
        bench = grant(env, tmp_path, postgres_url, "bench-1")
        code, _, err = here(env, tmp_path, "run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16",
                            "--out", str(tmp_path / "bench-1" / "run"), db=bench)
    assert code == 0, err
    assert "not yet in the lab database" not in err and "stopped" not in err
    with psycopg.connect(postgres_url) as conn:
        run_id = conn.execute("SELECT id FROM runs WHERE station = 'bench-1'").fetchone()[0]
    return postgres_url, bench, run_id, tmp_path


def test_grant_station_prints_the_benchs_url_last_and_keeps_the_password_off_the_screen(
        tmp_path, postgres_url, monkeypatch, capfd):
    """Read through capfd: what reaches the file descriptors, as a process of its own would write it."""
    password_file = tmp_path / "bench-2.pgpass"
    code, out, err = here(monkeypatch, tmp_path, "db", "grant-station", "Bench 2", "--db", postgres_url,
                          "--password-file", str(password_file), db=postgres_url, capture=capfd)
    assert code == 0, err
    host_port_db = postgres_url.rpartition("@")[2]
    assert out.strip().splitlines()[-1] == f"postgresql://labcal_bench_bench_2@{host_port_db}"
    assert stat.S_IMODE(password_file.stat().st_mode) == 0o600
    host, port, database, role, password = password_file.read_text().strip().split(":")
    assert (host, port, database, role) == ("127.0.0.1", host_port_db.split(":")[1].split("/")[0],
                                            host_port_db.rpartition("/")[2], "labcal_bench_bench_2")
    assert password not in out + err and len(password) >= 24
    with psycopg.connect(postgres_url) as conn:
        verifier, login = conn.execute("SELECT rolpassword, rolcanlogin FROM pg_authid "
                                       "WHERE rolname = 'labcal_bench_bench_2'").fetchone()
        members = conn.execute("SELECT g.rolname FROM pg_auth_members m JOIN pg_roles g ON g.oid = m.roleid"
                               " JOIN pg_roles r ON r.oid = m.member WHERE r.rolname = %s",
                               ("labcal_bench_bench_2",)).fetchall()
        mapped = conn.execute("SELECT station FROM station_roles WHERE role = %s",
                              ("labcal_bench_bench_2",)).fetchone()
    assert login and members == [("labcal_bench",)] and mapped == ("Bench 2",)
    assert verifier.startswith("SCRAM-SHA-256$4096:") and password not in verifier
    # a password file is never overwritten; a SQLite lab database has no roles: one line each
    code, _, err = here(monkeypatch, tmp_path, "db", "grant-station", "Bench 2", "--db", postgres_url,
                        "--password-file", str(password_file), db=postgres_url, capture=capfd)
    assert code == 2 and "never overwritten" in err
    assert len(err.splitlines()) == 1
    code, _, err = here(monkeypatch, tmp_path, "db", "grant-station", "x", "--db",
                        str(tmp_path / "lab.sqlite"), db=postgres_url, capture=capfd)
    assert code == 2 and "one machine, one trust domain" in err


def test_the_password_verifier_answers_rfc_7677s_published_exchange():
    """RFC 7677 §3: user "user", password "pencil", salt W22ZaJ0SNY7soEsUEjb6gQ==, 4096 iterations; the
    client's proof and the server's signature over the exchange are published. A verifier that holds
    the right StoredKey and ServerKey reproduces both."""
    from labcal.store.roles import scram_verifier

    verifier = scram_verifier("pencil", base64.b64decode("W22ZaJ0SNY7soEsUEjb6gQ=="))
    mechanism, iterations_salt, keys = verifier.split("$")
    stored_key, server_key = (base64.b64decode(k) for k in keys.split(":"))
    assert (mechanism, iterations_salt) == ("SCRAM-SHA-256", "4096:W22ZaJ0SNY7soEsUEjb6gQ==")
    nonce = "rOprNGfwEbeRWgbNEkqO%hvYDpWUa2RaTCAfuxFIlj)hNlF$k0"
    auth = (f"n=user,r=rOprNGfwEbeRWgbNEkqO,r={nonce},s=W22ZaJ0SNY7soEsUEjb6gQ==,i=4096,c=biws,r={nonce}"
            ).encode()
    server_signature = hmac.new(server_key, auth, "sha256").digest()
    assert base64.b64encode(server_signature).decode() == "6rriTRBi23WpRR/wtup+mMhUZUn/dB5nLTJRsjl95G4="
    proof = base64.b64decode("dHzbZapWIk4jUhN+Ute9ytag9zjfMHgsqmmiz7AndVQ=")
    client_signature = hmac.new(stored_key, auth, "sha256").digest()
    client_key = bytes(a ^ b for a, b in zip(proof, client_signature, strict=True))
    assert hashlib.sha256(client_key).digest() == stored_key


def test_a_bench_role_cannot_touch_users_approvers_approvals_nor_edit_a_point_or_an_event(lab):
    admin, bench, run_id, _ = lab
    assert "permission denied for table users" in denied(
        bench, "INSERT INTO users (name, role, password_hash, token_hash, created_utc) "
               "VALUES ('mallory', 'approver', 'x', 'y', '2026-01-01')")
    # who the server signed for is read (verifying its signature at a bench); their hashes never
    assert "permission denied for table users" in denied(bench, "SELECT password_hash, token_hash FROM users")
    # the register of approvers is read at every bench (verifying a signature), written by none
    assert "permission denied for table approvers" in denied(
        bench, "INSERT INTO approvers (name, role, public_key, key_id, added_utc) "
               "VALUES ('mallory', 'approver', 'k', 'id', '2026-01-01')")
    assert "permission denied for table approvers" in denied(bench, "UPDATE approvers SET revoked_utc = NULL")
    assert "permission denied for table points" in denied(
        bench, "UPDATE points SET vx = vx + 0.0005 WHERE run_id = %s AND seq = 17", (run_id,))
    assert "permission denied for table points" in denied(bench, "DELETE FROM points WHERE run_id = %s",
                                                          (run_id,))
    assert "permission denied for table events" in denied(bench, "UPDATE events SET message = 'nothing'")
    assert "permission denied for table events" in denied(bench, "DELETE FROM events")
    with psycopg.connect(admin) as conn:  # every other table, approvals included wherever the schema has it
        tables = {r[0] for r in conn.execute("SELECT tablename FROM pg_tables WHERE schemaname = %s",
                                             ("public",))}
    for table in sorted(tables - BENCH_READS - {"users"}):  # users: its names only, above
        assert f"permission denied for table {table}" in denied(bench, f"SELECT 1 FROM {table}")
    for table in sorted(tables):  # a bench deletes nothing
        assert f"permission denied for table {table}" in denied(bench, f"DELETE FROM {table}")
    with psycopg.connect(admin) as conn:  # nothing changed
        assert conn.execute("SELECT count(*) FROM points WHERE run_id = %s", (run_id,)).fetchone() == (16,)


def test_a_bench_role_cannot_append_a_run_or_a_point_for_another_station(lab, tmp_path, monkeypatch, capsys):
    admin, bench, run_id, _ = lab
    other = grant(monkeypatch, tmp_path, admin, "bench-2")
    forged = ("INSERT INTO runs (run_dir, plan_name, plan_text, plan_hash, station_text, station_hash, "
              "software_version, settings, metadata, started_utc, status, uuid, station) VALUES "
              "('x', 'p', 'p', 'h', 's', 'h', 'v', '{}', '{}', '2026-01-01', 'running', 'u-forged', %s)")
    assert "row-level security" in denied(bench, forged, ("bench-2",))
    assert "row-level security" in denied(
        other, "INSERT INTO points (run_id, seq, replicate, y_deg, u_deg, pitch_deg, roll_deg, attempt, "
               "status, utc, n_samples) VALUES (%s, 999, 1, 0, 0, 0, 0, 1, 'ok', '2026-01-01', 0)", (run_id,))
    assert "row-level security" in denied(
        other, "INSERT INTO events (run_id, utc, kind, message) VALUES (%s, '2026-01-01', 'note', 'x')",
        (run_id,))
    with psycopg.connect(other) as conn:  # it reads the lab's record all the same, and ends no run of bench-1
        assert conn.execute("SELECT count(*) FROM points WHERE run_id = %s", (run_id,)).fetchone() == (16,)
        assert conn.execute("UPDATE runs SET status = 'aborted' WHERE id = %s", (run_id,)).rowcount == 0
    # a bench that says it is another station is refused by the server, and keeps every reading
    code, _, err = here(monkeypatch, tmp_path, "run", "--sim", "--yes", "--no-report", "--plan",
                        "one-mount-16", "--out", str(tmp_path / "bench-2" / "run"), db=bench,
                        station="bench-2", capture=capsys)
    assert code == 0
    assert "row-level security" in err and "journal keeps every record" in err
    with psycopg.connect(admin) as conn:
        assert conn.execute("SELECT count(*) FROM runs WHERE station = 'bench-2'").fetchone() == (0,)


def test_a_bench_role_syncs_its_journal_end_to_end(lab, monkeypatch, capsys):
    """The run of the fixture reached the lab as it was measured; a second run, made while the lab
    could not be reached, reaches it by `labcal sync` as the bench's role: every point, with the
    digests the journal wrote."""
    import sqlite3
    from contextlib import closing

    from services import free_port

    admin, bench, run_id, tmp_path = lab
    away = bench.replace(bench.rpartition("@")[2].split("/")[0], f"127.0.0.1:{free_port()}")
    code, _, err = here(monkeypatch, tmp_path, "run", "--sim", "--yes", "--no-report", "--plan",
                        "one-mount-16", "--out", str(tmp_path / "bench-1" / "offline"), db=away,
                        capture=capsys)
    assert code == 0 and "unreachable" in err, err
    code, out, err = here(monkeypatch, tmp_path, "sync", db=bench, capture=capsys)
    assert code == 0, err
    assert "16 points" in " ".join(out.split()), out
    with closing(sqlite3.connect(tmp_path / "bench-1" / "journal.sqlite")) as db:
        journal = db.execute("SELECT r.uuid, p.seq, p.vx, p.vy, p.vz, p.link, p.digest FROM points p "
                             "JOIN runs r ON r.id = p.run_id ORDER BY r.uuid, p.seq").fetchall()
    with psycopg.connect(admin) as conn:
        lab_points = conn.execute("SELECT r.uuid, p.seq, p.vx, p.vy, p.vz, p.link, p.digest FROM points p "
                                  "JOIN runs r ON r.id = p.run_id WHERE r.station = 'bench-1' "
                                  "ORDER BY r.uuid, p.seq").fetchall()
        statuses = conn.execute("SELECT status FROM runs WHERE station = 'bench-1'").fetchall()
    assert lab_points == journal and len(journal) == 32 and statuses == [("complete",), ("complete",)]
    code, out, _ = here(monkeypatch, tmp_path, "sync", db=bench, capture=capsys)
    assert code == 0 and "nothing to send" in " ".join(out.split())


def test_the_servers_role_reads_the_lab_and_appends_no_reading(lab, tmp_path, monkeypatch, capfd):
    """Read through capfd: what reaches the file descriptors, as a process of its own would write it."""
    admin, bench, run_id, _ = lab
    secret = "a-password-typed-by-the-administrator"
    monkeypatch.setattr("sys.stdin", io.StringIO(secret + "\n"))
    code, out, err = here(monkeypatch, tmp_path, "db", "grant-server", "web", "--db", admin,
                          "--password-stdin", db=admin, capture=capfd)
    assert code == 0, err
    server = out.strip().splitlines()[-1]
    assert server == f"postgresql://labcal_server_web@{admin.rpartition('@')[2]}"
    assert secret not in out + err
    with psycopg.connect(admin) as conn:  # another test of this module may have added a user
        users = conn.execute("SELECT count(*) FROM users").fetchone()
    with psycopg.connect(server) as conn:
        assert conn.execute("SELECT count(*) FROM users").fetchone() == users
        assert conn.execute("SELECT count(*) FROM points WHERE run_id = %s", (run_id,)).fetchone() == (16,)
    assert "permission denied for table points" in denied(server, "UPDATE points SET vx = 0")
    assert "permission denied for table runs" in denied(
        server, "INSERT INTO runs (run_dir, plan_name, plan_text, plan_hash, station_text, station_hash, "
                "software_version, settings, metadata, started_utc, status) VALUES "
                "('x', 'p', 'p', 'h', 's', 'h', 'v', '{}', '{}', '2026-01-01', 'running')")
    assert "permission denied for table users" in denied(
        server, "INSERT INTO users (name, role, password_hash, token_hash, created_utc) "
                "VALUES ('mallory', 'approver', 'x', 'y', '2026-01-01')")
    with psycopg.connect(admin) as conn:
        verifier = conn.execute("SELECT rolpassword FROM pg_authid WHERE rolname = %s",
                                ("labcal_server_web",)).fetchone()
    assert verifier[0].startswith("SCRAM-SHA-256$4096:")


def test_the_lab_server_serves_the_benchs_runs_connected_as_its_own_role(lab, tmp_path, monkeypatch, capsys):
    import httpx
    from lab_server import add_user, served

    admin, _, run_id, _ = lab
    code, out, err = here(monkeypatch, tmp_path, "db", "grant-server", "lab-web", "--db", admin, db=admin,
                          capture=capsys)
    assert code == 0, err
    server = out.strip().splitlines()[-1]
    token = add_user(admin, "vic", "viewer", "vic's passphrase")  # users are the administrator's to add
    with served(server) as url:
        runs = httpx.get(f"{url}/api/runs", headers={"Authorization": f"Bearer {token}"}, timeout=30)
    assert runs.status_code == 200, runs.text
    assert run_id in [r["id"] for r in runs.json()["runs"]]

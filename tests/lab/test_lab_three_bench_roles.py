"""The lab as one system with the trust boundaries in place: three benches, each a process with its own
PostgreSQL role (`labcal db grant-station`) and its own journal, and the lab server on the server's role,
against a real PostgreSQL server (tests/services.py).

- ACC-0042 calibrated at bench 1 and, with its bias shifted 5 mV on x, at bench 2: `labcal history` at
  each of the three benches shows both calibrations and flags the shift; the server's /api/runs lists
  both runs under the one serial.
- A device estimate made at bench 2 drives `labcal plan optimize --device` at bench 2 after bench 2's
  journal is deleted.
- An approver registered once, by the lab's administrator, verifies a certificate at all three benches.

Expectations are stated independently: the shift is the one put into the simulated rig, the lab's
rows are read with plain SQL, the signature is checked by `labcal certificate verify` at each bench.
"""

from __future__ import annotations

import io
import json
import subprocess
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import httpx
import psycopg
import pytest
from cli import LABCAL, bench_env
from lab_server import add_user, served
from simulated_runs import bench_run, days_ago, rig_with_bias_shift

from labcal.cli import main

SERIAL = "ACC-0042"
NAME, ROLE = "A. Metrologist", "Technical manager"
pytestmark = pytest.mark.slow(seconds=90)  # two dry runs, one through the drivers, a server


def environment(tmp_path: Path, station: str, db: str) -> dict[str, str]:
    return bench_env(tmp_path, db, station)


def at(tmp_path: Path, station: str, db: str, *args: str) -> subprocess.CompletedProcess:
    """A labcal command as a process of its own at ``station``, connected as ``db``."""
    done = subprocess.run([LABCAL, *args], capture_output=True, text=True,
                          env=environment(tmp_path, station, db), timeout=240)
    assert done.returncode == 0, f"{station}: labcal {' '.join(args)}: {done.stderr}"
    return done


def test_three_bench_roles_and_the_servers_share_one_record(tmp_path, postgres_url, monkeypatch):
    admin = postgres_url
    at(tmp_path, "admin", admin, "db", "upgrade", "--db", admin)
    role = {station: at(tmp_path, "admin", admin, "db", "grant-station", station, "--db", admin
                        ).stdout.strip().splitlines()[-1] for station in ("bench-1", "bench-2", "bench-3")}
    server = at(tmp_path, "admin", admin, "db", "grant-server", "web", "--db", admin
                ).stdout.strip().splitlines()[-1]
    assert all(url.startswith(f"postgresql://labcal_bench_{s.replace('-', '_')}@") for s, url in role.items())

    # ACC-0042 at bench 1, and at bench 2 with its bias 5 mV higher on x (far beyond its U95)
    shifted = rig_with_bias_shift(tmp_path / "shifted.toml", (0.005, 0.0, 0.0))
    at(tmp_path, "bench-1", role["bench-1"], "run", "--sim", "--yes", "--seed", "3", "--serial", SERIAL,
       "--out", str(tmp_path / "bench-1" / "b1-run"))
    at(tmp_path, "bench-2", role["bench-2"], "run", "--sim", "--yes", "--seed", "4", "--serial", SERIAL,
       "--rig", str(shifted), "--out", str(tmp_path / "bench-2" / "b2-run"))
    histories = [json.loads(at(tmp_path, station, role[station], "history", SERIAL, "--include-simulated",
                                "--json").stdout) for station in role]
    assert histories[0] == histories[1] == histories[2]
    assert len(histories[0]["calibrations"]) == 2
    assert ("B", "x") in {(f["coefficient"], f["sensor"]) for f in histories[0]["flagged"]}
    bias_x = [c["coefficients"][0][0] for c in histories[0]["calibrations"]]
    assert abs(bias_x[1] - bias_x[0] - 0.005) < 0.001  # the shift put into the rig, as both measured it

    token = add_user(admin, "vic", "viewer", "vic's long passphrase")
    with served(server) as url:
        answer = httpx.get(f"{url}/api/runs", headers={"Authorization": f"Bearer {token}"}, timeout=30)
    runs = answer.json()["runs"]
    assert sorted((r["station"], r["serial"]) for r in runs) == [("bench-1", SERIAL), ("bench-2", SERIAL)]

    # bench 2's device estimate, after bench 2's journal is gone (bench 1's dated three days back: two
    # estimates of one day are one sitting)
    with psycopg.connect(admin) as conn:
        sources = {r[0] for r in conn.execute("SELECT source FROM device_estimates "
                                              "WHERE device_id = 'SIMULATED'")}
        assert sources == {"b1-run", "b2-run"}
        earlier = days_ago(3)
        conn.execute("UPDATE device_estimates SET calibrated_utc = %s, document = jsonb_set(document::jsonb, "
                     "'{calibrated_utc}', to_jsonb(%s::text))::text WHERE source = 'b1-run'",
                     (earlier, earlier))
    for path in (tmp_path / "bench-2").glob("journal.sqlite*"):
        path.unlink()
    optimized = at(tmp_path, "bench-2", role["bench-2"], "plan", "optimize", "--device", "SIMULATED",
                   "--target-attitude-u95-deg", "1", "--json")
    assert json.loads(optimized.stdout)["device_correction"]["source"] == "b2-run"

    # an approver registered once, by the administrator; a certificate of bench 1's approved there
    at(tmp_path, "admin", admin, "certificate", "keygen", "--out", str(tmp_path / "approver"))
    at(tmp_path, "admin", admin, "certificate", "approvers", "add", NAME, "--role", ROLE, "--public-key",
       str(tmp_path / "approver.pub"))
    for name, value in environment(tmp_path, "bench-1", role["bench-1"]).items():
        if name.startswith("LABCAL_"):
            monkeypatch.setenv(name, value)
    run = bench_run(tmp_path / "bench-1" / "b1-signed", role["bench-1"], SERIAL)  # through the drivers
    err = io.StringIO()
    with redirect_stdout(io.StringIO()), redirect_stderr(err):
        code = main(["certificate", "approve", str(run), "--by", NAME, "--role", ROLE, "--key",
                     str(tmp_path / "approver.key")])
    assert code == 0, err.getvalue()
    for station in role:
        verified = json.loads(at(tmp_path, station, role[station], "certificate", "verify",
                                 str(run / "certificate.json"), "--json").stdout)
        assert verified["valid"] is True and verified["verified_against"] == "the registered key", station

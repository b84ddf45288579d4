"""The approver's queue costs what is waiting, not the lab's history: in a lab of 200 complete runs
whose certificates are approved and three whose drafts wait, the queue lists the three and is built
in a number of statements that does not grow with the approved runs (counted on the engine with a
SQLAlchemy event listener, not timed: a machine's speed is no test)."""

from __future__ import annotations

import json
from pathlib import Path

from sqlalchemy import event, insert

from labcal.app.desk import queue
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.store.schema import certificates, runs

STORED = Path(__file__).parent.parent / "data" / "certificates" / "simulated.json"
APPROVED, WAITING = 200, 3


def _run(run_id: int) -> dict:
    return {"id": run_id, "run_dir": f"/nowhere/run{run_id}", "plan_name": "one-mount-16", "plan_text": "",
            "plan_hash": "", "station_text": "[station]\nname = 'bench-1'\n", "station_hash": "",
            "software_version": "test", "instrument_serial": "ACC-0042", "settings": "{}", "metadata": "{}",
            "started_utc": "2026-11-01T00:00:00+00:00", "status": "complete", "uuid": f"uuid-{run_id:04d}",
            "station": "bench-1", "points_total": 16}


def _certificate(run_id: int, approved: bool) -> dict:
    doc = json.loads(STORED.read_text())
    doc["certificate_id"] = f"ACC-0042-{run_id:04d}"
    doc["data"]["journal"] = {"run_uuid": f"uuid-{run_id:04d}"}
    if approved:
        doc["approval"] = {"by": "ada", "role": "approver", "approved_utc": "2026-11-02T00:00:00+00:00"}
    return {"certificate_id": doc["certificate_id"], "serial": "ACC-0042",
            "calibrated_utc": doc["calibrated_utc"], "issued_utc": doc["issued_utc"], "sha256": str(run_id),
            "document": json.dumps(doc)}


def test_the_queue_of_a_lab_of_two_hundred_approved_runs_takes_a_bounded_number_of_statements(tmp_path):
    lab = open_lab(OpenLab(str(tmp_path / "lab.sqlite"), must_exist=False))
    try:
        total = APPROVED + WAITING
        with lab.engine.begin() as conn:
            conn.execute(insert(runs), [_run(i) for i in range(1, total + 1)])
            conn.execute(insert(certificates), [_certificate(i, i <= APPROVED) for i in range(1, total + 1)])
        statements = []
        event.listen(lab.engine, "before_cursor_execute", lambda *args: statements.append(args[2]))
        listed = queue(lab, dry_runs=True)
    finally:
        lab.close()
    assert [w.run["id"] for w in listed.waiting] == list(range(APPROVED + 1, total + 1))
    # the runs, their counts, the approvals (certificates once, the server's files once), then for
    # each waiting run its revisions (certificates, the server's files), its faults and the overrides
    # it resumed under: none of it grows with the 200 approved runs
    assert len(statements) <= 4 + 4 * WAITING, statements

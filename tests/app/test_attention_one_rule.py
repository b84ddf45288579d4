"""One rule for what needs an approver's eye: `labcal runs --attention` lists, for a run, exactly the
lines the approver's desk shows in its queue and on the run's page — the checklist item it went on
regardless of, the faults journaled during the run, and the conformity check its certificate failed —
read from the same lab record. The run is a real dry run; what it went on regardless of and its faults
are journaled into it the way a run journals them, and its certificate is reissued with a tolerance
it cannot meet. The expected lines are written out here from what the test put in."""

from __future__ import annotations

import json
import sqlite3

from simulated_runs import simulated_run

from labcal.app.desk import queue, run_results
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.cli import main
from labcal.store.journal import Journal

WARM_UP = "warm-up: warmed up 3 min of the 30 the station declares"
FAULTS = ("DMM timeout at point 3", "pitch table stalled at point 9")


def test_the_cli_and_the_desk_list_the_same_attention_for_the_same_run(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    run_dir = simulated_run(tmp_path / "run", db, seed=4)
    checklist = {"went_on_regardless": True, "items": [
        {"item": "warm-up", "status": "fail", "message": WARM_UP.removeprefix("warm-up: ")},
        {"item": "DMM", "status": "ok", "message": "answers"}]}
    with Journal(db) as journal:  # chained into the run's record, as the run journals a fault
        for message in FAULTS:
            journal.event(1, "fault", message)
    # a tolerance of 0.01″ on the attitude: no calibration meets it
    assert main(["report", str(run_dir), "--tolerance-deg", str(0.01 / 3600), "--db", str(db)]) == 0
    cert = json.loads((run_dir / "certificate.json").read_text(encoding="utf-8"))
    failed = [c for c in cert["conformity"]["checks"] if not c["passed"]]
    assert failed  # the premise: the certificate states a failed check
    # the checklist as a run journals it when the operator goes on regardless (set after the report:
    # the run's metadata is sealed in the journal's chain, which the report verifies)
    with sqlite3.connect(db) as conn:
        (metadata,) = conn.execute("SELECT metadata FROM runs WHERE id = 1").fetchone()
        conn.execute("UPDATE runs SET metadata = ? WHERE id = 1",
                     (json.dumps({**json.loads(metadata), "checklist": checklist}),))
    capsys.readouterr()

    assert main(["runs", "--attention", "--db", str(db), "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["runs"]
    assert [r["id"] for r in listed] == [1]
    cli = tuple(listed[0]["attention"])

    assert cli[0] == f"went on regardless: {WARM_UP}"
    assert cli[1] == f"2 fault(s) during the run: {FAULTS[0]}; {FAULTS[1]}"
    assert cli[2].startswith("out of tolerance: ")
    assert all(c["quantity"] in cli[2] for c in failed) and len(cli) == 3

    lab = open_lab(OpenLab(str(db)))
    try:
        waiting = queue(lab, dry_runs=True).waiting  # a dry run: listed when asked
        results = run_results(lab, 1)
    finally:
        lab.close()
    assert [w.run["id"] for w in waiting] == [1]
    assert waiting[0].attention == cli
    assert results is not None and results.attention == cli


def test_a_run_with_nothing_to_note_is_not_listed_and_the_desk_notes_nothing(tmp_path, capsys):
    db = tmp_path / "lab.sqlite"
    simulated_run(tmp_path / "run", db, seed=5)
    capsys.readouterr()
    assert main(["runs", "--attention", "--db", str(db), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["runs"] == []
    lab = open_lab(OpenLab(str(db)))
    try:
        assert [w.attention for w in queue(lab, dry_runs=True).waiting] == [()]
    finally:
        lab.close()

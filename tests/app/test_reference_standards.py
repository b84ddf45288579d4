"""The lab's reference standards: an overdue one stops a run before anything moves, an approver's
signed override lets it go on, and the override is stated on the certificate, its report and the
approver's view; on PostgreSQL a bench's role cannot write an override at all. Real `labcal`
processes on the simulated rig against a real SQLite lab database (and the private PostgreSQL
cluster). Every date is counted here from today, by hand."""

from __future__ import annotations

import json
import sqlite3
from contextlib import closing
from datetime import UTC, date, datetime, timedelta
from pathlib import Path

import psycopg
import pytest
from second_ed25519 import holds
from services import postgres_cluster, postgres_url  # noqa: F401 - fixtures
from test_instruments import InProcess

TODAY = datetime.now().astimezone().date()  # the day the runs below are checked on, as labcal counts it
REASON = "recalibration booked for 3 December; checked against the spare DMM at 10 V"


@pytest.fixture
def lc(capsys) -> InProcess:
    return InProcess(capsys)


@pytest.fixture
def bench(lc, monkeypatch, lab_database):
    """This computer is bench-1, which uses a DMM registered to it and overdue since yesterday."""
    monkeypatch.setenv("LABCAL_STATION", "bench-1")
    lc("standard", "add", "MY-DMM-7", "--kind", "dmm", "--manufacturer", "Keysight", "--model", "34970A",
           "--certificate", "CAL-2025-118", "--issued-by", "Volt Lab", "--calibrated",
           (TODAY - timedelta(days=366)).isoformat(), "--due", (TODAY - timedelta(days=1)).isoformat(),
           "--bench", "bench-1")
    return lab_database


@pytest.fixture
def approver(lc, tmp_path) -> Path:
    """Ann Lee, a registered approver, and her private key."""
    lc("certificate", "keygen", "--out", str(tmp_path / "ann"))
    lc("certificate", "approvers", "add", "Ann Lee", "--role", "Technical manager", "--public-key",
           str(tmp_path / "ann.pub"))
    return tmp_path / "ann.key"


def run(lc: InProcess, tmp_path: Path, check: int = 0):
    return lc("run", "--sim", "--yes", "--seed", "5", "--plan", "one-mount-16", "--serial", "ACC-0042",
                  "--out", str(tmp_path / "run"), check=check)


def points_journaled(journal: Path) -> int:
    if not journal.exists():
        return 0
    with sqlite3.connect(journal) as db:
        tables = {name for (name,) in db.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
        return db.execute("SELECT count(*) FROM points").fetchone()[0] if "points" in tables else 0


def test_an_overdue_standard_stops_the_run_in_one_line_before_anything_moves(lc, tmp_path, bench):
    done = run(lc, tmp_path, check=2)
    assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
    yesterday = (TODAY - timedelta(days=1)).isoformat()
    assert f"DMM MY-DMM-7 (certificate CAL-2025-118) was due {yesterday}" in done.stderr
    assert "nothing was moved" in done.stderr and "labcal standard override" in done.stderr
    assert not (tmp_path / "run").exists()
    assert points_journaled(tmp_path / "journal.sqlite") == 0 and points_journaled(bench) == 0


def test_a_standard_in_date_or_on_another_bench_lets_the_run_go_on(lc, tmp_path, bench):
    lc("standard", "edit", "my-dmm-7", "--bench", "bench-2")  # any case finds it
    run(lc, tmp_path)
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    assert "overrides" not in cert and cert["administration"]["traceability"] == []


def test_an_approvers_override_lets_the_run_go_on_and_every_document_states_it(lc, tmp_path, bench,
                                                                              approver):
    until = TODAY + timedelta(days=3)
    done = lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Ann Lee", "--role",
                  "Technical manager", "--key", str(approver), "--until", until.isoformat(), "--json")
    assert json.loads(done.stdout)["valid_until"] == until.isoformat()
    measured = run(lc, tmp_path)
    assert "under Ann Lee's override" in " ".join(measured.stderr.split())
    folder = tmp_path / "run"
    cert = json.loads((folder / "certificate.json").read_text(encoding="utf-8"))
    [override] = cert["overrides"]
    assert (override["kind"], override["by"], override["reason"]) == ("reference standard",
                                                                      "Ann Lee (Technical manager)", REASON)
    assert any(REASON in s and "MY-DMM-7" in s for s in cert["statements"])
    # the standard used is on the certificate's traceability, with the certificate and due date registered
    [used] = cert["administration"]["traceability"]
    assert (used["equipment"], used["certificate"], used["issued_by"], used["due"]) == (
        "DMM", "CAL-2025-118", "Volt Lab", (TODAY - timedelta(days=1)).isoformat())
    assert "Keysight 34970A" in used["identity"] and "MY-DMM-7" in used["identity"]
    from pypdf import PdfReader

    pdf = " ".join(" ".join(page.extract_text() for page in PdfReader(folder / "report.pdf").pages).split())
    assert REASON in pdf and "overrides the run was measured under" in pdf
    # dates as people write them (%B: the C locale's English month), the JSON keeping ISO 8601
    calibrated = datetime.fromisoformat(cert["calibrated_utc"]).astimezone(UTC)
    due = TODAY - timedelta(days=1)
    assert f"{calibrated.day} {calibrated:%B %Y}, {calibrated:%H:%M} UTC" in pdf
    assert f"due {due.day} {due:%B %Y}" in pdf
    html = (folder / "report.html").read_text(encoding="utf-8")
    assert REASON in html and "overrides the run was measured under" in html
    # the approver's view reads the same override from the lab database, by the lab's run number
    from labcal.app.runs import ReadLog, overrides_of

    number = json.loads(lc("runs", "--json").stdout)["runs"][0]["id"]
    [seen] = overrides_of(ReadLog(str(number)))
    assert (seen.kind, seen.reason, seen.by) == ("reference standard", REASON, "Ann Lee (Technical manager)")


def test_an_override_signature_holds_in_a_second_implementation_over_its_row(lc, bench, approver):
    """libsodium (`second_ed25519`) accepts the approver's signature over the override's row as the
    lab database holds it, in canonical JSON (sorted keys, no spaces, UTF-8) of the standard, its due
    date, the last valid day, the reason, the approver, the role and the time recorded: the bytes
    made here from the row. A longer validity or another reason: refused."""
    lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Ann Lee", "--role",
           "Technical manager", "--key", str(approver))
    with closing(sqlite3.connect(bench)) as db:
        [row] = db.execute("SELECT standard_key, due_on, valid_until, reason, approver, role, recorded_utc, "
                           "signature FROM standard_overrides").fetchall()
    names = ("standard", "due_on", "valid_until", "reason", "approver", "role", "recorded_utc")
    fields, signature = dict(zip(names, row[:7], strict=True)), row[7]
    assert (fields["due_on"], fields["reason"]) == ((TODAY - timedelta(days=1)).isoformat(), REASON)

    def covered(**changed: str) -> bytes:
        return json.dumps({**fields, **changed}, sort_keys=True, separators=(",", ":"),
                          ensure_ascii=False).encode("utf-8")

    public = approver.with_suffix(".pub")
    assert holds(public, covered(), signature)
    assert not holds(public, covered(valid_until=(TODAY + timedelta(days=30)).isoformat()), signature)
    assert not holds(public, covered(reason="no reason"), signature)


def test_an_override_whose_row_was_changed_after_signing_holds_nothing(lc, tmp_path, bench, approver):
    lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Ann Lee", "--role",
           "Technical manager", "--key", str(approver))
    with sqlite3.connect(bench) as db:  # a longer validity, written into the file by hand
        later = (TODAY + timedelta(days=30)).isoformat()
        db.execute("UPDATE standard_overrides SET valid_until = ?", (later,))
    done = run(lc, tmp_path, check=2)
    assert "signature does not hold" in done.stderr and not (tmp_path / "run").exists()


def test_a_recalibrated_standard_no_longer_takes_an_old_override_and_needs_none_in_date(lc, tmp_path, bench,
                                                                                       approver):
    lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Ann Lee", "--role",
           "Technical manager", "--key", str(approver))
    # a new certificate whose due date has passed too: the override was for the old due date
    lc("standard", "edit", "MY-DMM-7", "--calibrated", (TODAY - timedelta(days=20)).isoformat(),
           "--due", (TODAY - timedelta(days=2)).isoformat())
    done = run(lc, tmp_path, check=2)
    assert f"recorded against due date {(TODAY - timedelta(days=1)).isoformat()}" in done.stderr
    show = json.loads(lc("standard", "show", "MY-DMM-7", "--json").stdout)
    assert show["overdue"] and [o["holds"] for o in show["overrides"]] == [False]


def test_only_a_registered_approver_records_an_override_and_never_for_long(lc, tmp_path, bench,
                                                                             approver):
    lc("certificate", "keygen", "--out", str(tmp_path / "mallory"))
    stranger = lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Mallory", "--role",
                      "Technical manager", "--key", str(tmp_path / "mallory.key"), check=2)
    assert "only a registered approver" in stranger.stderr and stranger.stderr.count("\n") == 1
    too_long = lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Ann Lee", "--role",
                      "Technical manager", "--key", str(approver), "--until",
                      (TODAY + timedelta(days=32)).isoformat(), check=2)
    assert "at most 31 days" in too_long.stderr
    with sqlite3.connect(bench) as db:
        assert db.execute("SELECT count(*) FROM standard_overrides").fetchone()[0] == 0


def test_a_standard_is_registered_with_its_calibration_or_refused_in_one_line(lc):
    missing = lc("standard", "add", "PT-1", "--kind", "pitch-table", check=2)
    assert "--certificate, --calibrated, --due" in missing.stderr and missing.stderr.count("\n") == 1
    backwards = lc("standard", "add", "PT-1", "--kind", "pitch-table", "--certificate", "C",
                       "--calibrated", "2026-05-01", "--due", "2026-04-30", check=2)
    assert "is not after --calibrated" in backwards.stderr
    lc("standard", "add", "PT-1", "--kind", "pitch-table", "--certificate", "C", "--calibrated",
           "2026-05-01", "--due", "2027-05-01")
    again = lc("standard", "add", "pt-1", "--kind", "pitch-table", "--certificate", "C", "--calibrated",
                   "2026-05-01", "--due", "2027-05-01", check=2)
    assert "already registered as PT-1" in again.stderr
    listed = json.loads(lc("standard", "list", "--on", "2027-05-02", "--json").stdout)["standards"]
    assert [(s["serial"], s["overdue"]) for s in listed] == [("PT-1", True)]


def test_a_station_file_names_a_standard_the_register_lacks_and_is_refused():
    from labcal.app.standards import standards_for_run
    from labcal.errors import LabcalError

    with pytest.raises(LabcalError, match="names reference standard\\(s\\) NOPE-1"):
        standards_for_run(["NOPE-1"], "bench-9", None, TODAY)


def test_a_benchs_role_on_postgresql_reads_the_standards_but_cannot_write_an_override(lc, postgres_url):  # noqa: F811
    up = lc("db", "upgrade", "--db", postgres_url)
    assert up.returncode == 0
    granted = lc("db", "grant-station", "bench-1", "--db", postgres_url).stdout.strip().splitlines()[-1]
    lc("standard", "add", "MY-DMM-7", "--kind", "dmm", "--certificate", "C-1", "--calibrated",
           "2025-01-01", "--due", "2025-12-31", "--bench", "bench-1", "--db", postgres_url)
    with psycopg.connect(granted) as conn:
        assert conn.execute("SELECT serial FROM standards").fetchall() == [("MY-DMM-7",)]
    for sql in ("INSERT INTO standard_overrides (standard_key, due_on, valid_until, reason, approver, role, "
                "key_id, signature, recorded_utc) VALUES ('my-dmm-7', '2025-12-31', '2099-01-01', 'r', 'a', "
                "'r', 'k', 's', '2026-01-01')",
                "UPDATE standards SET due_on = '2099-01-01'"):
        with psycopg.connect(granted) as conn, pytest.raises(psycopg.errors.InsufficientPrivilege):
            conn.execute(sql)
    # and the run's check, made as the bench's role, finds the standard overdue
    from labcal.app.standards import standards_for_run
    from labcal.errors import LabcalError

    with pytest.raises(LabcalError, match="MY-DMM-7"):
        standards_for_run([], "bench-1", granted, date(2026, 1, 1))


def test_the_approvers_view_lists_a_fault_resumed_after_but_not_a_pause_for_ctrl_c(lc, tmp_path):
    """The journal's own words: the sequencer pauses on a device fault with "fault: …", and an answered
    pause journals "operator resumed after the pause" (a Ctrl-C pause is not a fault accepted)."""
    from labcal.app.runs import ReadLog, overrides_of
    from labcal.store.journal import Journal
    from labcal.store.rundir import read_run_json

    lc("run", "--sim", "--yes", "--seed", "5", "--plan", "one-mount-16", "--no-report", "--operator", "Bo",
       "--out", str(tmp_path / "run"))
    info = read_run_json(tmp_path / "run")
    with Journal(Path(info["journal"])) as journal:
        for kind, message in (("pause", "operator paused"), ("resume", "operator resumed after the pause"),
                              ("fault", "pitch: no answer within 0.5 s"),
                              ("pause", "fault: pitch: no answer within 0.5 s"),
                              ("resume", "operator resumed after the pause")):
            journal.event(info["run_id"], kind, message, station_time=10.0)
    [accepted] = overrides_of(ReadLog(str(tmp_path / "run")))
    assert (accepted.kind, accepted.by) == ("fault accepted", "Bo")
    assert "fault: pitch: no answer within 0.5 s" in accepted.what


def test_a_standard_fallen_due_since_the_run_began_stops_its_resume_until_an_override(lc, tmp_path,
                                                                                     monkeypatch):
    monkeypatch.setenv("LABCAL_STATION", "bench-1")
    answers = tmp_path / "answers"
    answers.write_text("y\nstop\n", encoding="utf-8")  # the first mount confirmed, stopped at the second
    folder = str(tmp_path / "run")
    stopped = lc("run", "--sim", "--answers", str(answers), "--seed", "5", "--serial", "ACC-0042", "--out",
                 folder, check=None)
    assert "stopped" in stopped.stderr
    kept = points_journaled(tmp_path / "labcal.sqlite")
    assert kept > 0
    lc("standard", "add", "MY-DMM-7", "--kind", "dmm", "--certificate", "CAL-2025-118", "--calibrated",
       (TODAY - timedelta(days=366)).isoformat(), "--due", (TODAY - timedelta(days=1)).isoformat(),
       "--bench", "bench-1")
    refused = lc("resume", folder, "--yes", check=2)
    assert "MY-DMM-7" in refused.stderr and "nothing was moved" in refused.stderr
    assert points_journaled(tmp_path / "labcal.sqlite") == kept
    lc("certificate", "keygen", "--out", str(tmp_path / "ann"))
    lc("certificate", "approvers", "add", "Ann Lee", "--role", "Technical manager", "--public-key",
       str(tmp_path / "ann.pub"))
    lc("standard", "override", "MY-DMM-7", "--reason", REASON, "--by", "Ann Lee", "--role",
       "Technical manager", "--key", str(tmp_path / "ann.key"))
    lc("resume", folder, "--yes")
    cert = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    assert [(o["kind"], o["reason"]) for o in cert["overrides"]] == [("reference standard", REASON)]

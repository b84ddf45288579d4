"""The application layer (`labcal.app`): each use case called with a typed request, no
argparse; and every read pure — a run folder's files (names, bytes, mtimes) and the lab database's
bytes are the same after it as before, by hashes taken here."""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import pytest
from simulated_runs import bench_run, simulated_run

from labcal.app.certificates import (
    AddApprover,
    ApproveCertificate,
    IssueCertificate,
    ListApprovers,
    MakeKeys,
    VerifyCertificate,
    add_approver,
    approve_certificate,
    issue_certificate,
    list_approvers,
    make_keys,
    verify_certificate,
)
from labcal.app.folders import ExportRun, RebuildRunFolder, export_run, rebuild_run_folder
from labcal.app.histories import DeviceHistory, InstrumentHistory, device_history, instrument_history
from labcal.app.runs import ListRuns, ReadLog, list_runs, read_log
from labcal.cli import main
from labcal.errors import LabcalError
from labcal.store.record import load_run

SERIAL = "ACC-0042"
EXPORTS = ("plan.toml", "readings.csv", "fit.json", "run.json")


def files(folder: Path) -> dict[str, tuple[str, int]]:
    """Every file under ``folder``: its SHA-256 and its mtime (ns), by relative name."""
    return {p.relative_to(folder).as_posix(): (sha(p), p.stat().st_mtime_ns)
            for p in sorted(folder.rglob("*")) if p.is_file()}


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """A lab database with a dry run (issued at its end) and a bench run (issued, then approved
    through the application layer: a dry run is never approved)."""
    base = tmp_path_factory.mktemp("app")
    db = base / "lab.sqlite"
    simulated_run(base / "dry", db, seed=7, serial=SERIAL)
    bench_run(base / "bench", db, SERIAL)
    keys = make_keys(MakeKeys(str(base / "approver")))
    assert keys.private_key.is_file() and keys.public_key.is_file() and len(keys.key_id) == 64
    added = add_approver(AddApprover("A. Metrologist", "Technical manager", str(keys.public_key), str(db)))
    assert added.key_id == keys.key_id and added.active
    approved = approve_certificate(ApproveCertificate(str(base / "bench"), "A. Metrologist",
                                                      "Technical manager", str(keys.private_key), str(db)))
    assert approved.to_json()["approved_by"] == "A. Metrologist"
    return base, db


@pytest.fixture
def unchanged(lab):
    """Asserts, after the test, that neither run folder nor the database's bytes changed."""
    base, db = lab
    before = {name: files(base / name) for name in ("dry", "bench")}, sha(db)
    yield lab
    assert ({name: files(base / name) for name in ("dry", "bench")}, sha(db)) == before


def test_list_runs_reads_only(unchanged):
    _, db = unchanged
    found = list_runs(ListRuns(str(db)))
    assert [(r.id, r.serial, r.status) for r in found.runs] == [(1, SERIAL, "complete"),
                                                                    (2, SERIAL, "complete")]
    assert list_runs(ListRuns(str(db), statuses=("interrupted",))).runs == ()


def test_a_missing_database_is_listed_empty_and_not_created(tmp_path):
    found = list_runs(ListRuns(str(tmp_path / "none.sqlite")))
    assert not found.exists and found.runs == () and not (tmp_path / "none.sqlite").exists()
    with pytest.raises(LabcalError, match="no lab database here"):
        read_log(ReadLog("1", str(tmp_path / "none.sqlite")))
    assert not (tmp_path / "none.sqlite").exists()


def test_read_log_reads_only(unchanged):
    base, db = unchanged
    by_id, by_folder = read_log(ReadLog("2", str(db))), read_log(ReadLog(str(base / "bench")))
    assert by_id == by_folder and by_id.points_ok == 16 and by_id.run_dir == str(base / "bench")
    assert any(e.kind == "prompt" for e in by_id.events)


def test_instrument_history_reads_only(unchanged):
    _, db = unchanged
    history = instrument_history(InstrumentHistory(SERIAL, str(db), include_simulated=True))
    assert len(history.entries) == 2 and len(history.tables) == 3  # one table per sensor x, y, z
    assert [len(row) for row in history.tables[0].rows] == [5, 5]  # #, B, and three of M's rows
    assert history.document["serial"] == SERIAL


def test_device_history_reads_only(unchanged):
    _, db = unchanged
    history = device_history(DeviceHistory("SIMULATED", str(db)))
    assert len(history.tables) == 1 and len(history.tables[0].rows) == 1  # the dry run's estimate


def test_verify_reads_only(unchanged):
    base, db = unchanged
    verified = verify_certificate(VerifyCertificate(str(base / "bench" / "certificate.json"), db=str(db)))
    assert verified.approved_by == "A. Metrologist" and verified.verified_against == "the registered key"
    assert verified.dcc == str(base / "bench" / "certificate.dcc.xml")
    assert [a.name for a in list_approvers(ListApprovers(str(db))).approvers] == ["A. Metrologist"]


def test_loading_a_run_reads_only(unchanged):
    base, _ = unchanged
    record = load_run(base / "dry")
    assert record.notes == () and len(record.readings.volts) == 64


def test_an_edited_export_is_reported_not_rewritten(lab, tmp_path):
    """Opening a run whose readings.csv was edited names it and the command that rebuilds the folder;
    the folder and the database stay as they are."""
    base, db = lab
    copy = tmp_path / "copy"
    shutil.copytree(base / "dry", copy)  # its run.json names the same journal and run
    (copy / "readings.csv").write_text("replicate,y_deg\n1,0\n")
    (copy / "fit.json").unlink()
    before, db_before = files(copy), sha(db)
    notes = load_run(copy).notes
    assert files(copy) == before and sha(db) == db_before
    assert any(n.startswith("readings.csv was edited by hand") and f"`labcal export {copy}`" in n
               for n in notes), notes
    assert any(n.startswith("fit.json is missing") for n in notes), notes


def test_export_to_another_folder_leaves_the_run_and_the_database_as_they_were(unchanged, tmp_path):
    """A regression: `labcal export RUN --out OTHER` re-pointed the run to OTHER."""
    base, db = unchanged
    written = export_run(ExportRun("1", str(tmp_path / "other"), str(db)))
    assert written.folder == tmp_path / "other" and written.notes == ()
    assert {n: (tmp_path / "other" / n).read_bytes() for n in EXPORTS} == \
        {n: (base / "dry" / n).read_bytes() for n in EXPORTS}  # the same bytes as the run's own folder
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
        assert con.execute("SELECT run_dir FROM runs WHERE id = 1").fetchone() == (str(base / "dry"),)
    # and through the command line, given the run's folder
    assert main(["export", str(base / "bench"), "--out", str(tmp_path / "again"), "--db", str(db)]) == 0
    assert (tmp_path / "again" / "readings.csv").read_bytes() == \
        (base / "bench" / "readings.csv").read_bytes()


def test_export_into_the_runs_own_folder_is_refused(unchanged):
    base, db = unchanged
    with pytest.raises(LabcalError, match="own folder; `labcal export 1` without --out rebuilds it"):
        export_run(ExportRun("1", str(base / "dry"), str(db)))


def test_rebuild_rewrites_the_runs_folder_and_records_where_it_is(tmp_path):
    """Rebuilding is the use case that writes: an edited file kept as NAME.edited, a missing one
    rewritten; rebuilding a copy makes the copy the run's folder (journaled)."""
    db = tmp_path / "lab.sqlite"
    assert main(["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--out",
                 str(tmp_path / "r"), "--db", str(db)]) == 0
    original = {n: (tmp_path / "r" / n).read_bytes() for n in EXPORTS}
    (tmp_path / "r" / "readings.csv").write_text("edited\n")
    rebuilt = rebuild_run_folder(RebuildRunFolder("1", str(db)))
    assert rebuilt.recorded is None and len(rebuilt.notes) == 1
    assert {n: (tmp_path / "r" / n).read_bytes() for n in EXPORTS} == original
    assert (tmp_path / "r" / "readings.csv.edited").read_text() == "edited\n"
    export_run(ExportRun("1", str(tmp_path / "copy"), str(db)))
    moved = rebuild_run_folder(RebuildRunFolder(str(tmp_path / "copy")))
    assert moved.recorded == str(tmp_path / "r")
    assert list_runs(ListRuns(str(db))).runs[0].run_dir == str(tmp_path / "copy")


def test_issuing_writes_its_documents_and_leaves_the_exports_as_they_are(tmp_path):
    """Issuing writes the certificate, report and DCC; an edited readings.csv is named in its notes,
    not rewritten, and the certificate names the journal's readings (digest computed here from the
    database with sqlite3)."""
    db, run_dir = tmp_path / "lab.sqlite", tmp_path / "r"
    assert main(["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--out", str(run_dir),
                 "--db", str(db)]) == 0
    (run_dir / "readings.csv").write_text("edited\n")
    kept = {n: files(run_dir)[n] for n in EXPORTS}
    issued = issue_certificate(IssueCertificate(str(run_dir), str(db), serial="SIMULATED"))
    assert {n: files(run_dir)[n] for n in EXPORTS} == kept
    assert not (run_dir / "readings.csv.edited").exists()
    assert any(n.startswith("readings.csv was edited by hand") for n in issued.notes), issued.notes
    with sqlite3.connect(db) as con:
        rows = con.execute("SELECT seq, replicate, y_deg, u_deg, pitch_deg, roll_deg, vx, vy, vz, temp_c "
                           "FROM points WHERE run_id = 1 AND status = 'ok' ORDER BY seq, replicate"
                           ).fetchall()
    digest = hashlib.sha256(json.dumps([list(r) for r in rows], separators=(",", ":")).encode()).hexdigest()
    cert = json.loads((run_dir / "certificate.json").read_text())
    assert cert["data"]["readings_sha256"] == digest and issued.to_json()["certificate"] == str(
        run_dir / "certificate.json")
    assert len(issued.tables) == 4


def test_bad_monte_carlo_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(LabcalError, match="--monte-carlo 5: give 100"):
        issue_certificate(IssueCertificate(str(tmp_path), monte_carlo=5))
    assert not any(tmp_path.iterdir())


class Front:
    """A front end for a run without a terminal: what it is told is kept, prompts are answered from
    a list (as `labcal run --answers` does), and the progress view shows nothing."""

    def __init__(self, tmp_path: Path, answers: str | None = None):
        from conftest import quiet_console

        self.lines: list[str] = []
        self.console = quiet_console()
        self.answers = None
        if answers is not None:
            self.answers = tmp_path / "answers.txt"
            self.answers.write_text(answers)
        self.points: list[int] = []
        self.tmp_path = tmp_path

    def say(self, text: str, markup: bool = True) -> None:
        self.lines.append(text)

    def operator(self):
        from labcal.run.operator import AutoOperator, ScriptedOperator

        return AutoOperator(self.console) if self.answers is None else ScriptedOperator(self.console,
                                                                                         self.answers)

    def checklist(self, bench, station, points, samples):
        """The real checklist, unattended: an unmet item stops the run (as with --yes)."""
        from datetime import datetime

        from labcal.bench.checklist import PowerOn, journaled, run_checklist, unmet

        now = datetime.now().astimezone()
        items = run_checklist(None, bench, station, db=self.tmp_path / "lab.sqlite", run_folder=self.tmp_path,
                              points=points, samples=samples, power=PowerOn(), now=now)
        assert not unmet(items), unmet(items)
        return journaled(items, PowerOn())

    def display(self, total, done):
        from contextlib import nullcontext

        from labcal.run.operator import Terminal

        class Seen:  # the run's progress as a subscriber sees it
            KINDS = ("point",)

            def __call__(inner, event) -> None:
                self.points.append(event.seq)

        return nullcontext((Seen(), Terminal()))


def test_start_stop_resume_and_resume_again_through_the_application_layer(tmp_path):
    """four-mount-64 is four mounts of 16 points: stopped at the second mount's prompt, 16 readings
    are kept; the resume measures the other 48; a third call finds the run complete."""
    from labcal.app.calibration import (
        AlreadyComplete,
        Ended,
        Estimated,
        Finished,
        ResumeRun,
        StartRun,
        resume_run,
        start_run,
    )

    db, run_dir = tmp_path / "lab.sqlite", tmp_path / "r"
    estimated = start_run(StartRun(sim=True, dry_run=True, db=str(db), out=str(run_dir)), Front(tmp_path))
    assert isinstance(estimated, Estimated) and estimated.plan.n_points == 64
    assert not run_dir.exists() and not db.exists()  # a dry run moves nothing and journals nothing
    front = Front(tmp_path, "y\nq\n")
    ended = start_run(StartRun(sim=True, seed=4, db=str(db), out=str(run_dir), no_report=True), front)
    assert isinstance(ended, Ended) and ended.how == "stopped" and ended.points_kept == 16
    assert front.lines[0] == f"Run directory: {run_dir}"
    assert sorted(front.points) == list(range(16))  # the front end's view heard every point measured
    copy = tmp_path / "copy"  # resumed from a copy (as after a full disk): the copy is the run's from then on
    export_run(ExportRun(str(run_dir), str(copy), str(db)))
    assert list_runs(ListRuns(str(db))).runs[0].run_dir == str(run_dir)
    resumed = Front(tmp_path)
    finished = resume_run(ResumeRun(str(copy), db=str(db), no_report=True), resumed)
    assert isinstance(finished, Finished) and finished.issued is None
    assert sorted(resumed.points) == list(range(16, 64))
    assert finished.result.outcome.points_recorded == 64 and finished.journal == db
    assert list_runs(ListRuns(str(db))).runs[0].run_dir == str(copy)
    again = resume_run(ResumeRun(str(copy), db=str(db), no_report=True), Front(tmp_path))
    assert isinstance(again, AlreadyComplete) and again.certificate is None and again.run_id == 1


def test_the_read_commands_change_nothing(unchanged, capsys):
    """The same reads through the command line, text and JSON."""
    base, db = unchanged
    for args in (["runs"], ["runs", "--json"], ["log", "1"], ["log", str(base / "bench"), "--json"],
                 ["history", SERIAL, "--include-simulated"], ["device", "history", "SIMULATED", "--json"],
                 ["certificate", "verify", str(base / "bench" / "certificate.json")],
                 ["certificate", "approvers", "list"]):
        assert main([*args, "--db", str(db)]) == 0, args
    assert "A. Metrologist" in capsys.readouterr().out

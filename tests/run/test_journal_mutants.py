"""The journal's every write and read, checked against what was put in by hand, the published SHA-256
test vectors (FIPS 180-2) and the raw bytes and pragmas read back with sqlite3 itself
(docs/mutation.md)."""

from __future__ import annotations

import hashlib
import re
import sqlite3
import struct
import uuid
from dataclasses import replace
from datetime import datetime, timedelta

import numpy as np
import pytest

from labcal.errors import LabcalError
from labcal.store.journal import Journal, Manifest, PointRecord, db_path, sha256, utc_now

SHA_ABC = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"  # FIPS 180-2, B.1
SHA_EMPTY = "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"

MANIFEST = Manifest(run_dir="runs/a", plan_name="four-mount-64", plan_text="abc", station_text="",
                    software_version="0.1.0", settings={"dwell": 2.5}, metadata={"note": "ü"},
                    instrument_serial="SN-7", device_id="CD-1", operator="ana")


def _point(seq: int, status: str = "ok", **changes: object) -> PointRecord:
    point = PointRecord(seq=seq, replicate=1, y_deg=0.0, u_deg=180.0, pitch_deg=30.0 + seq, roll_deg=-45.0,
                        pitch_read=30.001, roll_read=-44.999, attempt=1, status=status, t_start=10.0 * seq,
                        t_end=10.0 * seq + 4.5, n_samples=2, vx=0.1 * seq, vy=0.2, vz=-0.3, sd_vx=1e-5,
                        sd_vy=2e-5, sd_vz=3e-5, temp_c=21.5, settle_s=1.25, settle_verdict="settled")
    return replace(point, **changes)


def test_sha256_is_the_published_digest_of_the_utf8_text():
    assert sha256("abc") == SHA_ABC
    assert sha256("") == SHA_EMPTY
    assert sha256("°") == hashlib.sha256(b"\xc2\xb0").hexdigest()  # "°" is C2 B0 in UTF-8


def test_utc_now_is_iso_8601_utc_to_the_millisecond():
    text = utc_now()
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}\+00:00", text), text
    assert datetime.fromisoformat(text).utcoffset() == timedelta(0)


def test_db_path_takes_the_option_else_the_environment(tmp_path, monkeypatch):
    assert db_path(tmp_path / "given.sqlite") == tmp_path / "given.sqlite"
    assert db_path(str(tmp_path / "s.sqlite")) == tmp_path / "s.sqlite"
    monkeypatch.setenv("LABCAL_DB", str(tmp_path / "env.sqlite"))
    monkeypatch.delenv("LABCAL_CONFIG", raising=False)
    monkeypatch.chdir(tmp_path)
    assert db_path(None) == tmp_path / "env.sqlite"
    assert db_path("") == tmp_path / "env.sqlite"


def test_durability_is_full_unless_relaxed(tmp_path):
    """SQLite's PRAGMA synchronous: 2 = FULL, 1 = NORMAL."""
    with Journal(tmp_path / "lab.sqlite") as j:
        assert j.db.execute("PRAGMA synchronous").fetchone()[0] == 2
    with Journal(tmp_path / "lab.sqlite", durable=False) as j:
        assert j.db.execute("PRAGMA synchronous").fetchone()[0] == 1
    with pytest.raises(sqlite3.ProgrammingError):  # the context closed it
        j.db.execute("SELECT 1")


def test_start_run_stores_the_manifest_with_its_hashes(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j:
        first = j.start_run(MANIFEST)
        second = j.start_run(replace(MANIFEST, run_dir="runs/b", instrument_serial=None))
        row = j.run(first)
        assert second == first + 1
    assert (row.id, row.run_dir, row.plan_name, row.plan_text, row.station_text) == (
        first, "runs/a", "four-mount-64", "abc", "")
    assert (row.plan_hash, row.station_hash) == (SHA_ABC, SHA_EMPTY)
    assert (row.software_version, row.settings, row.metadata) == ("0.1.0", {"dwell": 2.5}, {"note": "ü"})
    assert (row.status, row.reason, row.ended_utc, row.instrument_serial, row.operator) == (
        "running", None, None, "SN-7", "ana")
    assert uuid.UUID(row.uuid).version == 4
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}\+00:00", row.started_utc)
    raw = sqlite3.connect(tmp_path / "lab.sqlite").execute(
        "SELECT device_id, settings, metadata FROM runs WHERE id=?", (first,)).fetchone()
    assert raw == ("CD-1", '{"dwell": 2.5}', '{"note": "\\u00fc"}')


def test_an_unknown_run_is_one_line_naming_the_file(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j, pytest.raises(LabcalError) as err:
        j.run(7)
    assert str(err.value) == f"{tmp_path / 'lab.sqlite'}: no run 7 in this journal"


def test_points_and_their_samples_round_trip_as_little_endian_doubles(tmp_path):
    samples = np.array([[0.0, 1.5, -2.25, 3.0], [0.5, 1.0, 2.0, 4.0]])
    with Journal(tmp_path / "lab.sqlite") as j:
        run = j.start_run(MANIFEST)
        j.record_point(run, _point(2), samples)
        j.record_point(run, _point(1, status="failed", vx=None, vy=None, vz=None), None)
        j.record_point(run, _point(0), samples.astype(np.float32))
        points = j.points(run)
        assert [p.seq for p in points] == [0, 1, 2]  # in schedule order, whatever the order written
        assert points[2] == _point(2)
        assert [p.seq for p in j.points(run, status="ok")] == [0, 2]
        assert [p.seq for p in j.points(run, status="failed")] == [1]
        np.testing.assert_array_equal(j.samples(run, 2), samples)
        np.testing.assert_array_equal(j.samples(run, 0), samples)
        assert j.samples(run, 1).shape == (0, 4)  # no samples stored
        assert j.samples(run, 9).shape == (0, 4)  # no such point
        with pytest.raises(sqlite3.IntegrityError):  # a point is written once
            j.record_point(run, _point(2, vx=9.0), samples)
        assert j.points(run)[2].vx == pytest.approx(0.2)
    blob, utc = sqlite3.connect(tmp_path / "lab.sqlite").execute(
        "SELECT samples, utc FROM points WHERE seq=2").fetchone()
    assert blob == struct.pack("<8d", 0.0, 1.5, -2.25, 3.0, 0.5, 1.0, 2.0, 4.0)
    assert re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}\+00:00", utc)


def test_readings_are_the_good_points_and_temperature_only_when_every_point_has_one(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j:
        run = j.start_run(MANIFEST)
        with pytest.raises(LabcalError) as err:
            j.readings(run)
        assert str(err.value) == f"run {run} has no readings yet"
        j.record_point(run, _point(0), None)
        j.record_point(run, _point(1, status="failed"), None)
        j.record_point(run, _point(2, replicate=2, y_deg=180.0, temp_c=22.0), None)
        r = j.readings(run)
        np.testing.assert_array_equal(r.replicate, [1, 2])
        np.testing.assert_array_equal(r.y_deg, [0.0, 180.0])
        np.testing.assert_array_equal(r.u_deg, [180.0, 180.0])
        np.testing.assert_array_equal(r.pitch_deg, [30.0, 32.0])
        np.testing.assert_array_equal(r.roll_deg, [-45.0, -45.0])
        np.testing.assert_array_equal(r.volts, [[0.0, 0.2, -0.3], [0.2, 0.2, -0.3]])
        np.testing.assert_array_equal(r.temp_c, [21.5, 22.0])
        j.record_point(run, _point(3, temp_c=None), None)
        assert j.readings(run).temp_c is None


def test_events_keep_their_order_kind_time_and_data(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j:
        run = j.start_run(MANIFEST)
        j.event(run, "prompt", "mount 2", {"mount": [180, 0]}, station_time=12.5)
        j.event(run, "answer", "yes")
        events = j.events(run)
    assert [(e.kind, e.message, e.data, e.station_time) for e in events] == [
        ("prompt", "mount 2", {"mount": [180, 0]}, 12.5), ("answer", "yes", None, None)]
    assert all(re.fullmatch(r"\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}\+00:00", e.utc) for e in events)
    raw = sqlite3.connect(tmp_path / "lab.sqlite").execute("SELECT data FROM events ORDER BY id").fetchall()
    assert raw == [('{"mount": [180, 0]}',), (None,)]  # no data is NULL, not the JSON text "null"


def test_rig_time_is_the_latest_point_end_or_event_time(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j:
        run = j.start_run(MANIFEST)
        other = j.start_run(MANIFEST)
        assert j.rig_time(run) == 0.0
        j.record_point(run, _point(3), None)  # t_end 34.5
        assert j.rig_time(run) == 34.5
        j.event(run, "pause", "paused", station_time=50.0)
        j.event(other, "pause", "paused", station_time=99.0)  # another run's clock
        assert j.rig_time(run) == 50.0
        j.event(run, "note", "untimed")
        j.record_point(run, _point(6), None)  # t_end 64.5
        assert j.rig_time(run) == 64.5


def test_finish_reopen_exports_and_moved_folder(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j:
        run = j.start_run(MANIFEST)
        j.finish(run, "complete", exports={"fit.json": SHA_ABC, "readings.csv": SHA_EMPTY})
        row = j.run(run)
        assert (row.status, row.reason) == ("complete", None) and row.ended_utc is not None
        assert j.export_hashes(run) == {"fit.json": SHA_ABC, "readings.csv": SHA_EMPTY}
        j.exported(run, {"fit.json": SHA_EMPTY})  # rewritten: replaces the old hash
        j.exported(run, {})
        assert j.export_hashes(run) == {"fit.json": SHA_EMPTY, "readings.csv": SHA_EMPTY}
        j.reopen(run)
        row = j.run(run)
        assert (row.status, row.reason, row.ended_utc) == ("running", None, None)
        j.finish(run, "interrupted", "SIGTERM")
        row = j.run(run)
        assert (row.status, row.reason) == ("interrupted", "SIGTERM")
        j.set_run_dir(run, "/elsewhere/run")
        assert j.run(run).run_dir == "/elsewhere/run"
        assert j.export_hashes(run + 1) == {}


def test_runs_lists_each_run_with_its_points_counted_and_filters(tmp_path):
    with Journal(tmp_path / "lab.sqlite") as j:
        a = j.start_run(MANIFEST)
        b = j.start_run(replace(MANIFEST, instrument_serial="SN-8", operator=None))
        c = j.start_run(MANIFEST)
        for seq in range(3):
            j.record_point(a, _point(seq), None)
        j.record_point(a, _point(3, status="failed"), None)
        j.record_point(b, _point(0, status="failed"), None)
        j.finish(c, "complete")
        everything = j.runs()
        assert [(s.id, s.instrument_serial, s.operator, s.status, s.points_ok, s.points_failed)
                for s in everything] == [(a, "SN-7", "ana", "running", 3, 1),
                                         (b, "SN-8", None, "running", 0, 1),
                                         (c, "SN-7", "ana", "complete", 0, 0)]
        assert (everything[0].run_dir, everything[0].plan_name, everything[0].reason) == (
            "runs/a", "four-mount-64", None)
        assert everything[2].ended_utc is not None and everything[0].ended_utc is None
        assert [s.id for s in j.runs(serial="SN-7")] == [a, c]
        assert [s.id for s in j.runs(statuses=("complete",))] == [c]
        assert [s.id for s in j.runs(serial="SN-7", statuses=("running", "interrupted"))] == [a]
        assert j.runs(serial="none") == []


def test_a_failed_statement_rolls_back_the_whole_transaction_and_says_which_file(tmp_path):
    path = tmp_path / "lab.sqlite"
    with Journal(path) as j:
        run = j.start_run(MANIFEST)
        insert = "INSERT INTO events (run_id, utc, station_time, kind, message, data) VALUES (?,?,?,?,?,?)"
        with pytest.raises(LabcalError) as err:  # a value sqlite3 cannot bind: ProgrammingError
            j._transaction([(insert, (run, "t", None, "a", "first", None)),
                            (insert, (run, "t", None, "b", object(), None))])
        assert str(err.value).startswith(f"{path}: cannot use the lab database (")
        assert j.events(run) == []  # the first insert went with the second
        assert not j.db.in_transaction
        with pytest.raises(KeyboardInterrupt):
            j._transaction([(insert, (run, "t", None, "a", "first", None)), (insert, _Interrupting())])
        assert j.events(run) == [] and not j.db.in_transaction
        assert j._transaction([(insert, (run, "t", None, "a", "kept", None))]) == 1  # lastrowid


class _Interrupting:
    """Parameters whose reading is interrupted (Ctrl-C while the statement binds them)."""

    def __len__(self) -> int:
        return 6

    def __getitem__(self, index: int) -> object:
        raise KeyboardInterrupt

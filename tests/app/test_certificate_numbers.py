"""The lab's own certificate numbers: a format in the lab file, checked when the file is read; one
gap-free sequence in the lab database, a run keeping its number through reissues; dry runs counted
apart. Real `labcal` commands on the simulated rig and a real SQLite lab database; the expected numbers
are written here by hand from the format."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from datetime import datetime
from pathlib import Path

import psycopg
import pytest
from services import postgres_cluster, postgres_url  # noqa: F401 - fixtures
from test_instruments import InProcess

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.store.certificate_numbers import assigned


@pytest.fixture
def lc(capsys) -> InProcess:
    return InProcess(capsys)


def lab_file(tmp_path: Path, monkeypatch, pattern: str, code: str = "ECL") -> None:
    path = tmp_path / "lab.toml"
    text = f'[laboratory]\nname = "Example Lab"\ncode = "{code}"\ncertificate_number = "{pattern}"\n'
    path.write_text(text, encoding="utf-8")
    monkeypatch.setenv("LABCAL_CONFIG", str(path))


@pytest.mark.parametrize(("pattern", "said"), [
    ("{lab}-{yr}-{seq:04d}", "unknown field(s) {yr}"), ("{lab}-{year}", "it needs {seq}"),
    ("{lab}-{seq:04q}", "not a format"), ("{lab}/{seq}", "no /"), ("{lab}-{seq", "not a format")])
def test_a_bad_numbering_format_is_one_line_when_the_lab_file_is_read(lc, tmp_path, monkeypatch, pattern,
                                                                       said):
    lab_file(tmp_path, monkeypatch, pattern)
    done = lc("config", "show", check=2)
    assert said in done.stderr and done.stderr.count("\n") == 1 and "certificate_number" in done.stderr


def test_the_labs_code_is_needed_where_the_format_names_it(lc, tmp_path, monkeypatch):
    lab_file(tmp_path, monkeypatch, "{lab}-{seq}", code="")
    assert "set code" in lc("config", "show", check=2).stderr


def test_dry_runs_are_numbered_in_their_own_gap_free_sequence_and_a_reissue_keeps_its_number(lc, tmp_path,
                                                                                               monkeypatch):
    lab_file(tmp_path, monkeypatch, "{lab}-{year}-{seq:04d}")
    for name in ("r1", "r2"):
        lc("run", "--sim", "--yes", "--seed", "5", "--plan", "one-mount-16", "--serial", "ACC-0042", "--out",
           str(tmp_path / name))
    certs = [json.loads((tmp_path / name / "certificate.json").read_text(encoding="utf-8"))
             for name in ("r1", "r2")]
    years = [datetime.fromisoformat(c["calibrated_utc"]).year for c in certs]
    assert [c["lab_number"] for c in certs] == [f"SIMULATED-ECL-{years[0]}-0001",
                                                f"SIMULATED-ECL-{years[1]}-0002"]
    lc("report", str(tmp_path / "r1"))  # issued again: the same number
    again = json.loads((tmp_path / "r1" / "certificate.json").read_text(encoding="utf-8"))
    assert again["lab_number"] == certs[0]["lab_number"]
    dcc = (tmp_path / "r1" / "certificate.dcc.xml").read_text(encoding="utf-8")
    assert f">{certs[0]['lab_number']} rev. 1<" in dcc


def test_benches_numbering_at_once_leave_no_gap_and_no_number_twice(lab_database):
    lab = open_lab(OpenLab(None, must_exist=False))
    got: list[str] = []

    def bench(name: str) -> None:
        for k in range(12):
            got.append(assigned(lab.engine, f"{name}-{k}", 2026, lambda seq: f"ECL-2026-{seq:04d}"))

    try:
        threads = [threading.Thread(target=bench, args=(name,)) for name in ("bench-1", "bench-2")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert sorted(got) == [f"ECL-2026-{seq:04d}" for seq in range(1, 25)]
        assert assigned(lab.engine, "bench-1-3", 2026, lambda seq: "unused") in got  # a run keeps its number
        assert assigned(lab.engine, "other-year", 2027, lambda seq: f"ECL-2027-{seq:04d}") == "ECL-2027-0001"
    finally:
        lab.close()


def test_a_benchs_role_on_postgresql_numbers_in_the_labs_one_sequence(lc, postgres_url):  # noqa: F811
    from labcal.store.labdb import lab_engine

    lc("db", "upgrade", "--db", postgres_url)
    benches = [lc("db", "grant-station", name, "--db", postgres_url).stdout.strip().splitlines()[-1]
               for name in ("bench-1", "bench-2")]
    engines = [lab_engine(url) for url in benches]
    try:
        got = [assigned(engines[k % 2], f"run-{k}", 0, lambda seq: f"ECL-{seq:05d}") for k in range(4)]
        assert got == ["ECL-00001", "ECL-00002", "ECL-00003", "ECL-00004"]
    finally:
        for engine in engines:
            engine.dispose()



NUMBERING = """
import sys
from labcal.store.certificate_numbers import assigned
from labcal.store.labdb import lab_engine
engine = lab_engine(sys.argv[1])
try:
    with engine.connect():  # connected and ready: then all start at once
        pass
    print("ready", flush=True)
    sys.stdin.readline()
    for k in range(30):
        print(assigned(engine, f"{sys.argv[2]}-{k}", 0, lambda seq: f"ECL-{seq:05d}"), flush=True)
finally:
    engine.dispose()
"""


def test_benches_numbering_at_once_in_their_own_processes_on_postgresql_leave_no_gap(lc, postgres_url):  # noqa: F811
    """Three processes, each a bench with its own role and connection, number thirty runs each,
    started together once all are connected: 90 numbers, none twice, none skipped, and PostgreSQL's
    own count and maximum agree. The benches' numbers interleave (they raced for the same next
    number), which is what the unique sequence and the retry are for."""
    lc("db", "upgrade", "--db", postgres_url)
    names = ("bench-1", "bench-2", "bench-3")
    urls = [lc("db", "grant-station", name, "--db", postgres_url).stdout.strip().splitlines()[-1]
            for name in names]
    benches = [subprocess.Popen([sys.executable, "-c", NUMBERING, url, name], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
               for url, name in zip(urls, names, strict=True)]
    try:
        for bench in benches:
            assert bench.stdout is not None and bench.stdout.readline() == "ready\n"
        for bench in benches:
            assert bench.stdin is not None
            bench.stdin.write("go\n")
            bench.stdin.flush()
        outputs = [bench.communicate(timeout=120) for bench in benches]
    finally:
        for bench in benches:
            bench.kill()
    assert [bench.returncode for bench in benches] == [0, 0, 0], [err for _, err in outputs]
    each = [[int(line.removeprefix("ECL-")) for line in out.split()] for out, _ in outputs]
    assert sorted(n for numbers in each for n in numbers) == list(range(1, 91))
    assert any(numbers != list(range(numbers[0], numbers[0] + 30)) for numbers in each), each  # they raced
    with psycopg.connect(postgres_url) as conn:
        count, top, runs = conn.execute("SELECT count(*), max(seq), count(DISTINCT run_uuid) FROM "
                                        "certificate_numbers WHERE scope = 0").fetchone()
    assert (count, top, runs) == (90, 90, 90)

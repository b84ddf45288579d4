"""Where the lab database is: a path, `sqlite:///PATH` or
`postgresql://USER@HOST:PORT/DBNAME` in --db, $LABCAL_DB or the lab file; any other `SCHEME://` is
one line, never a folder named after it."""

from __future__ import annotations

import sqlite3

import pytest

from labcal.cli import main


@pytest.mark.parametrize("location, message", [
    ("postgresql://lab@127.0.0.1:5432", "names no database; write postgresql://USER@HOST:PORT/DBNAME"),
    ("postgresql+psycopg://lab@db/", "names no database"),
    ("mysql://lab@db/labcal", "unknown database scheme 'mysql'"),
    ("sqlite://", "names no file; write sqlite:///PATH"),
])
def test_a_location_that_is_no_sqlite_file_is_one_line_and_creates_nothing(location, message, tmp_path,
                                                                             monkeypatch, capsys):
    monkeypatch.setenv("LABCAL_DB", location)
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["runs"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "$LABCAL_DB" in err and message in err and "Traceback" not in err
    assert main(["run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "r")]) == 2
    assert message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == before  # no folder named after the URL, no run
    assert main(["runs", "--db", location]) == 2 and "--db" in capsys.readouterr().err


def test_sqlite_urls_name_the_file_as_sqlalchemy_reads_them(tmp_path, monkeypatch, capsys):
    """`sqlite:///lab.sqlite` is relative (to the current folder), `sqlite:////abs/lab.sqlite` absolute;
    a run journals into that file."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("LABCAL_DB", "sqlite:///relative.sqlite")
    assert main(["run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "one")]) == 0
    absolute = tmp_path / "sub" / "absolute.sqlite"
    absolute.parent.mkdir()
    monkeypatch.setenv("LABCAL_DB", f"sqlite:///{absolute}")  # the path's own slash makes the fourth
    assert main(["run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "two")]) == 0
    for db in (tmp_path / "relative.sqlite", absolute):
        with sqlite3.connect(db) as con:
            assert con.execute("SELECT count(*) FROM runs").fetchone()[0] == 1
    capsys.readouterr()


def test_with_a_server_the_station_journals_locally_where_labcal_journal_says(tmp_path, monkeypatch, capsys):
    """Nothing listens at the URL: the run journals in $LABCAL_JOURNAL all the same (it never waits
    for the server), says once that the server is unreachable, and `labcal runs` lists the journal."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    journal = tmp_path / "station" / "journal.sqlite"
    monkeypatch.setenv("LABCAL_DB", f"postgresql://lab@127.0.0.1:{port}/labcal")
    monkeypatch.setenv("LABCAL_JOURNAL", str(journal))
    assert main(["run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "r")]) == 0
    err = capsys.readouterr().err
    assert err.count("unreachable") == 1 and "labcal sync" in err
    with sqlite3.connect(journal) as con:
        assert con.execute("SELECT count(*) FROM points").fetchone()[0] == 64  # four-mount-64
    assert main(["runs", "--json"]) == 0
    assert '"status": "complete"' in capsys.readouterr().out


def test_a_server_url_is_printed_without_its_password(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LABCAL_CONFIG", str(tmp_path / "lab.toml"))
    (tmp_path / "lab.toml").write_text('database = "postgresql://lab:s3cret@db.example:5432/labcal"\n')
    monkeypatch.delenv("LABCAL_DB", raising=False)
    assert main(["config", "path", "--json"]) == 0
    out = capsys.readouterr().out
    assert "postgresql://lab:***@db.example:5432/labcal" in out and "s3cret" not in out

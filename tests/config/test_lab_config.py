"""The lab-wide configuration file: found independently of the current folder, validated, and the
one place the database, the laboratory and the certificate defaults come from."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from labcal.cli import main
from labcal.config.lab import certificate_settings, load_lab_config
from labcal.config.settings import CertificateSettings
from labcal.store.journal import db_path

LAB = """database = "data/lab.sqlite"
[laboratory]
name = "Example Calibration Laboratory"
address = "1 Metrology Way"
accreditation_id = "UKAS 0000"
[certificate]
attitude_u95_max_deg = 0.05
usage_pitch_deg = [-45, 45]
"""


@pytest.fixture
def lab_file(tmp_path, monkeypatch):
    path = tmp_path / "config" / "labcal" / "lab.toml"  # $XDG_CONFIG_HOME (conftest) /labcal/lab.toml
    path.parent.mkdir(parents=True)
    path.write_text(LAB)
    monkeypatch.delenv("LABCAL_DB")
    return path


def test_database_comes_from_the_lab_file_whatever_the_current_folder(lab_file, tmp_path, monkeypatch):
    for folder in (tmp_path, Path("/")):
        monkeypatch.chdir(folder)
        assert db_path(None) == lab_file.parent / "data" / "lab.sqlite"  # relative to the lab file
    monkeypatch.setenv("LABCAL_DB", "/x/env.sqlite")
    assert db_path(None) == Path("/x/env.sqlite")  # the environment over the file
    assert db_path("given.sqlite") == Path("given.sqlite")  # --db over both


def test_labcal_config_names_the_file_and_shows_it(lab_file, capsys):
    assert main(["config", "path"]) == 0
    assert capsys.readouterr().out.strip() == str(lab_file)
    assert main(["config", "show", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["laboratory"]["accreditation_id"] == "UKAS 0000"
    assert doc["certificate"]["laboratory"] == "Example Calibration Laboratory, 1 Metrology Way"
    assert doc["certificate"]["attitude_u95_max_deg"] == 0.05


def test_station_settings_go_over_the_lab_defaults_and_only_where_set(lab_file):
    station = CertificateSettings.model_validate({"bias_max_v": 0.01})
    merged = certificate_settings(station, "station.toml")
    assert merged.bias_max_v == 0.01 and merged.attitude_u95_max_deg == 0.05  # the lab's, not the default
    assert merged.usage_pitch_deg == (-45, 45)


def test_site_wide_file_and_labcal_config(tmp_path, monkeypatch):
    site = tmp_path / "site-config" / "labcal" / "lab.toml"  # $XDG_CONFIG_DIRS (conftest)
    site.parent.mkdir(parents=True)
    site.write_text('[laboratory]\nname = "Site lab"\n')
    assert load_lab_config().path == site
    other = tmp_path / "other.toml"
    other.write_text('[laboratory]\nname = "Other"\n')
    monkeypatch.setenv("LABCAL_CONFIG", str(other))
    assert load_lab_config().laboratory.name == "Other"


@pytest.mark.parametrize("text, message", [
    ("[laboratory]\nnmae = 'x'\n", "laboratory.nmae: unknown key; did you mean name?"),
    ("[certificate]\nattitude_u95_max_deg = -1\n", "certificate.attitude_u95_max_deg"),
    ("database = [", "malformed TOML"),
])
def test_a_wrong_lab_file_is_one_line(tmp_path, monkeypatch, capsys, text, message):
    path = tmp_path / "lab.toml"
    path.write_text(text)
    monkeypatch.setenv("LABCAL_CONFIG", str(path))
    assert main(["config", "show"]) == 2
    err = capsys.readouterr().err
    assert message in err and str(path) in err and len(err.strip().splitlines()) == 1


def test_a_missing_labcal_config_file_is_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LABCAL_CONFIG", str(tmp_path / "nope.toml"))
    assert main(["config", "path"]) == 2
    assert "no such lab configuration file" in capsys.readouterr().err


def test_labcal_config_shows_where_notifications_go_and_no_token(tmp_path, capsys, monkeypatch):
    """The lab file's ``notify`` by scheme only (an apprise URL holds its service's token),
    and $LABCAL_NOTIFY over it, even empty."""
    lab = tmp_path / "lab.toml"
    lab.write_text('notify = ["tgram://123456:SECRET/42", "json://127.0.0.1:8080/hook"]\n')
    monkeypatch.setenv("LABCAL_CONFIG", str(lab))
    assert main(["config", "show", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["notify"], doc["notify_from"]) == (["tgram://…", "json://…"], f"{lab}: notify")
    monkeypatch.setenv("LABCAL_NOTIFY", "mailto://me:SECRET@example.com, ")
    assert main(["config", "show"]) == 0
    shown = capsys.readouterr().out
    assert "notify: mailto://… ($LABCAL_NOTIFY)" in shown and "SECRET" not in shown
    monkeypatch.setenv("LABCAL_NOTIFY", "")
    assert main(["config", "show", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["notify"] == []



def test_the_lab_servers_key_comes_from_the_lab_file_unless_given(lab_file, tmp_path, capsys):
    """`server_key` is relative to the lab file, checked when the server starts (a missing key is one
    line), and --key goes over it."""
    from labcal.app.server_approval import server_key
    from labcal.errors import LabcalError

    assert server_key(None) is None  # the file names none: the server approves nothing
    lab_file.write_text(LAB.replace('database = "data/lab.sqlite"',
                                    'database = "data/lab.sqlite"\nserver_key = "keys/server.key"'))
    with pytest.raises(LabcalError, match="server.key"):
        server_key(None)  # named but not there
    (lab_file.parent / "keys").mkdir()
    assert main(["certificate", "keygen", "--out", str(lab_file.parent / "keys" / "server")]) == 0
    assert main(["certificate", "keygen", "--out", str(tmp_path / "other")]) == 0
    assert server_key(None) == lab_file.parent / "keys" / "server.key"
    assert server_key(str(tmp_path / "other.key")) == tmp_path / "other.key"

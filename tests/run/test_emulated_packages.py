"""A single-axis and an x–y package calibrated on a station's devices (`labcal run --station FILE
--emulate`): the real drivers against the emulators, the DMM scanning one channel per sensor, the
journal holding NULL for the sensors the package lacks, and the run ending in the package's sealed
certificate as a simulated package run does."""

from __future__ import annotations

import json
import sqlite3

import numpy as np
import pytest
from cli import cli
from emulators import TIME_SCALE, no_leaks, private_file  # noqa: F401 - fixture

from labcal.documents.certificate import read_certificate

# (package, the station's [dmm] channels, its [instrument] and [certificate] settings, the columns
# of the outputs it has). The x–y package is used within roll ±45°, inside its usable range (its
# Jacobian is singular at roll ±90°, Tripp & Tcheng eq. 86); a single sensor at the table's roll.
PACKAGES = [
    ("single-axis", "[101]", 'package = "single-axis"\nroll_in_use = "table"\nroll_sd_deg = 0.001', "", (0,)),
    ("two-axis-xy", "[101, 102]", 'package = "two-axis-xy"',
     "usage_pitch_deg = [-45, 45]\nusage_roll_deg = [-45, 45]", (0, 1)),
]


@pytest.mark.slow
@pytest.mark.parametrize(("package", "channels", "instrument", "certificate", "present"), PACKAGES)
def test_a_package_on_a_stations_emulated_devices_ends_in_its_sealed_certificate(
        package, channels, instrument, certificate, present, tmp_path, capsys, no_leaks):  # noqa: F811
    """64 points over 4 mounts through Modbus TCP tables and the 34972A on the LAN (with its
    thermometer): every point journals the package's outputs and NULL for the others; the fit's
    columns are the emulated truth's for the sensors present to 0.1 mV (as for a three-axis
    instrument on these emulators: arcsec misalignments, drift and a temperature swing); the mount
    notes say the wiring was taken as stated; the certificate verifies its seal and states the
    package, its sensors and its roll in use."""
    path = private_file("az-modbus-tcp", tmp_path, f"\n[instrument]\n{instrument}\n"
                        + (f"\n[certificate]\n{certificate}\n" if certificate else ""))
    text = path.read_text(encoding="utf-8")
    assert "channels = [101, 102, 103]" in text
    path.write_text(text.replace("channels = [101, 102, 103]", f"channels = {channels}"), encoding="utf-8")
    run_dir, db = tmp_path / "run", tmp_path / "lab.sqlite"
    code, _, err = cli(capsys, "run", "--station", str(path), "--emulate", "--time-scale", str(TIME_SCALE),
                       "--seed", "7", "--yes", "--out", str(run_dir), "--db", str(db))
    assert code == 0, err
    with sqlite3.connect(db) as journal:
        rows = journal.execute("SELECT vx, vy, vz, sd_vx, sd_vy, sd_vz FROM points").fetchall()
        mounts = [m for (m,) in journal.execute("SELECT message FROM events WHERE kind = 'mount'")]
    assert len(rows) == 64
    for row in rows:
        assert [row[j] is None for j in range(3)] == [j not in present for j in range(3)]
        assert [row[3 + j] is None for j in range(3)] == [j not in present for j in range(3)]
    verified = [m for m in mounts if m.startswith("mount verified")]
    assert len(verified) == 4 and all("wiring taken as stated" in m for m in verified)
    meta = json.loads((run_dir / "run.json").read_text())
    truth = np.array(meta["simulated_truth"]["coefficients"])[:, list(present)]
    fitted = np.array(json.loads((run_dir / "fit.json").read_text())["coefficients"])
    assert fitted.shape == truth.shape and np.max(np.abs(fitted - truth)) < 1e-4
    cert = read_certificate(run_dir / "certificate.json")  # refuses a certificate whose seal fails
    assert cert.package is not None and cert.package.package == package
    assert cert.package.sensors == ["xyz"[j] for j in present]
    assert cert.package.roll_in_use == ("table" if package == "single-axis" else "inferred")


@pytest.mark.slow
def test_a_stopped_single_axis_run_resumes_on_its_one_channel_and_ends_in_its_certificate(
        tmp_path, capsys, no_leaks):  # noqa: F811
    """The example single-axis station, its DMM's port closed for good after 40 scans: the run stops
    (the operator aborts at the pause), and `labcal resume` rebuilds the station from the journal,
    scans the one channel again, keeps every reading taken, and ends in the single-axis certificate
    with the roll in use the station stated."""
    closes = '\n[[emulation.faults]]\ndevice = "dmm"\nkind = "close-port"\nafter = 40\nmatch = "FETC"\n'
    path = private_file("single-axis-tcp", tmp_path, closes, "timeout_s = 0.1\nreconnect_s = 1")
    run_dir, answers = tmp_path / "run", tmp_path / "answers.txt"
    answers.write_text("y\ny\ny\na\n")
    code, _, err = cli(capsys, "run", "--station", str(path), "--emulate", "--time-scale", str(TIME_SCALE),
                       "--seed", "7", "--answers", str(answers), "--out", str(run_dir), "--db",
                       str(tmp_path / "lab.sqlite"))
    assert code == 1 and "continue with: labcal resume" in err, err
    with (run_dir / "readings.csv").open() as f:
        before = [line for line in f if not line.startswith("#")]
    assert 16 < len(before) - 1 < 64
    answers.write_text("y\ny\ny\n")
    code, _, err = cli(capsys, "resume", str(run_dir), "--answers", str(answers), "--db",
                       str(tmp_path / "lab.sqlite"))
    assert code == 0, err
    with (run_dir / "readings.csv").open() as f:
        after = [line for line in f if not line.startswith("#")]
    assert len(after) == 65 and set(before) <= set(after)  # the header and 64 points; none changed
    cert = read_certificate(run_dir / "certificate.json")
    assert cert.package is not None and cert.package.package == "single-axis"
    assert cert.package.sensors == ["x"]
    assert cert.package.roll_in_use == "table" and cert.package.roll_sd_deg == 0.001

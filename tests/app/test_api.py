"""labcal from Python (`labcal.api`): the example in docs/ runs a simulated calibration unattended
and reads its certificate back; what it states is checked against the journal and the certificate
file as sqlite3 and json read them, not through labcal."""

from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from contextlib import closing
from pathlib import Path

import pytest

import labcal.api

EXAMPLE = Path(__file__).resolve().parents[2] / "docs" / "examples" / "calibrate.py"


def test_the_example_in_the_documents_calibrates_and_reads_its_certificate(tmp_path):
    done = subprocess.run([sys.executable, str(EXAMPLE), str(tmp_path / "run")], capture_output=True,
                          text=True, timeout=300, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert len(EXAMPLE.read_text(encoding="utf-8").splitlines()) <= 15
    certificate = json.loads((tmp_path / "run" / "certificate.json").read_text(encoding="utf-8"))
    assert f"certificate {certificate['certificate_id']}:" in done.stdout
    largest = certificate["attitude"]["pitch_U95_max_deg"]
    assert f"largest pitch U95 {largest:.5f}°" in done.stdout
    assert "(unattended: confirmed)" in done.stdout  # the one remount, taken as done
    journal = Path(json.loads((tmp_path / "run" / "run.json").read_text(encoding="utf-8"))["journal"])
    with closing(sqlite3.connect(journal)) as db:
        points = db.execute("SELECT count(*) FROM points WHERE status = 'ok'").fetchone()[0]
    assert points == 16 and f"the run's {points} points are in" in done.stdout


def test_a_refusal_is_a_labcal_error_and_nothing_runs(tmp_path):
    with pytest.raises(labcal.api.LabcalError, match="unknown plan"):
        labcal.api.run(sim=True, plan="no-such-plan", out=str(tmp_path / "run"))
    assert not (tmp_path / "run").exists()


def test_every_public_name_is_there():
    assert all(hasattr(labcal.api, name) for name in labcal.api.__all__)

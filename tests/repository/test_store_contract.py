"""Only the store speaks to a database, and the documents never reach into the run machinery: a copy
of the installed package with a database library imported by a new application module and the
run's events imported by a new document module breaks exactly the two contracts that say so —
imports the contracts before the store and the device interfaces were split out let through."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import labcal
import labcal.drivers
import labcal.sim

PYPROJECT = Path(__file__).resolve().parents[2] / "pyproject.toml"
LINT = str(Path(sys.executable).with_name("lint-imports"))


def installed_copy(site: Path) -> None:
    """The package as a user imports it, drivers and sim inside (an editable install keeps them apart)."""
    ignore = shutil.ignore_patterns("__pycache__")
    shutil.copytree(Path(labcal.__file__).resolve().parent, site / "labcal", ignore=ignore)
    for name, package in (("drivers", labcal.drivers), ("sim", labcal.sim)):
        if not (site / "labcal" / name).is_dir():
            shutil.copytree(Path(package.__file__).parent, site / "labcal" / name, ignore=ignore)


def test_a_database_library_outside_the_store_and_run_events_in_the_documents_break_their_contracts(tmp_path):
    site = tmp_path / "site"
    installed_copy(site)
    (site / "labcal" / "app" / "brand_new.py").write_text("import sqlite3  # noqa\n")
    (site / "labcal" / "documents" / "brand_new.py").write_text("import labcal.run.events  # noqa\n")
    planted = subprocess.run([LINT, "--config", str(PYPROJECT)], cwd=site, capture_output=True, text=True,
                             env={**os.environ, "PYTHONPATH": str(site)}, timeout=240)
    report = " ".join(planted.stdout.split())
    assert planted.returncode != 0
    assert "Only the store speaks to a database" in report and "labcal.store BROKEN" in report
    assert "never import the run machinery BROKEN" in report
    assert report.count("BROKEN") == 2, report[-3000:]

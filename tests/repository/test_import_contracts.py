"""The import contracts say what they mean: a copy of the installed package with three forbidden
imports planted in it — a driver reaching into the lab database, a new command module reaching below
the application layer, a new module importing the simulator — breaks exactly the three contracts
that name those rules, while the package as installed keeps every contract."""

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


def lint(site: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(site)}
    return subprocess.run([LINT, "--config", str(PYPROJECT)], cwd=site, env=env, capture_output=True,
                          text=True, timeout=240)


def test_planted_forbidden_imports_break_the_contracts_that_name_them(tmp_path):
    site = tmp_path / "site"
    installed = Path(labcal.__file__).resolve().parent
    if not (installed / "drivers").is_dir():  # an editable install keeps drivers/ and sim/ outside labcal/
        shutil.copytree(installed, site / "labcal", ignore=shutil.ignore_patterns("__pycache__"))
        for name, package in (("drivers", labcal.drivers), ("sim", labcal.sim)):
            shutil.copytree(Path(package.__file__).parent, site / "labcal" / name,
                            ignore=shutil.ignore_patterns("__pycache__"))
    else:
        shutil.copytree(installed, site / "labcal", ignore=shutil.ignore_patterns("__pycache__"))
    clean = lint(site)
    assert clean.returncode == 0, clean.stdout[-2000:]

    with (site / "labcal" / "drivers" / "visa.py").open("a") as driver:
        driver.write("\nimport labcal.store.labdb  # noqa\n")
    (site / "labcal" / "commands" / "brand_new.py").write_text("import labcal.store.journal  # noqa\n")
    (site / "labcal" / "app" / "brand_new.py").write_text("import labcal.sim.rig  # noqa\n")
    planted = lint(site)
    report = " ".join(planted.stdout.split())
    assert planted.returncode != 0
    assert "Drivers know only the device interfaces (labcal.devices) and errors BROKEN" in report
    assert "call the application layer and nothing below it BROKEN" in report
    assert "import the simulator BROKEN" in report
    assert report.count("BROKEN") == 3, report[-3000:]


def test_every_command_module_is_one_the_independence_contract_names():
    """A new command module stands alone only if the contract lists it: the list is checked against
    the modules in labcal/commands (the shared ones, common and console, are what they may import)."""
    import tomllib

    root = Path(__file__).resolve().parents[2]
    contracts = tomllib.loads((root / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["importlinter"]
    [independence] = [c for c in contracts["contracts"] if c["type"] == "independence"]
    shared = {"__init__", "common", "console"}
    present = {f"labcal.commands.{p.stem}" for p in (root / "labcal" / "commands").glob("*.py")
               if p.stem not in shared}
    assert present == set(independence["modules"])

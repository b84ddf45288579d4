"""The parser is built without the heavy libraries: `labcal --help` and `labcal plan list` pay for
what they use, not for numpy, pydantic, rich or importlib.metadata that other commands need."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from labcal.analysis.models import EXTENSIONS
from labcal.commands import COMMANDS
from labcal.commands.fit import EXTENSION_NAMES

HEAVY = ("numpy", "pydantic", "rich", "importlib.metadata", "scipy", "matplotlib")

PROBE = """
import json, sys
from labcal.cli import main
sys.argv = ["labcal", *ARGS]
try:
    main()
except SystemExit:
    pass
heavy = sorted(m for m in sys.modules if m in HEAVY or m.split(".")[0] in HEAVY)
sys.__stderr__.write(json.dumps(heavy))
"""


def imported_by(*argv: str, among: tuple[str, ...] = HEAVY) -> list[str]:
    code = PROBE.replace("ARGS", repr(list(argv))).replace("HEAVY", repr(among))
    # not measured by coverage.py (CI's `patch = subprocess` starts it in every Python process it
    # sees, and it imports dataclasses, tomllib and inspect itself)
    env = {k: v for k, v in os.environ.items()
           if k not in ("COVERAGE_PROCESS_CONFIG", "COVERAGE_PROCESS_START")}
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                          check=True, env=env)
    return json.loads(proc.stderr.strip().splitlines()[-1])


def test_help_and_plan_list_import_none_of_the_heavy_libraries():
    assert imported_by("--help") == []
    assert imported_by("plan", "list") == []
    assert imported_by("fit", "--help") == []
    # lighter, but a third of --help's own import time when they were on its path
    assert imported_by("--help", among=("logging", "tomllib", "dataclasses", "inspect")) == []
    # the lab database's and the lab server's libraries: none is needed to print the help
    assert imported_by("--help", among=SERVER) == []


SERVER = ("sqlalchemy", "alembic", "apprise", "fastapi", "uvicorn", "starlette", "argon2", "psycopg")

# The commands whose parsers are built from the station model, the plans or the run machinery (their
# options' choices and bounds come from there): their help loads numpy and pydantic, about 0.5 s.
HELP_BUILT_FROM_THE_MODELS = ("run", "resume", "simulate", "attitude", "station", "sim", "sync", "config",
                              "db")


def test_every_other_commands_help_loads_no_scientific_database_or_document_library():
    """`labcal certificate --help` took 1.4 s of CPU (installed from a wheel): the command's module
    imported its use cases, and with them SQLAlchemy, scipy, matplotlib and reportlab, to print a page
    of text. A command module names its use cases with labcal.lazy; its help, and an option refused
    by argparse, load none of them."""
    among = ("numpy", "scipy", "matplotlib", "PIL", "pydantic", "reportlab", "lxml", *SERVER)
    for command in sorted(set(COMMANDS) - set(HELP_BUILT_FROM_THE_MODELS)):
        assert imported_by(command, "--help", among=among) == [], command
    assert set(HELP_BUILT_FROM_THE_MODELS) <= set(COMMANDS)  # the exceptions are commands that exist


def test_the_fit_help_names_every_model_extension():
    assert EXTENSION_NAMES == tuple(EXTENSIONS)


def test_a_dry_run_without_report_draws_nothing(tmp_path):
    """The run's statistics take scipy's distributions and its device fit scipy's Levenberg–Marquardt,
    imported where they are first used; a run that draws no report never loads matplotlib, nor
    scipy.stats (several times scipy.special's import time: the distributions are scipy.special's)."""
    found = imported_by("run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "run"), "--db",
                        str(tmp_path / "lab.sqlite"), among=("scipy", "matplotlib"))
    assert "scipy.special" in found and "scipy.optimize" in found
    assert not [m for m in found if m.startswith(("matplotlib", "scipy.stats"))]


def test_a_dry_run_loads_no_driver_server_or_document_library(tmp_path):
    """A simulated run on a SQLite lab database (a new file: created without replaying the migrations)
    needs no instrument driver, nothing of the lab server, and with --no-report no document."""
    among = (*SERVER, "pymodbus", "pyvisa", "serial", "reportlab", "lxml", "labcal.drivers.oriental_az",
             "labcal.drivers.modbus", "labcal.documents.certificate", "labcal.documents.history")
    found = imported_by("run", "--sim", "--yes", "--no-report", "--out", str(tmp_path / "run"), "--db",
                        str(tmp_path / "lab.sqlite"), among=among)
    assert found == []


def test_listing_and_reading_the_lab_loads_no_plotting_pdf_or_statistics_library(tmp_path):
    """`labcal runs` cost 1.4 s of CPU to list one run, `labcal certificate approvers list` as much
    (installed from a wheel; 0.6 s each now): their use cases' modules imported matplotlib (the
    desk's residual plot, the history's plot), reportlab (the report) and scipy (the device fit, the
    statistics) at the top. Each is now named with labcal.lazy and loaded where a plot is drawn, a
    report typeset or a statistic computed."""
    db = str(tmp_path / "lab.sqlite")
    run = ["run", "--sim", "--yes", "--no-report", "--plan", "one-mount-16", "--db", db,
           "--out", str(tmp_path / "run")]
    done = subprocess.run([sys.executable, "-m", "labcal.cli", *run], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    among = ("matplotlib", "reportlab", "scipy", "PIL")
    for argv in (("runs",), ("runs", "--json"), ("log", "1"), ("certificate", "approvers", "list")):
        assert imported_by(*argv, "--db", db, among=among) == [], argv

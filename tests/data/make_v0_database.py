"""Make tests/data/v0/: a lab database written by the labcal before the versioned schema.

Not run by the tests (the old labcal is not on CI machines); run by hand, once, with the previous
release installed in its own venv:

    git worktree add /tmp/base a8863ee        # "labcal start-up no longer imports the run machinery"
    python3 -m venv /tmp/base/.venv && /tmp/base/.venv/bin/pip install -e /tmp/base
    python3 tests/data/make_v0_database.py /tmp/base/.venv/bin/labcal

It makes, in one database (user_version 0, the tables exactly as that labcal created them):

- ``complete``: ``labcal run --sim --yes --seed 3 --plan one-mount-16`` — a finished dry run whose
  certificate the run's automatic report stored in the ``certificates`` table (serial SIMULATED);
- ``stopped``: ``labcal run --sim --seed 3 --no-report --answers ANSWERS`` on four-mount-64 with the
  answers ``y`` (mount 1) then ``q`` (the operator stops at the remount to mount 2): 16 readings
  committed, status ``stopped``, which ``labcal resume`` finishes.

and copies each run directory's run.json and plan.toml. The database is checkpointed
(``PRAGMA wal_checkpoint(TRUNCATE)``) so the one file holds everything; it stays in WAL mode,
as every lab database is.
The run.json files name the journal where it was made; tests rewrite that path to their copy.
"""

from __future__ import annotations

import os
import shutil
import sqlite3
import subprocess
import sys
import tempfile
from pathlib import Path

OUT = Path(__file__).resolve().parent / "v0"


def main(labcal: str) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        db = work / "labcal.sqlite"
        env = {**os.environ, "LABCAL_DB": str(db)}
        subprocess.run([labcal, "--version"], check=True)
        subprocess.run([labcal, "run", "--sim", "--yes", "--seed", "3", "--plan", "one-mount-16",
                        "--out", str(work / "complete")], env=env, check=True, cwd=work)
        answers = work / "answers.txt"
        answers.write_text("y\nq\n")
        stopped = subprocess.run([labcal, "run", "--sim", "--seed", "3", "--no-report",
                                  "--answers", str(answers), "--out", str(work / "stopped")],
                                 env=env, cwd=work)
        assert stopped.returncode == 1, "the operator's q at the second mount stops the run"
        with sqlite3.connect(db) as con:
            con.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            assert con.execute("PRAGMA user_version").fetchone()[0] == 0
        if OUT.exists():
            shutil.rmtree(OUT)
        OUT.mkdir()
        shutil.copy(db, OUT / "labcal.sqlite")
        for run in ("complete", "stopped"):
            (OUT / run).mkdir()
            for name in ("run.json", "plan.toml"):
                shutil.copy(work / run / name, OUT / run / name)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "/tmp/base/.venv/bin/labcal")

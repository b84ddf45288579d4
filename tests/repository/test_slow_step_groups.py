"""CI's slow step runs `pytest -m slow --dist loadgroup` so that a module marked `xdist_group` builds its
costly fixture on one worker only. pytest-xdist does the grouping by renaming node ids, and on pytest 9.2
that renaming silently stops working (pytest-xdist#1386): the tests spread over every worker again and
each worker builds the fixture. This checks the installed pair still groups."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

GROUPED = '''
import os, pytest
pytestmark = pytest.mark.xdist_group("costly")

@pytest.mark.parametrize("i", range(6))
def test_grouped(i):
    with open(os.environ["WORKERS_SEEN"], "a") as seen:
        seen.write(os.environ["PYTEST_XDIST_WORKER"] + "\\n")
'''


def test_tests_of_one_xdist_group_run_on_one_worker(tmp_path: Path):
    (tmp_path / "pyproject.toml").write_text("[tool.pytest.ini_options]\n")  # not labcal's own options
    (tmp_path / "test_grouped.py").write_text(GROUPED)
    seen = tmp_path / "workers.txt"
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "-p", "no:cacheprovider",
               "-n", "3", "--dist", "loadgroup", str(tmp_path / "test_grouped.py")]
    done = subprocess.run(command, cwd=tmp_path, env={"WORKERS_SEEN": str(seen), "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    workers = seen.read_text().split()
    assert len(workers) == 6 and len(set(workers)) == 1, workers

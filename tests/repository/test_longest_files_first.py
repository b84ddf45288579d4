"""The suite hands its longest files out first: a one-test file marked `long(seconds=N)` runs before
files with more tests, where pytest-xdist's own order (most tests first) put it last to run alone
while the other workers idled. Checked on a worker running three files with the suite's own
tests/conftest.py and the order options of its pyproject.toml."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
RECORD = '''
import os, pytest

def record(name):
    with open(os.environ["ORDER_SEEN"], "a") as seen:
        seen.write(name + "\\n")
'''


def test_a_marked_long_file_runs_before_files_with_more_tests(tmp_path: Path):
    options = tomllib.loads((TESTS.parent / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"]
    addopts = options["addopts"].split()
    assert "--no-loadscope-reorder" in addopts, "pytest-xdist would order the files by their number of tests"
    order = ["--dist", "loadfile", "--no-loadscope-reorder"]
    assert "loadfile" in addopts
    markers = "".join(f"    {m!r},\n" for m in options["markers"])
    (tmp_path / "pyproject.toml").write_text(  # the suite's helper modules, which its conftest imports
        f"[tool.pytest.ini_options]\npythonpath = [{str(TESTS)!r}]\nmarkers = [\n{markers}]\n")
    shutil.copy(TESTS / "conftest.py", tmp_path / "conftest.py")
    (tmp_path / "test_many.py").write_text(RECORD + "".join(
        f"\ndef test_many_{i}():\n    record('many')\n" for i in range(5)))
    (tmp_path / "test_some.py").write_text(RECORD + "".join(
        f"\ndef test_some_{i}():\n    record('some')\n" for i in range(3)))
    (tmp_path / "test_long.py").write_text(RECORD + "\npytestmark = pytest.mark.long(seconds=40)\n\n"
                                           "def test_long():\n    record('long')\n")
    seen = tmp_path / "order.txt"
    command = [sys.executable, "-m", "pytest", "-q", "-p", "no:randomly", "-p", "no:cacheprovider",
               "-n", "1", *order, str(tmp_path)]
    done = subprocess.run(command, cwd=tmp_path, env={"ORDER_SEEN": str(seen), "PATH": "/usr/bin:/bin"},
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    ran = seen.read_text().split()
    assert ran == ["long"] + ["many"] * 5 + ["some"] * 3, ran

"""The README's two commands in a fresh clone at a long path, as a new lab member runs them.

A long path is where a fresh machine differs from a developer's: a venv's console scripts then have
a shebang longer than the kernel's 127-byte limit (pip has to work around it), and any message that
quotes a path is longer than a terminal line. The commands are taken from the README itself, so
the test follows the README when it changes.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def readme_command(heading: str) -> str:
    """The first ```sh block under the README's heading."""
    text = (REPO / "README.md").read_text()
    section = text[text.index(f"## {heading}"):]
    return re.search(r"```sh\n(.+?)\n```", section, re.S).group(1).strip()


@pytest.mark.slow(seconds=180)
@pytest.mark.timeout(1200)
def test_the_readme_commands_in_a_fresh_clone_at_a_long_path(tmp_path):
    if not (REPO / ".git").exists() or shutil.which("git") is None:
        pytest.skip("not a git checkout: nothing to clone")
    clone = tmp_path.joinpath(*["a-lab-member-s-rather-long-folder-name-for-labcal"] * 4, "labcal")
    assert len(str(clone / ".venv" / "bin" / "python3")) > 127  # past the kernel's shebang limit
    subprocess.run(["git", "clone", "--quiet", str(REPO), str(clone)], check=True)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PYTEST_", "COV_", "VIRTUAL_ENV")) and k != "PYTHONPATH"}
    env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if ".venv" not in p)

    first = readme_command("Set up and run a simulated calibration")
    assert first.startswith("python3 -m venv .venv") and "labcal run --sim --yes" in first
    done = subprocess.run(["bash", "-c", first], cwd=clone, env=env, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Traceback" not in done.stderr
    run_dirs = list((clone / "runs").glob("*-four-mount-64"))
    assert len(run_dirs) == 1
    for name in ("readings.csv", "fit.json", "certificate.json", "report.html", "report.pdf"):
        assert (run_dirs[0] / name).stat().st_size > 0, name

    second = readme_command("Run the tests")
    assert second.startswith("python3 -m venv .venv") and second.endswith("pytest -q")
    # The whole suite is what CI's first step runs; here, from the clone at its long path, a few
    # of its files prove the install and the runner work there (PYTEST_ADDOPTS narrows the run).
    env["PYTEST_ADDOPTS"] = "tests/commands/test_command_line.py tests/analysis/test_soto_tables.py"
    tested = subprocess.run(["bash", "-c", second], cwd=clone, env=env, capture_output=True, text=True)
    assert tested.returncode == 0, tested.stdout[-3000:] + tested.stderr[-3000:]
    assert re.search(r"\d+ passed", tested.stdout) and " failed" not in tested.stdout

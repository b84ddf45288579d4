"""Screenshots of the approver's desk and the instrument register: docs/screenshots/queue.png,
run-results.png, run-approved.png, instruments.png, instrument.png and due.png.

    .venv/bin/python tools/desk_screenshots.py [--out docs/screenshots]

The pages are the ones `tests/server/test_lab_desk_pages.py` builds and checks in Chromium (a real lab
database, a calibration through the real drivers, a four-mount dry run on the device model, a
register of 20 instruments, `labcal serve`): that test saves each page it has checked where
$LABCAL_SCREENSHOTS points, so a screenshot is always of a page that passed. Needs the test extra
(`pip install -e '.[test]'`) and `apt-get install chromium`.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "docs" / "screenshots"))
    args = parser.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    test = ROOT / "tests" / "server" / "test_lab_desk_pages.py"
    command = [sys.executable, "-m", "pytest", "-q", "-m", "slow", "-n", "0", "-p", "no:randomly", str(test)]
    done = subprocess.run(command, cwd=ROOT, env={**os.environ, "LABCAL_SCREENSHOTS": str(out)}, check=False)
    return done.returncode


if __name__ == "__main__":
    raise SystemExit(main())

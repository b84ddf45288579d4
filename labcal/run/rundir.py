"""A run's directory: what people and other programs read of a run.

plan.toml (the plan that ran), run.json (which journal and run, and how the run ended), and the
exports readings.csv and fit.json. The journal stays the source of truth; results (certificate,
report, history) find a finished run through this module without importing the sequencer.
"""

from __future__ import annotations

import json
from datetime import UTC, datetime
from pathlib import Path

from labcal.analysis.plan import Plan
from labcal.errors import LabcalError
from labcal.run.journal import Journal

READINGS = "readings.csv"
FIT = "fit.json"
PLAN = "plan.toml"
RUN = "run.json"


def new_run_dir(out: str | None, plan: Plan) -> Path:
    if out is None:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        path = Path("runs") / f"{stamp}-{plan.name}"
    else:
        path = Path(out)
    if path.exists() and not path.is_dir():
        raise LabcalError(f"{path}: exists and is not a directory; --out names a new or empty run directory")
    if path.exists() and any(path.iterdir()):
        raise LabcalError(f"{path}: run directory exists and is not empty; choose another --out")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabcalError(f"{path}: cannot create run directory ({exc.strerror})") from None
    return path


def read_run_json(run_dir: Path) -> dict:
    try:
        return json.loads((run_dir / RUN).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise LabcalError(f"{run_dir}: not a run directory (no {RUN})") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise LabcalError(f"{run_dir / RUN}: unreadable ({exc})") from None


def points_on_disk(run_dir: Path) -> int:
    """Readings safe in the run's journal (0 when there is no journal yet)."""
    try:
        info = read_run_json(run_dir)
        with Journal(info["journal"]) as journal:
            return len(journal.points(info["run_id"], status="ok"))
    except (LabcalError, KeyError):
        return 0

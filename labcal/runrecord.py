"""What a finished calibration run holds, read from its one source of truth.

`load_run` is the single seam between the run's storage and everything that issues results
(certificate, report, history): today it reads the run directory (readings.csv, plan.toml,
run.json); when the run journal moves to SQLite only this function changes.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from labcal.errors import LabcalError
from labcal.files import read_text
from labcal.plan import Plan, parse_plan
from labcal.readings import Readings, read_readings
from labcal.run import PLAN, READINGS, RUN


@dataclass(frozen=True)
class RunRecord:
    """A completed run: its readings, the plan it followed and what it recorded about itself."""

    directory: Path
    readings: Readings
    readings_sha256: str  # of the stored readings, so a certificate names the exact data it rests on
    plan: Plan
    plan_text: str
    meta: dict  # run.json: station, settings, dates, status, identities, simulated truth

    @property
    def simulated(self) -> bool:
        return "simulated_truth" in self.meta


def load_run(run_dir: str | Path) -> RunRecord:
    """Read a run directory; a missing, unfinished or malformed run is one LabcalError line."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise LabcalError(f"{run_dir}: no such run directory")
    meta_path = run_dir / RUN
    try:
        meta = json.loads(read_text(meta_path, "run record"))
    except json.JSONDecodeError as exc:
        raise LabcalError(f"{meta_path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(meta, dict):
        raise LabcalError(f"{meta_path}: not a labcal run record (expected a JSON object)")
    status = meta.get("status")
    if status != "complete":
        why = f" ({meta['reason']})" if meta.get("reason") else ""
        raise LabcalError(f"{run_dir}: the run is {status or 'of unknown status'}{why}; "
                          "only a complete run gets a certificate")
    readings_path = run_dir / READINGS
    readings = read_readings(readings_path)
    digest = hashlib.sha256(readings_path.read_bytes()).hexdigest()
    plan_text = read_text(run_dir / PLAN, "plan")
    plan = parse_plan(plan_text, str(run_dir / PLAN))
    return RunRecord(run_dir, readings, digest, plan, plan_text, meta)

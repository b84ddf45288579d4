"""A calibration run: its directory, the plan it used, the sequencer, and the fit at the end."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from labcal import __version__
from labcal.errors import LabcalError
from labcal.fit import Fit, fit_linear
from labcal.operator import Operator
from labcal.plan import Plan
from labcal.readings import ReadingsWriter, read_readings
from labcal.sequencer import Display, RunOutcome, SequencerSettings, run_plan
from labcal.station import Station

READINGS = "readings.csv"
FIT = "fit.json"
PLAN = "plan.toml"
RUN = "run.json"


def json_safe(value):
    """Replace NaN and infinities (no JSON for them) by null."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def write_json(path: Path, doc: dict) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(json_safe(doc), indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)  # atomic: a reader never sees half a file


def points_on_disk(run_dir: Path) -> int:
    """Readings already safe in a run directory (rows after the header)."""
    try:
        with (run_dir / READINGS).open(encoding="utf-8") as f:
            return max(0, sum(1 for line in f if line.strip()) - 1)
    except FileNotFoundError:
        return 0


def new_run_dir(out: str | None, plan: Plan) -> Path:
    if out is None:
        stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
        path = Path("runs") / f"{stamp}-{plan.name}"
    else:
        path = Path(out)
    if path.exists() and any(path.iterdir()):
        raise LabcalError(f"{path}: run directory exists and is not empty; choose another --out")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise LabcalError(f"{path}: cannot create run directory ({exc.strerror})") from None
    return path


@dataclass
class RunResult:
    directory: Path
    outcome: RunOutcome
    fit: Fit
    wall_s: float


def calibrate(
    plan: Plan, plan_text: str, station: Station, operator: Operator, settings: SequencerSettings,
    run_dir: Path, display: Display | None = None, metadata: dict | None = None,
) -> RunResult:
    """Run the plan into ``run_dir`` and fit the readings. On interruption the directory keeps
    every reading taken and run.json says how the run ended."""
    (run_dir / PLAN).write_text(plan_text, encoding="utf-8")
    meta = {
        "labcal_version": __version__, "plan": plan.name, "station": station.description,
        "started_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        "settings": settings.model_dump(), "status": "running", **(metadata or {}),
    }
    write_json(run_dir / RUN, meta)
    wall0 = time.perf_counter()
    with ReadingsWriter(run_dir / READINGS, temperature=station.dmm.measures_temperature) as writer:
        try:
            outcome = run_plan(plan, station, operator, writer, settings, display)
        except BaseException as exc:
            meta.update(status="interrupted", reason=str(exc) or type(exc).__name__,
                        points_recorded=writer.count)
            write_json(run_dir / RUN, meta)
            raise
    fit = fit_linear(read_readings(run_dir / READINGS))
    write_json(run_dir / FIT, fit.to_json())
    wall = time.perf_counter() - wall0
    meta.update(status="complete", points_recorded=outcome.points_recorded,
                station_time_s=outcome.station_time_s, wall_time_s=wall)
    write_json(run_dir / RUN, meta)
    return RunResult(run_dir, outcome, fit, wall)

"""A calibration run: its journal entry, its exports, and resuming it.

The journal (SQLite) is the source of truth; the run directory (`labcal.run.rundir`) holds what
people and other programs read, rewritten whenever the run stops for any reason.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

from labcal import __version__
from labcal.analysis.fit import Fit, fit_readings
from labcal.analysis.plan import Plan
from labcal.config.files import validate_model, write_json
from labcal.config.plans import parse_plan
from labcal.config.readings_csv import ReadingsWriter
from labcal.config.settings import SequencerSettings
from labcal.errors import LabcalError
from labcal.run.interrupts import Interrupts
from labcal.run.journal import Journal, Manifest, sha256
from labcal.run.operator import Operator
from labcal.run.rundir import FIT, PLAN, READINGS, RUN, read_run_json
from labcal.run.sequencer import Display, RunOutcome, Sequencer, Step, schedule
from labcal.run.station import Station

MIN_POINTS_FOR_MOUNT_CHECK_FIT = 8


def export(journal: Journal, run_id: int, run_dir: Path) -> Fit | None:
    """Rewrite readings.csv (and fit.json when the points determine a fit) from the journal."""
    points = journal.points(run_id, status="ok")
    with ReadingsWriter(run_dir / READINGS, temperature=bool(points) and all(p.temp_c is not None
                                                                               for p in points)) as w:
        for p in points:
            w.append(replicate=p.replicate, y_deg=p.y_deg, u_deg=p.u_deg, pitch_deg=p.pitch_deg,
                     roll_deg=p.roll_deg, volts=[p.vx, p.vy, p.vz], temp_c=p.temp_c,
                     sd=[p.sd_vx, p.sd_vy, p.sd_vz], n_samples=p.n_samples, time_s=p.t_end)
    try:
        fit = fit_readings(journal.readings(run_id))
    except LabcalError:
        return None  # too few points so far for a fit
    write_json(run_dir / FIT, fit.to_json())
    return fit


@dataclass
class RunResult:
    directory: Path
    run_id: int
    outcome: RunOutcome
    fit: Fit
    wall_s: float


def _provisional_fit(journal: Journal, run_id: int):
    """X from the points so far, for checking the next mount; None when there are too few."""
    def fit():
        if len(journal.points(run_id, status="ok")) < MIN_POINTS_FOR_MOUNT_CHECK_FIT:
            return None
        try:
            return fit_readings(journal.readings(run_id)).coefficients
        except LabcalError:
            return None
    return fit


def execute(journal: Journal, run_id: int, run_dir: Path, plan: Plan, station: Station, operator: Operator,
            settings: SequencerSettings, display: Display | None = None,
            steps: list[Step] | None = None) -> RunResult:
    """Run (or go on with) every step not yet in the journal; whatever happens, the journal says
    how the run ended and the exports are rewritten. ``steps``: the schedule, if already made."""
    display = display or Display()
    wall0 = time.perf_counter()
    steps = schedule(plan, settings) if steps is None else steps
    committed = {p.seq for p in journal.points(run_id)}
    status = "interrupted"
    reason: str | None = "Ctrl-C"
    try:
        with Interrupts(lambda: display.message("[yellow]Ctrl-C: pausing after this point "
                                                "(press again to stop the tables now)[/]")) as interrupts:
            station.guard_exchanges(interrupts.critical)  # no device exchange is cut in half
            try:
                sequencer = Sequencer(plan, station, operator, journal, run_id, settings, display, interrupts)
                outcome = sequencer.run(steps, committed, _provisional_fit(journal, run_id))
            finally:
                station.guard_exchanges(None)
        status, reason = "complete", None
    except KeyboardInterrupt:
        raise
    except BaseException as exc:
        status, reason = "stopped", str(exc) or type(exc).__name__
        raise
    finally:
        journal.finish(run_id, status, reason)
        fit = export(journal, run_id, run_dir)
        info = read_run_json(run_dir)
        info.update(status=status, reason=reason, points_recorded=len(journal.points(run_id, status="ok")))
        write_json(run_dir / RUN, info)
    if fit is None:
        reason = "finished without enough good points to fit"
        journal.finish(run_id, "failed", reason)
        write_json(run_dir / RUN, {**info, "status": "failed", "reason": reason})
        raise LabcalError(f"run {run_id} {reason}")
    info.update(station_time_s=outcome.station_time_s, wall_time_s=time.perf_counter() - wall0)
    write_json(run_dir / RUN, info)
    return RunResult(run_dir, run_id, outcome, fit, time.perf_counter() - wall0)


def calibrate(plan: Plan, plan_text: str, station: Station, station_text: str, operator: Operator,
              settings: SequencerSettings, run_dir: Path, journal: Journal, display: Display | None = None,
              metadata: dict | None = None, serial: str | None = None,
              operator_name: str | None = None, steps: list[Step] | None = None) -> RunResult:
    """Start a new run: manifest first, then every point."""
    (run_dir / PLAN).write_text(plan_text, encoding="utf-8")
    run_id = journal.start_run(Manifest(
        run_dir=str(run_dir), plan_name=plan.name, plan_text=plan_text, station_text=station_text,
        software_version=__version__, settings=settings.model_dump(), metadata=metadata or {},
        instrument_serial=serial, operator=operator_name))
    write_json(run_dir / RUN, {
        "labcal_version": __version__, "journal": str(journal.path.resolve()), "run_id": run_id,
        "plan": plan.name, "plan_sha256": sha256(plan_text), "station": station.description,
        "instrument_serial": serial, "operator": operator_name,
        "started_utc": datetime.now(UTC).isoformat(timespec="seconds"), "status": "running",
        "settings": settings.model_dump(), **(metadata or {}),
    })
    return execute(journal, run_id, run_dir, plan, station, operator, settings, display, steps)


@dataclass(frozen=True)
class ResumeContext:
    journal: Journal
    run_id: int
    plan: Plan
    settings: SequencerSettings
    station_text: str
    metadata: dict
    software_version: str  # the labcal that started the run


def open_for_resume(run_dir: Path) -> ResumeContext:
    """The journal entry of an unfinished run, its plan checked against the hash in the manifest."""
    info = read_run_json(run_dir)
    journal = Journal(info["journal"])
    row = journal.run(info["run_id"])
    if row.status == "complete":
        raise LabcalError(f"{run_dir}: run {row.id} is already complete; nothing to resume")
    if sha256(row.plan_text) != row.plan_hash:
        raise LabcalError(f"{run_dir}: the journal's plan does not match its recorded hash; not resuming")
    plan = parse_plan(row.plan_text, f"run {row.id} plan")
    settings = validate_model(row.settings, SequencerSettings, f"{run_dir}: run {row.id}'s settings")
    return ResumeContext(journal, row.id, plan, settings, row.station_text, row.metadata,
                         row.software_version)

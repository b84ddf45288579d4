"""A calibration run: its journal entry, its exports, and resuming it.

The journal (SQLite) is the source of truth; the run directory (`labcal.store.rundir`) holds what
people and other programs read, rewritten whenever the run stops for any reason.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass
from pathlib import Path

from labcal import __version__
from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.fit import Fit, fit_readings
from labcal.analysis.plan import Plan
from labcal.config.files import validate_model
from labcal.config.plans import parse_plan
from labcal.config.run_metadata import RunMetadata, parse_run_metadata
from labcal.config.settings import SequencerSettings
from labcal.devices.station import Station
from labcal.errors import LabcalError
from labcal.run.devicelog import journaled_warnings
from labcal.run.events import EventBus, Note
from labcal.run.interrupts import Interrupts
from labcal.run.journaling import subscribe_journal
from labcal.run.operator import Operator, Terminal
from labcal.run.sequencer import Forecast, ReadingsRefused, RunOutcome, Sequencer, Step, schedule
from labcal.store import exports
from labcal.store.journal import Journal, Manifest, sha256
from labcal.store.lock import RunLock
from labcal.store.rundir import make_run_dir, open_run

MIN_POINTS_FOR_MOUNT_CHECK_FIT = 8
log = logging.getLogger(__name__)


def publish(journal: Journal, run_id: int, run_dir: Path, status: str, reason: str | None
            ) -> exports.Derived:
    """The run's exports from the journal, written whole, then its status with their hashes in one
    transaction: "complete" is journaled only once the files that show it are in place. A run that
    ends without enough good points for a fit is "failed"; a folder that cannot be written (deleted,
    disk full) leaves the run "stopped", every reading kept, and says how to recreate it."""
    row = journal.run(run_id)
    derived = exports.derive(journal, row, status, reason)
    if status == "complete" and derived.fit is None:
        status, reason = "failed", "finished without enough good points to fit"
        derived = exports.derive(journal, row, status, reason)
    try:
        hashes = exports.write(run_dir, derived)
    except LabcalError as exc:
        why = f"exports not written: {exc}"
        if status == "complete":
            status, reason = "stopped", why
        journal.finish(run_id, status, reason)
        raise LabcalError(f"{exc}; run {run_id} is safe in {journal.path}: `labcal export {run_id} --db "
                          f"{journal.path} --out DIR` recreates its folder, `labcal resume DIR` completes "
                          "it") from None
    journal.finish(run_id, status, reason, hashes)
    if status == "failed":
        raise LabcalError(f"run {run_id} {reason}")
    return derived


@dataclass
class RunResult:
    directory: Path
    run_id: int
    outcome: RunOutcome
    fit: Fit
    wall_s: float
    device: DeviceFit | None = None  # the device model, where the plan identifies it
    model_note: str = ""  # which model fit.json holds, and why


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
            settings: SequencerSettings, events: EventBus | None = None,
            steps: list[Step] | None = None, *, terminal: Terminal | None = None,
            forecast: Forecast | None = None) -> RunResult:
    """Run (or go on with) every step not yet in the journal, holding the run's lock; whatever
    happens, the exports are rewritten and the journal says how the run ended.

    The run's events go to ``events``' subscribers (the console, a lab database sync, a notifier),
    the journal subscribed first and durably here (`labcal.run.journaling`): it has each event
    before anyone else hears of it. ``terminal``: what prompts borrow the terminal from;
    ``forecast``: the plan's estimates (`labcal.run.estimate.Estimate.forecast`), for the statuses'
    next remount and ETA (None without one).

    Rig time runs on from where the run was last heard of (`Journal.rig_time`): each segment's
    offset is journaled, time_s never goes back, and the station's clock must start there too (a
    simulated rig's virtual clock does: `labcal.bench.setup`). ``steps``: the schedule, if already made."""
    bus = events if events is not None else EventBus()
    terminal = terminal or Terminal()
    wall0 = time.perf_counter()
    journaling = subscribe_journal(bus, journal)
    try:
        lock = RunLock(journal.path, run_id).acquire()  # released in the finally below, or with the process
        steps = schedule(plan, settings) if steps is None else steps  # made once by the caller, if it did
        committed = {p.seq for p in journal.points(run_id)}
        offset = journal.rig_time(run_id)
        sequencer: Sequencer | None = None
        ended: BaseException | None = None  # the news that ended the run, if it did not complete
        status = "interrupted"
        reason: str | None = "Ctrl-C"
        try:
            bus.publish(Note(run_id=run_id, rig_time_s=offset, name="segment",
                             message=f"measuring from rig time {offset:.3f} s", data={"offset_s": offset}))
            with Interrupts(lambda: terminal.notice("[yellow]Ctrl-C: pausing after this point "
                                                    "(press again to stop the tables now)[/]")) as interrupts:
                station.guard_exchanges(interrupts.critical)  # no device exchange is cut in half
                try:
                    sequencer = Sequencer(plan, station, operator, journal, run_id, settings, events=bus,
                                          terminal=terminal, interrupts=interrupts, offset_s=offset,
                                          forecast=forecast)
                    with journaled_warnings(sequencer.note):  # retries and reconnects are events of the run
                        outcome = sequencer.run(steps, committed, _provisional_fit(journal, run_id))
                finally:
                    station.guard_exchanges(None)
            status, reason = "complete", None
        except KeyboardInterrupt as exc:
            reason, ended = getattr(exc, "reason", reason), exc  # a StopSignal names what stopped the run
            raise
        except ReadingsRefused as exc:  # every point measured, and the readings fail their checks
            status, reason, ended = "failed", str(exc), exc
            raise
        except BaseException as exc:
            status, reason, ended = "stopped", str(exc) or type(exc).__name__, exc
            raise
        finally:
            try:
                derived = publish(journal, run_id, run_dir, status, reason)
            except BaseException as exc:
                ended = ended or exc
                raise
            finally:
                try:
                    if sequencer is not None:
                        _say_how_it_ended(sequencer, journal, run_id, ended)
                finally:
                    lock.release()
    finally:
        bus.unsubscribe(journaling)
    assert derived.fit is not None  # publish raises for a run that cannot be fitted
    return RunResult(run_dir, run_id, outcome, derived.fit, time.perf_counter() - wall0, derived.device,
                     derived.model_note)


def _say_how_it_ended(sequencer: Sequencer, journal: Journal, run_id: int,
                      ended: BaseException | None) -> None:
    """The final Status, as the journal has just recorded it (a run that could not be fitted is
    "failed", one whose folder could not be written "stopped"), at the rig time the exports state
    (the journal's last): journaling it must not make run.json out of date. If it cannot be
    journaled while other news is ending the run, that news is what the caller hears; the failure
    is logged."""
    try:
        row = journal.run(run_id)
        sequencer.status("end", row.status, row.reason, journal.rig_time(run_id))
    except Exception as exc:
        if ended is None:
            raise
        log.warning("run %d's final status was not published: %s", run_id, exc)


def calibrate(plan: Plan, plan_text: str, station: Station, station_text: str, operator: Operator,
              settings: SequencerSettings, run_dir: Path, journal: Journal, events: EventBus | None = None,
              metadata: RunMetadata | None = None, serial: str | None = None,
              operator_name: str | None = None, steps: list[Step] | None = None, *,
              terminal: Terminal | None = None, forecast: Forecast | None = None) -> RunResult:
    """Start a new run: manifest first (its folder's files derived from it), then every point."""
    recorded = (metadata or RunMetadata()).with_station(station.description).journaled()
    run_id = journal.start_run(Manifest(
        run_dir=os.path.abspath(run_dir), plan_name=plan.name, plan_text=plan_text, station_text=station_text,
        software_version=__version__, settings=settings.model_dump(), metadata=recorded,
        instrument_serial=serial, operator=operator_name))
    row = journal.run(run_id)
    try:
        make_run_dir(run_dir)
        journal.exported(run_id, exports.write(run_dir, exports.derive(journal, row)))
    except LabcalError:
        journal.finish(run_id, "failed", "its run folder could not be written")
        raise
    return execute(journal, run_id, run_dir, plan, station, operator, settings, events, steps,
                   terminal=terminal, forecast=forecast)


@dataclass(frozen=True)
class ResumeContext:
    journal: Journal
    run_id: int
    plan: Plan
    settings: SequencerSettings
    station_text: str
    metadata: RunMetadata
    software_version: str  # the labcal that started the run
    lock: RunLock  # held from before anything changes until the command ends
    status: str  # as found: "complete" (only the exports were checked), "running" (interrupted), …
    notes: tuple[str, ...]  # what the folder's check found and repaired

    @property
    def complete(self) -> bool:
        return self.status == "complete"


def open_for_resume(run_dir: Path) -> ResumeContext:
    """The journal entry of a run, its folder checked against it (identity, then every export
    rewritten that is missing, stale or edited), its plan against the hash in the manifest, and its
    lock taken: a run another process is measuring is refused, with who, before anything changes.

    A run the journal calls "running" whose lock nobody held was interrupted (its process was
    killed); a complete run is only checked and repaired."""
    _, journal, row = open_run(run_dir)
    try:
        lock = RunLock(journal.path, row.id, "resuming").acquire()
        try:
            return _resume_context(run_dir, journal, row, lock)
        except BaseException:
            lock.release()
            raise
    except BaseException:
        journal.close()
        raise


def _resume_context(run_dir: Path, journal: Journal, row, lock: RunLock) -> ResumeContext:
    if sha256(row.plan_text) != row.plan_hash:
        raise LabcalError(f"{run_dir}: the journal's plan does not match its recorded hash; not resuming")
    notes, _ = exports.sync(journal, row, run_dir)
    if row.status == "running":
        notes.insert(0, f"run {row.id} was interrupted: the journal says running but no process holds it "
                        "(killed or powered off)")
        journal.event(row.id, "interrupted", "found running with nobody holding its lock")
    plan = parse_plan(row.plan_text, f"run {row.id} plan")
    settings = validate_model(row.settings, SequencerSettings, f"{run_dir}: run {row.id}'s settings")
    return ResumeContext(journal, row.id, plan, settings, row.station_text,
                         parse_run_metadata(row.metadata, f"{run_dir}: run {row.id}'s metadata"),
                         row.software_version, lock, row.status, tuple(notes))

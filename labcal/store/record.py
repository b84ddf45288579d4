"""What a finished calibration run holds, read from its one source of truth: the journal.

`load_run` is the single seam between the run's storage and everything that issues results
(certificate, report, history); it only reads. The run directory's run.json says which journal and which run;
the readings, the plan, the identities and the dates come from the journal itself.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, replace
from pathlib import Path

from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.fit import Fit
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.config.plans import parse_plan
from labcal.config.run_metadata import RunMetadata, parse_run_metadata
from labcal.config.snapshot import StationSnapshot, is_simulated, output_units, parse_snapshot
from labcal.errors import LabcalError
from labcal.store import exports
from labcal.store.chain import ChainCheck, check_sqlite
from labcal.store.journal import EventRow, PointRecord, RunRow
from labcal.store.lock import held_by
from labcal.store.rundir import open_run, read_run_json


@dataclass(frozen=True)
class RunRecord:
    """A completed run: its readings, the plan it followed and what it recorded about itself."""

    directory: Path
    readings: Readings
    readings_sha256: str  # of the stored readings, so a certificate names the exact data it rests on
    plan: Plan
    plan_text: str
    meta: RunMetadata  # the journal's metadata and row over run.json: station, settings, dates, status, …
    notes: tuple[str, ...] = ()  # how the folder differs from the journal (said, not repaired)
    station: StationSnapshot | None = None  # the journal's snapshot of the station the run used
    events: tuple[EventRow, ...] = ()  # the journal's events: prompts, answers, faults, retries, pauses
    # The fits fit.json was derived from (checking the folder fits them): issuing reuses them
    fit: Fit | None = None
    device: DeviceFit | None = None  # the device model, where the points identify it
    model_note: str = ""  # which model fit.json holds, and why
    chain: ChainCheck | None = None  # the journal's chain of digests, recomputed (`labcal.store.chain`)

    @property
    def simulated(self) -> bool:
        """A dry run: on the simulated rig or its emulators, by its metadata or its station snapshot
        (either is enough: a run folder's run.json edited cannot make the journal's station real)."""
        return is_simulated(self.meta, self.station)


def readings_digest(points) -> str:
    """SHA-256 over the committed points in a canonical form: names the exact data a result rests on."""
    rows = [[p.seq, p.replicate, p.y_deg, p.u_deg, p.pitch_deg, p.roll_deg, p.vx, p.vy, p.vz, p.temp_c]
            for p in points]
    return hashlib.sha256(json.dumps(rows, separators=(",", ":")).encode()).hexdigest()


def load_run(run_dir: str | Path) -> RunRecord:
    """Read a run from its journal; a missing, unfinished, foreign or malformed run is one
    LabcalError line. A read: it changes neither the folder nor the journal. The folder's exports
    are checked against the journal on the way and a missing, stale or edited one is named in the
    notes (`labcal.store.exports.check`); rewriting them is its own use case (`labcal export RUN`,
    `labcal.app.folders.rebuild_run_folder`)."""
    run_dir = Path(run_dir)
    if not run_dir.is_dir():
        raise LabcalError(f"{run_dir}: no such run directory (if it was deleted, `labcal export RUN_ID` "
                          "recreates it from the journal)")
    _, journal, row = open_run(run_dir)
    with journal:
        if row.status != "complete":
            state = row.status
            if state == "running" and held_by(journal.path, row.id) is None:
                state = "interrupted (its process ended without closing it)"
            why = f" ({row.reason})" if row.reason else ""
            raise LabcalError(f"{run_dir}: the run is {state}{why}; only a complete run gets a "
                              "certificate (labcal resume finishes it)")
        notes, derived = exports.check(journal, row, run_dir)
        info = read_run_json(run_dir)
        points = journal.points(row.id, status="ok")
        readings = journal.readings(row.id)
        events = tuple(journal.events(row.id))
        chain = check_sqlite(journal.db, row.id)
    return run_record(run_dir, row, info, points, readings, events, chain, notes, f"run {row.id}",
                      "the journal", derived)


def run_record(directory: Path, row: RunRow, info: dict, points: list[PointRecord], readings: Readings,
               events: tuple[EventRow, ...], chain: ChainCheck, notes: list[str], label: str, copy: str,
               derived: exports.Derived | None = None) -> RunRecord:
    """A run as a `RunRecord`, from wherever it was read — a station's journal and its folder's run.json
    (`load_run`), or the lab database's copy (`labcal.store.lab_certificates.lab_record`): the journal's
    row stated over run.json's ``info``, the readings in the station's output unit, the chain's problem
    (if any) noted as a change to ``copy``. ``label`` names the run in the plan's errors."""
    station = parse_snapshot(row.station_text)
    if chain.problem is not None:
        notes = [*notes, f"{copy} was changed after it was written: {chain.problem}"]
    meta = parse_run_metadata({**info, **row.metadata, "status": row.status, "reason": row.reason,
                               "started_utc": row.started_utc, "ended_utc": row.ended_utc,
                               "settings": row.settings, "instrument_serial": row.instrument_serial,
                               "operator": row.operator}, f"{label}'s metadata")
    fits = (derived.fit, derived.device, derived.model_note) if derived is not None else (None, None, "")
    return RunRecord(directory, replace(readings, units=output_units(station)), readings_digest(points),
                     parse_plan(row.plan_text, f"{label} plan"), row.plan_text, meta, tuple(notes), station,
                     events, *fits, chain)

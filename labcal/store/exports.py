"""A run folder's files, derived from the journal: written whole, checked, repaired.

plan.toml, readings.csv, fit.json and run.json are exports of the run's journal entry: the same
journal always gives the same bytes. Each is written with `write_atomic` (temporary file, one
fsync, rename), run.json last, and their SHA-256 are journaled with the run's status in one
transaction (`Journal.finish`), so a run is "complete" only once the files that show it are in
place. `check` compares a folder with what the journal gives and only says what differs (every
read of a run); `sync` rewrites what is missing or stale (`labcal export`, `labcal resume`); a
file whose hash labcal never wrote (edited by hand) is named, kept beside as
``NAME.edited`` and rewritten — nothing anyone wrote is lost, and the journal stays the truth.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, replace
from pathlib import Path

from labcal.analysis.device_fit import DeviceFit, preferred_fit
from labcal.analysis.fit import SENSORS, Fit, fit_readings, reference_temperature
from labcal.analysis.models import Model
from labcal.analysis.readings import Readings
from labcal.config.files import write_atomic
from labcal.config.json_values import json_safe
from labcal.config.plans import plan_correction
from labcal.config.readings_csv import ReadingsWriter, coefficient_units
from labcal.config.run_metadata import parse_run_metadata
from labcal.config.snapshot import StationSnapshot, output_units, parse_snapshot, stated_angle_errors
from labcal.errors import LabcalError
from labcal.store.journal import Journal, RunRow
from labcal.store.rundir import FIT, PLAN, READINGS, RUN, identity

EXPORTS = (PLAN, READINGS, FIT, RUN)  # in the order written: run.json, which names the run, last


@dataclass(frozen=True)
class Derived:
    """What the journal gives for a run folder: each file's bytes, and the fit (None: too few points)."""

    files: dict[str, bytes]
    fit: Fit | None
    device: DeviceFit | None = None  # the device model, where the points identify it
    model_note: str = ""  # which model fit.json holds, and why


def digest(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def derive(journal: Journal, row: RunRow, status: str | None = None, reason: str | None = None) -> Derived:
    """Every export of ``row`` as the journal has it (``status``/``reason``: the ones about to be
    journaled, when the run is ending)."""
    points = journal.points(row.id, status="ok")
    writer = ReadingsWriter(Path(READINGS), temperature=bool(points) and all(p.temp_c is not None
                                                                                for p in points))
    for p in points:
        writer.append(replicate=p.replicate, y_deg=p.y_deg, u_deg=p.u_deg, pitch_deg=p.pitch_deg,
                      roll_deg=p.roll_deg, volts=[p.vx, p.vy, p.vz], temp_c=p.temp_c,
                      sd=[p.sd_vx, p.sd_vy, p.sd_vz], n_samples=p.n_samples, time_s=p.t_end)
    snapshot = parse_snapshot(row.station_text)
    units = output_units(snapshot)  # the station's [instrument] units; volts unless it says
    stated = "" if units == "V" else f"# units = {units}\n"  # `labcal fit` reads it; volts: as before
    files = {PLAN: row.plan_text.encode("utf-8"), READINGS: (stated + writer.text()).encode("utf-8")}
    fit, device, note = None, None, ""
    if points:
        readings = replace(journal.readings(row.id), units=units)
        try:
            fit, device, note = run_fits(readings, row.plan_text, snapshot)
        except LabcalError:
            fit = None  # too few points so far for a fit
    if fit is not None:
        doc = fit.to_json() if device is None else device.to_json()
        doc["notes"] = [note, *doc.get("notes", [])]
        if (status or row.status) == "failed":  # the coefficients of readings that failed: no certificate
            doc["notes"].insert(0, f"the run failed and issues no certificate: {reason or row.reason}")
        if units != "V":  # as `labcal fit --units` states it: B in these, S in these per g
            doc["units"] = units
            doc["layout"] = {**doc["layout"], "units": coefficient_units(units)}
        files[FIT] = _json(doc)
    status = status or row.status
    info = {"labcal_version": row.software_version, "journal": str(journal.path.resolve()),
            **identity(row), "plan": row.plan_name, "station": station_description(row),
            "operator": row.operator, "status": status,
            "reason": reason if status != row.status or reason else row.reason,
            "points_recorded": len(points), "rig_time_s": journal.rig_time(row.id),
            "settings": row.settings, **{k: v for k, v in row.metadata.items() if k != "station"}}
    files[RUN] = _json(info)
    return Derived(files, fit, device, note)


def run_fits(readings: Readings, plan_text: str, station: StationSnapshot | None
             ) -> tuple[Fit, DeviceFit | None, str]:
    """A run's fits and the line saying which of them fit.json holds. A plan with a device correction
   : the linear fit on the gravity its misalignments give (held at the correction's values,
    what the remounts it leaves out would have identified; Soto eq. 11), no device model. Else the
    device model where the points identify it, with the tables' index and wobble as the run's station
    states them, or the linear fit. LabcalError where the readings cannot be fitted."""
    correction = plan_correction(plan_text, "the run's plan")
    if correction is not None:
        model = Model(t_ref=reference_temperature(readings), device=correction.misalignment())
        return fit_readings(readings, model), None, correction.model_note()
    fit = fit_readings(readings)
    if fit.sensors != SENSORS:  # the device model needs three sensors' gravity to see the misalignments
        return fit, None, (f"linear model of the {', '.join(fit.sensors)} sensor(s) the package has, each "
                           "v = b + s·g (Tripp & Tcheng eq. 8)")
    return fit, *preferred_fit(readings, fit, stated_angle_errors(station))


def station_description(row: RunRow) -> str:
    """What the run's station was, from the journal (runs before it was journaled: from the kind of
    its snapshot)."""
    recorded = parse_run_metadata(row.metadata, f"run {row.id}'s metadata").station
    if recorded:
        return recorded
    snapshot = parse_snapshot(row.station_text)
    return snapshot.kind if snapshot is not None else "the station in the journal's snapshot"


def _json(doc: dict) -> bytes:
    return (json.dumps(json_safe(doc), indent=2) + "\n").encode("utf-8")


def write(run_dir: Path, derived: Derived) -> dict[str, str]:
    """Write every export whose bytes differ from the folder's (run.json last); their hashes."""
    for name, data in derived.files.items():
        if _read(run_dir / name) != data:
            write_atomic(run_dir / name, data)
    return {name: digest(data) for name, data in derived.files.items()}


def _read(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except OSError:
        return None


def differences(run_dir: Path, derived: Derived, known: dict[str, str], row: RunRow) -> list[tuple[str, str]]:
    """How a folder differs from what the journal gives, reading only: (name, what) for each export
    that is "missing", "stale" (a file labcal wrote for this run, out of date) or "edited" (a hash
    labcal never wrote for it); an identical file, or an older labcal's plan.toml of the same plan
    text, is not named."""
    found = []
    for name, data in derived.files.items():
        on_disk = _read(run_dir / name)
        if on_disk == data:
            continue
        if on_disk is None:
            found.append((name, "missing"))
            continue
        sha = digest(on_disk)
        if sha == known.get(name) or (name == RUN and _is_run_json_of(on_disk, row)):
            found.append((name, "stale"))
        elif not (name == PLAN and sha == row.plan_hash):
            found.append((name, "edited"))
    return found


def check(journal: Journal, row: RunRow, run_dir: Path) -> tuple[list[str], Derived]:
    """What `sync` would repair in a run folder, said and not done: one note per export that is
    missing, out of date or edited, and per partial file of a killed write. Writes nothing (a read
    of a run never changes its folder or the journal; `labcal export RUN` rebuilds it)."""
    derived = derive(journal, row)
    rebuild = f"`labcal export {run_dir}` rewrites it from the journal"
    notes = [f"{path.name}: a partial file left by a killed write; `labcal export {run_dir}` removes it"
             for path in orphans(run_dir)]
    for name, what in differences(run_dir, derived, journal.export_hashes(row.id), row):
        if what == "edited":
            found = digest((run_dir / name).read_bytes())
            notes.append(f"{name} was edited by hand (sha256 {found[:12]}…, the journal's "
                         f"{digest(derived.files[name])[:12]}…); {rebuild}, keeping yours as {name}.edited")
        else:
            notes.append(f"{name} is {'missing' if what == 'missing' else 'out of date'}; {rebuild}")
    return notes, derived


def sync(journal: Journal, row: RunRow, run_dir: Path, remember: bool = True) -> tuple[list[str], Derived]:
    """Bring a run folder back to what its journal says; one note per file that was not. Returns
    the notes and what was derived (the fits included, so that nothing fits them again).

    Missing and stale exports (a kill before they were rewritten) are rewritten; a file whose hash
    is none that labcal wrote for this run was edited by hand: it is named, kept as NAME.edited,
    and rewritten from the journal. ``remember`` False: a copy elsewhere, whose hashes the journal
    does not keep (it records the run's own folder only)."""
    derived = derive(journal, row)
    known = journal.export_hashes(row.id)
    notes = [f"{name} removed: a partial file left by a killed write" for name in remove_orphans(run_dir)]
    for name, what in differences(run_dir, derived, known, row):
        if what == "missing":
            notes.append(f"{name} was missing; rewritten from the journal")
        elif what == "stale":
            notes.append(f"{name} was out of date; rewritten from the journal")
        else:
            path = run_dir / name
            found = digest(path.read_bytes())
            kept = path.with_name(name + ".edited")
            os.replace(path, kept)
            notes.append(f"{name} was edited by hand (sha256 {found[:12]}…, the journal's "
                         f"{digest(derived.files[name])[:12]}…); kept as {kept.name}, rewritten from the "
                         "journal")
    hashes = write(run_dir, derived)
    if remember:
        journal.exported(row.id, hashes)
    return notes, derived


def orphans(run_dir: Path) -> list[Path]:
    """The temporary files of writes whose process is gone (`write_atomic` names them
    ``.NAME.PID.tmp``); a live writer's are not among them."""
    found = []
    for path in run_dir.glob(".*.*.tmp"):
        pid = path.name.rsplit(".", 2)[-2]
        if pid.isdigit() and not _alive(int(pid)):
            found.append(path)
    return found


def remove_orphans(run_dir: Path) -> list[str]:
    """Delete the temporary files of writes whose process is gone; returns their names."""
    removed = []
    for path in orphans(run_dir):
        try:
            path.unlink()
        except OSError:
            continue
        removed.append(path.name)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True  # someone else's process: alive
    return True


def _is_run_json_of(data: bytes, row: RunRow) -> bool:
    """run.json is labcal's status record, rewritten at every stop: one naming this run is labcal's."""
    try:
        info = json.loads(data)
    except ValueError:
        return False
    if not isinstance(info, dict):
        return False
    if "run_uuid" in info:
        return info["run_uuid"] == row.uuid
    return info.get("run_id") == row.id and info.get("plan_sha256") == row.plan_hash  # before UUIDs

"""The calibration device's own history: every device-model estimate of its misalignments a…k,
stored per calibration-device id in the lab database (table ``device_estimates``, `labcal.store.labdb`),
and the changes between consecutive estimates that exceed their combined expanded uncertainty —
the lab's health chart for its rotary tables.

Each estimate comes from a finished run whose plan identifies all six misalignments; a run whose
plan cannot is not stored (there is nothing to store). The device id is what the run recorded
(``device_id`` in run.json), else ``SIMULATED`` for a dry run, else the station's description.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from contextlib import closing
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis import correction_check
from labcal.analysis.correction_check import FALSE_ALARM, Change, check
from labcal.analysis.device_fit import DeviceFit, PointMeans
from labcal.analysis.fit import Fit
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES
from labcal.analysis.plan import Plan
from labcal.config.corrections import DeviceCorrectionTable
from labcal.config.files import write_json
from labcal.config.lab import load_lab_config
from labcal.config.plans import DEVICE_CORRECTION, plan_correction
from labcal.config.readings_csv import read_numeric_csv
from labcal.config.run_metadata import RunMetadata
from labcal.config.snapshot import stated_angle_errors
from labcal.documents.device_report import DEVICE_JSON, device_document
from labcal.documents.plotfile import check_folder, save
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labdb
from labcal.store.journal import db_path
from labcal.store.record import RunRecord
from labcal.store.rundir import READINGS

if TYPE_CHECKING:
    from matplotlib import figure

    from labcal.analysis import device_ageing, device_model, optimize
    from labcal.documents import history
else:
    device_ageing = lazy("labcal.analysis.device_ageing")  # start-up without numpy
    device_model = lazy("labcal.analysis.device_model")  # start-up without scipy, numpy
    figure = lazy("matplotlib.figure")  # start-up without matplotlib, numpy
    history = lazy("labcal.documents.history")  # with the certificates: not on a run's path
    optimize = lazy("labcal.analysis.optimize")  # start-up without scipy, numpy, pydantic

RULE = "|Δ| > √(U₁² + U₂²): a change larger than the combined expanded uncertainty (95 %)"
IDENTIFYING_PLAN = "four-mount-64"  # the built-in plan whose mounts identify all six misalignments


class DeviceMoved(LabcalError):
    """A corrected run saw the calibration device's misalignments move since the estimate its plan
    corrects for: no certificate is issued from the correction. ``changes``: the check's verdicts."""

    def __init__(self, message: str, changes: list[Change]) -> None:
        super().__init__(message)
        self.changes = changes


def correction_changes(record: RunRecord, fit: Fit, correction: DeviceCorrectionTable) -> list[Change]:
    """The run's check of the misalignments its plan corrects for (`analysis.correction_check.check`):
    each one the run sees, its change since the correction's estimate and the verdict; the tables'
    index and wobble as the run's station states them."""
    names, held = MISALIGNMENT_NAMES, correction.misalignment()
    noise = window_noise(record)
    return check(PointMeans.of(record.readings), fit.ls.residuals, fit.coefficients,
                 fit.ls.residual_se if noise is None else noise,
                 np.array([getattr(held, n) for n in names]),
                 np.array([correction.u_history_rad()[n] for n in names]),
                 np.array([correction.u_rad()[n] for n in names]), stated_angle_errors(record.station))


def window_noise(record: RunRecord) -> NDArray[np.float64] | None:
    """Each sensor's noise of one reading (a window's mean), from the scatter within the windows that
    readings.csv records (sd of the samples, their number): √(mean of sd²/n). The noise the plan was
    priced with; the residuals would count the tables' per-angle errors, which the check adds as
    their own term, a second time. None where the file does not record them (readings imported)."""
    wanted = ("n_samples", "sd_vx", "sd_vy", "sd_vz")
    try:
        cols = read_numeric_csv(record.directory / READINGS, "readings", wanted)
    except LabcalError:
        return None
    n = cols["n_samples"]
    if len(n) == 0 or np.any(n < 2):
        return None
    sd = np.column_stack([cols[c] for c in wanted[1:]])
    return np.asarray(np.sqrt(np.mean(sd**2 / n[:, None], axis=0)), dtype=float)


def refuse_if_moved(record: RunRecord, fit: Fit) -> list[Change]:
    """The run's check where its plan corrects for the device (else []); `DeviceMoved` (one line naming
    the largest change and the plan that identifies the device again) where a change is detected."""
    correction = plan_correction(record.plan_text, f"{record.directory}: the run's plan")
    if correction is None:
        return []
    found = correction_changes(record, fit, correction)
    moved = sorted((c for c in found if c.detected), key=lambda c: -abs(c.z))
    if moved:
        also = "" if len(moved) == 1 else f" (and {', '.join(c.name for c in moved[1:])})"
        since = f"its estimate of run {correction.source} ({correction.calibrated_utc})"
        raise DeviceMoved(
            f"no certificate from this run's device correction: {moved[0].describe(since)}{also}, beyond its "
            f"check's {100 * FALSE_ALARM:g} % false-alarm limit; identify the device again with a plan that "
            f"does (labcal run --plan {IDENTIFYING_PLAN}), then plan with labcal plan optimize --device "
            f"{correction.device_id}", found)
    return found


@dataclass(frozen=True)
class DeviceEstimate:
    """One run's estimate of the device's six misalignments, in arcseconds with U (95 %)."""

    device_id: str
    calibrated_utc: str
    source: str  # the run it came from (its folder name)
    value_arcsec: dict[str, float]
    U_arcsec: dict[str, float]

    def to_json(self) -> dict[str, Any]:
        return {"device_id": self.device_id, "calibrated_utc": self.calibrated_utc, "source": self.source,
                "misalignments": {n: {"value_arcsec": self.value_arcsec[n], "U_arcsec": self.U_arcsec[n]}
                                  for n in MISALIGNMENT_NAMES}}


def device_id_of(record: RunRecord) -> str:
    return station_device_id(record.meta, record.simulated)


def station_device_id(metadata: RunMetadata, simulated: bool) -> str:
    """The calibration device's id as a run records it: ``device_id`` in its metadata, else SIMULATED for
    a dry run, else the station's description."""
    if metadata.device_id:
        return metadata.device_id
    return "SIMULATED" if simulated else (metadata.station or "UNNAMED")


NORMAL_K = 1.96  # U → u of an estimate: its U is stated at 95 % with the device fit's many dof


def calibrated(estimate: DeviceEstimate) -> datetime:
    """When the estimate's run calibrated (UTC; a time without a zone is read as UTC)."""
    try:
        t = datetime.fromisoformat(estimate.calibrated_utc)
    except ValueError:
        raise LabcalError(f"device {estimate.device_id}'s estimate from {estimate.source} has no readable "
                          f"calibration time ({estimate.calibrated_utc!r})") from None
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)


def in_sittings(estimates: list[DeviceEstimate]) -> list[DeviceEstimate]:
    """The history's distinct sittings, each by its latest estimate (`analysis.device_ageing.sittings`):
    estimates of one UTC day, or of the same readings, are one piece of evidence, not several."""
    found = device_ageing.sittings(
        [calibrated(e) for e in estimates],
        [np.array([e.value_arcsec[n] for n in MISALIGNMENT_NAMES]) for e in estimates],
    )
    return [estimates[i] for i in found.kept]


def correction_uses(device_id: str, source: str, db: str | Path | None = None) -> int:
    """How many complete runs journaled in ``db`` corrected from ``device_id``'s estimate ``source``."""
    path = db_path(db)
    if not path.is_file():
        return 0
    with closing(labdb.connect(path)) as conn:
        rows = conn.execute("SELECT plan_text FROM runs WHERE status = 'complete' AND plan_text LIKE ?",
                            (f"%[{DEVICE_CORRECTION}]%",)).fetchall()
    used = 0
    for (text,) in rows:
        try:
            c = plan_correction(text, "a journaled plan")
        except LabcalError:
            continue
        used += c is not None and (c.device_id, c.source) == (device_id, source)
    return used


def expired(device_id: str, source: str, calibrated_at: datetime, db: str | Path | None,
            now: datetime | None = None) -> str | None:
    """Why a correction from this estimate may no longer be used (the lab file's limits: its age, its
    number of uses), or None."""
    limits = load_lab_config().file.device_correction
    age = ((now or datetime.now(UTC)) - calibrated_at).total_seconds() / 86400.0
    again = (f"identify the device again with a plan that does (labcal run --plan {IDENTIFYING_PLAN}), then "
             f"plan with labcal plan optimize --device {device_id}")
    if age > limits.max_age_days:
        return (f"device {device_id}'s estimate from {source} is {age:.0f} days old, past the lab's "
                f"{limits.max_age_days:g}-day limit for a correction; {again}")
    uses = correction_uses(device_id, source, db)
    if uses >= limits.max_uses:
        return (f"device {device_id}'s estimate from {source} has corrected {uses} runs, the lab's limit "
                f"({limits.max_uses}); {again}")
    return None


def correction_for(device_id: str, db: str | Path | None = None, now: datetime | None = None,
                   said: Callable[[str], None] | None = None):
    """The device's misalignments where its history knows them, as `analysis.optimize.DeviceCorrection`:
    two sittings at least, no flagged change between the last two (`RULE`), the latest not expired;
    each u aged by the history's random walk (`analysis.device_ageing`) to ``now``. (None, why) where
    not known. ``said`` hears the line saying the lab could not be reached (`estimates_read`)."""
    estimates, stale = estimates_read(device_id, db)  # an unknown device: one line naming the known ones
    if stale and said is not None:
        said(stale)
    kept = in_sittings(estimates)
    if len(kept) < 2:
        return None, (f"device {device_id} has {len(estimates)} estimate(s) from {len(kept)} sitting(s); two "
                      "sittings (different days, different readings) are needed to judge it in control")
    moved = [c for c in changes(kept[-2:]) if c.flagged]
    if moved:
        return None, (f"device {device_id} changed between {moved[0].before} and {moved[0].after} "
                      f"({', '.join(c.name for c in moved)} beyond √(U₁² + U₂²)); its misalignments are not "
                      "known")
    last = kept[-1]
    why = expired(device_id, last.source, calibrated(last), db, now)
    if why:
        return None, why
    rate = device_ageing.walk_rate(
        [calibrated(e) for e in kept],
        [np.array([e.value_arcsec[n] for n in MISALIGNMENT_NAMES]) for e in kept],
        [np.array([e.U_arcsec[n] / NORMAL_K for n in MISALIGNMENT_NAMES]) for e in kept],
    )
    age = ((now or datetime.now(UTC)) - calibrated(last)).total_seconds() / 86400.0
    u = rate.aged_u(np.array([last.U_arcsec[n] / NORMAL_K for n in MISALIGNMENT_NAMES]), age)
    return optimize.DeviceCorrection(
        device_id,
        last.source,
        {n: last.value_arcsec[n] * ARCSEC for n in MISALIGNMENT_NAMES},
        {n: float(v) * ARCSEC for n, v in zip(MISALIGNMENT_NAMES, u, strict=True)},
        {n: last.U_arcsec[n] * ARCSEC for n in MISALIGNMENT_NAMES},
        last.calibrated_utc,
    ), ""


def check_correction(correction: DeviceCorrectionTable, device_id: str, db: str | Path | None = None,
                     plan: Plan | None = None) -> None:
    """Whether a plan's device correction still applies to the station about to run it:
    the station's calibration device is the one corrected for, and its history still has the estimate
    the correction took with no flagged change (`RULE`) from it to the latest; the estimate is not
    expired (`expired`); and the plan's points see every misalignment it corrects for, so that its run
    can notice one move (`analysis.correction_check`). One LabcalError line where not: the plan's
    misalignments would then not be the device's, or not known to be."""
    wanted = correction.device_id
    if device_id != wanted:
        raise LabcalError(f"this plan corrects for calibration device {wanted}'s misalignments but this "
                          f"station's device is {device_id}: plan again with labcal plan optimize --device "
                          f"{device_id}, or run a plan that identifies them (four-mount-64)")
    estimates = estimates_for(wanted, db)
    sources = [e.source for e in estimates]
    if correction.source not in sources:
        raise LabcalError(f"device {wanted}'s history has no estimate from {correction.source}, which this "
                          f"plan's correction took; plan again with labcal plan optimize --device {wanted}")
    moved = [c for c in changes(estimates[sources.index(correction.source):]) if c.flagged]
    if moved:
        first = moved[0]
        names = ", ".join(c.name for c in moved if (c.before, c.after) == (first.before, first.after))
        raise LabcalError(f"device {wanted} changed since {correction.source}, whose estimate this plan "
                          f"corrects for: {names} moved between {first.before} and {first.after} beyond "
                          "√(U₁² + U₂²); measure its misalignments again with a plan that identifies them "
                          "(four-mount-64)")
    why = expired(wanted, correction.source, calibrated(estimates[sources.index(correction.source)]), db)
    if why:
        raise LabcalError(why)
    if plan is not None:
        unit = np.vstack([np.zeros(3), np.eye(3)])  # what is seen is geometry: any instrument, any noise
        held = correction.misalignment()
        seen = correction_check.sensitivity(
            device_model.Geometry.of_plan(list(plan.points), list(plan.mounts)),
            unit,
            np.ones(3),
            np.array([getattr(held, n) for n in MISALIGNMENT_NAMES]),
        ).observable
        unseen = [n for n in MISALIGNMENT_NAMES if n not in seen]
        if unseen:
            raise LabcalError(f"this plan corrects for device {wanted}'s misalignments but its mounts cannot "
                              f"see {', '.join(unseen)}: a run could not notice them move; add mounts (three "
                              "that reverse fore/aft and top/bottom), or plan with labcal plan optimize "
                              f"--device {wanted}")


def estimate_of(record: RunRecord, fit: DeviceFit) -> DeviceEstimate:
    doc = fit.to_json()["misalignments"]
    return DeviceEstimate(device_id_of(record), str(record.meta.started_utc or ""),
                          record.directory.name, {n: doc[n]["value_arcsec"] for n in MISALIGNMENT_NAMES},
                          {n: doc[n]["U_arcsec"] for n in MISALIGNMENT_NAMES})


def store_device_estimate(record: RunRecord, fit: DeviceFit, db: str | Path | None = None) -> Path:
    """A finished run's device estimate: into the lab database, and as device.json in the run folder
    (the device's misalignments with U and the instrument's intrinsic parameters, beside the
    certificate)."""
    estimate = estimate_of(record, fit)
    write_json(record.directory / DEVICE_JSON, device_document(fit, estimate.device_id))
    return store(estimate, db)


def store(estimate: DeviceEstimate, db: str | Path | None = None) -> Path:
    """Insert the estimate, or replace the one stored before from the same run."""
    path = db_path(db)
    with closing(labdb.connect(path)) as conn, conn:
        conn.execute("INSERT OR REPLACE INTO device_estimates (device_id, source, calibrated_utc, stored_utc,"
                     " document) VALUES (?, ?, ?, ?, ?)",
                     (estimate.device_id, estimate.source, estimate.calibrated_utc,
                      datetime.now(UTC).isoformat(timespec="seconds"), json.dumps(estimate.to_json())))
    return path


def estimates_for(device_id: str, db: str | Path | None = None) -> list[DeviceEstimate]:
    """The device's estimates, oldest calibration first (`estimates_read`)."""
    return estimates_read(device_id, db)[0]


def estimates_read(device_id: str, db: str | Path | None = None) -> tuple[list[DeviceEstimate], str | None]:
    """The device's estimates, oldest calibration first: every bench's, where the lab database is a
    server; and the line saying the lab could not be reached (None: read from it)."""
    stored = history.stored_rows(
        db, "device_estimates", "device_id", device_id, ("document",), ("calibrated_utc", "source"),
        f"no device estimates for {device_id!r}", "known devices",
        "a finished run stores its device estimate there")
    found = []
    for (text,) in stored.rows:
        try:
            doc = json.loads(text)
            mis = doc["misalignments"]
            found.append(DeviceEstimate(doc["device_id"], doc["calibrated_utc"], doc["source"],
                                        {n: float(mis[n]["value_arcsec"]) for n in MISALIGNMENT_NAMES},
                                        {n: float(mis[n]["U_arcsec"]) for n in MISALIGNMENT_NAMES}))
        except (ValueError, KeyError, TypeError) as exc:
            raise LabcalError(f"{stored.shown}: a device estimate of {device_id!r} is damaged "
                              f"({exc})") from None
    return found, stored.stale


@dataclass(frozen=True)
class DeviceChange:
    name: str
    before: str
    after: str
    delta_arcsec: float
    limit_arcsec: float

    @property
    def flagged(self) -> bool:
        return abs(self.delta_arcsec) > self.limit_arcsec

    def to_json(self) -> dict[str, Any]:
        return {"misalignment": self.name, "before": self.before, "after": self.after,
                "delta_arcsec": self.delta_arcsec, "limit_arcsec": self.limit_arcsec, "flagged": self.flagged}


def changes(estimates: list[DeviceEstimate]) -> list[DeviceChange]:
    """Every misalignment's change between consecutive estimates, judged by `RULE`."""
    return [DeviceChange(n, a.source, b.source, b.value_arcsec[n] - a.value_arcsec[n],
                         (a.U_arcsec[n] ** 2 + b.U_arcsec[n] ** 2) ** 0.5)
            for a, b in zip(estimates, estimates[1:], strict=False) for n in MISALIGNMENT_NAMES]


def history_json(device_id: str, estimates: list[DeviceEstimate],
                 found: list[DeviceChange]) -> dict[str, Any]:
    return {"device_id": device_id, "rule": RULE, "estimates": [e.to_json() for e in estimates],
            "changes": [c.to_json() for c in found], "flagged": [c.to_json() for c in found if c.flagged]}


def plot_history(device_id: str, estimates: list[DeviceEstimate], found: list[DeviceChange],
                 path: str | Path) -> None:
    """Each misalignment against calibration number with ±U error bars; flagged changes in red."""
    check_folder(path)
    index = {e.source: n for n, e in enumerate(estimates, start=1)}
    fig = figure.Figure(figsize=(10, 6))
    fig.subplots_adjust(left=0.08, right=0.98, top=0.9, bottom=0.1, hspace=0.35, wspace=0.3)
    axes = fig.subplots(2, 3, squeeze=False).ravel()
    numbers = list(range(1, len(estimates) + 1))
    for ax, name in zip(axes, MISALIGNMENT_NAMES, strict=True):
        values = [e.value_arcsec[name] for e in estimates]
        ax.errorbar(numbers, values, yerr=[e.U_arcsec[name] for e in estimates], fmt="o-", ms=4, capsize=3)
        for ch in found:
            if ch.flagged and ch.name == name:
                n0, n1 = index[ch.before], index[ch.after]
                ax.plot([n0, n1], [values[n0 - 1], values[n1 - 1]], color="tab:red", lw=2.5)
        ax.set_title(f"{name} (arcsec)", fontsize=9)
        ax.set_xlabel("calibration #")
        ax.set_xticks(numbers)
    fig.suptitle(f"Calibration device {device_id}: misalignments ± U (95 %); red: change > combined U",
                 fontsize=10)
    save(fig, path, dpi=110)

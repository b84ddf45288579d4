"""The calibration device's own history: every device-model estimate of its misalignments a…k,
stored per calibration-device id in the lab database (table ``device_estimates``, `labcal.run.labdb`),
and the changes between consecutive estimates that exceed their combined expanded uncertainty —
the lab's health chart for its rotary tables (issue 12).

Each estimate comes from a finished run whose plan identifies all six misalignments; a run whose
plan cannot is not stored (there is nothing to store). The device id is what the run recorded
(``device_id`` in run.json), else ``SIMULATED`` for a dry run, else the station's description.
"""

from __future__ import annotations

import json
from contextlib import closing
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.kinematics import MISALIGNMENT_NAMES
from labcal.config.corrections import DeviceCorrectionTable
from labcal.documents.plotfile import check_folder, save
from labcal.errors import LabcalError
from labcal.run import labdb
from labcal.run.journal import db_path
from labcal.run.record import RunRecord

RULE = "|Δ| > √(U₁² + U₂²): a change larger than the combined expanded uncertainty (95 %)"


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


def station_device_id(metadata: dict, simulated: bool) -> str:
    """The calibration device's id as a run records it: ``device_id`` in its metadata, else SIMULATED for
    a dry run, else the station's description."""
    recorded = metadata.get("device_id")
    if recorded:
        return str(recorded)
    return "SIMULATED" if simulated else str(metadata.get("station") or "UNNAMED")


def check_correction(correction: DeviceCorrectionTable, device_id: str, db: str | Path | None = None) -> None:
    """Whether a plan's device correction still applies to the station about to run it (issue 27):
    the station's calibration device is the one corrected for, and its history still has the estimate
    the correction took with no flagged change (`RULE`) from it to the latest. One LabcalError line
    where not: the plan's misalignments would then not be the device's."""
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


def estimate_of(record: RunRecord, fit: DeviceFit) -> DeviceEstimate:
    doc = fit.to_json()["misalignments"]
    return DeviceEstimate(device_id_of(record), str(record.meta.get("started_utc", "")),
                          record.directory.name, {n: doc[n]["value_arcsec"] for n in MISALIGNMENT_NAMES},
                          {n: doc[n]["U_arcsec"] for n in MISALIGNMENT_NAMES})


def store_device_estimate(record: RunRecord, fit: DeviceFit, db: str | Path | None = None) -> Path:
    """A finished run's device estimate: into the lab database, and as device.json in the run folder
    (the device's misalignments with U and the instrument's intrinsic parameters, beside the
    certificate)."""
    from labcal.config.files import write_json
    from labcal.documents.device_report import DEVICE_JSON, device_document

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
    from labcal.documents.history import stored_rows  # with the certificates: not on a run's path

    stored = stored_rows(
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
    from matplotlib.figure import Figure

    check_folder(path)
    index = {e.source: n for n, e in enumerate(estimates, start=1)}
    fig = Figure(figsize=(10, 6))
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

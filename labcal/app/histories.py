"""An instrument's coefficients over its calibrations, and the calibration device's misalignments
over its runs: pure reads of the lab database (a plot, when asked for, is written where asked)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from labcal.analysis.fit import ROW_NAMES, SENSORS
from labcal.analysis.kinematics import MISALIGNMENT_NAMES
from labcal.documents.certificate import format_result
from labcal.documents.history import RULE, certificates_read, changes, history_json, plot_history
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.documents import device_history as documents_device_history
else:
    # start-up without scipy, numpy, pydantic
    documents_device_history = lazy("labcal.documents.device_history")


@dataclass(frozen=True)
class Cell:
    text: str
    flagged: bool = False  # changed from the calibration before by more than the rule allows


@dataclass(frozen=True)
class HistoryTable:
    title: str
    columns: tuple[str, ...]
    rows: tuple[tuple[Cell, ...], ...]


@dataclass(frozen=True)
class History:
    """What a history shows: the calibrations in order, one table per sensor (or one for the device),
    each flagged change in words, the rule, and the JSON document of it all."""

    subject: str  # the instrument's serial or the device's id
    entries: tuple[str, ...]  # one line per calibration, oldest first
    tables: tuple[HistoryTable, ...]
    flagged: tuple[str, ...]
    tally: str
    rule: str
    document: dict[str, Any]
    plot: str | None = None
    stale: str | None = None  # the lab could not be reached: read from this bench's journal, this old


@dataclass(frozen=True)
class InstrumentHistory:
    serial: str
    db: str | None = None
    include_simulated: bool = False  # dry runs under this serial (left out: never taken for real ones)
    plot: str | None = None  # also plot each coefficient over time into this file


def instrument_history(request: InstrumentHistory) -> History:
    """Every certificate of an instrument, oldest first, each coefficient ± U, drift flagged."""
    certs, stale = certificates_read(request.serial, request.db, request.include_simulated)
    found = changes(certs)
    if request.plot:
        plot_history(request.serial, certs, found, request.plot)
    flagged = {(c.after, c.row, c.sensor) for c in found if c.flagged}
    entries = tuple(f"{n}  {c.calibrated_utc:%Y-%m-%d %H:%M} UTC  {c.certificate_id}"
                    + ("  (simulated: a dry run)" if c.station.simulated else "")
                    for n, c in enumerate(certs, start=1))
    columns = ("#", *(f"{row} ({'V' if i == 0 else 'V/g'})" for i, row in enumerate(ROW_NAMES)))
    def cell(c, i: int, j: int) -> Cell:
        """A coefficient ± U, or a dash where the certificate's package has not that sensor."""
        X, U = c.by_sensor(c.coefficients), c.by_sensor(c.U)
        if np.isnan(X[i, j]):
            return Cell("—")
        return Cell(format_result(X[i, j], U[i, j]), (c.certificate_id, i, j) in flagged)

    present = [j for j, s in enumerate(SENSORS) if any(s in c.sensors for c in certs)] or [0, 1, 2]
    tables = tuple(HistoryTable(
        f"sensor {SENSORS[j]}: coefficients ± U (95 %)", columns,
        tuple((Cell(str(n)), *(cell(c, i, j) for i in range(len(ROW_NAMES))))
              for n, c in enumerate(certs, start=1)))
        for j in present)
    lines = tuple(f"{ch.name} from {ch.before} to {ch.after}: Δ = {ch.delta:+.3g}, "
                  f"limit k·√(u₁²+u₂²) = {ch.limit:.2g} (k = {ch.k:.2f})" for ch in found if ch.flagged)
    return History(request.serial, entries, tables, lines, f"{len(certs)} calibration(s)", RULE,
                   history_json(request.serial, certs, found), request.plot, stale)


@dataclass(frozen=True)
class DeviceHistory:
    device_id: str
    db: str | None = None
    plot: str | None = None


def device_history(request: DeviceHistory) -> History:
    """Every device-model estimate of a calibration device, oldest first, each ± U, changes flagged."""
    estimates, stale = documents_device_history.estimates_read(request.device_id, request.db)
    found = documents_device_history.changes(estimates)
    if request.plot:
        documents_device_history.plot_history(request.device_id, estimates, found, request.plot)
    flagged = {(c.after, c.name) for c in found if c.flagged}
    table = HistoryTable(
        f"Calibration device {request.device_id}: misalignments (″) ± U (95 %)",
        ("#", "calibrated (UTC)", "run", *MISALIGNMENT_NAMES),
        tuple((Cell(str(n)), Cell(e.calibrated_utc[:16].replace("T", " ")), Cell(e.source),
               *(Cell(f"{e.value_arcsec[m]:+.2f} ± {e.U_arcsec[m]:.2f}", (e.source, m) in flagged)
                 for m in MISALIGNMENT_NAMES))
              for n, e in enumerate(estimates, start=1)))
    lines = tuple(f"{ch.name} from {ch.before} to {ch.after}: Δ = {ch.delta_arcsec:+.2f}″, "
                  f"limit √(U₁²+U₂²) = {ch.limit_arcsec:.2f}″" for ch in found if ch.flagged)
    return History(
        request.device_id,
        (),
        (table,),
        lines,
        f"{len(estimates)} estimate(s)",
        documents_device_history.RULE,
        documents_device_history.history_json(request.device_id, estimates, found),
        request.plot,
        stale,
    )

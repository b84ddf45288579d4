"""Every certificate in the lab's SQLite database, and each instrument's coefficients over time.

The database is shared with the run journal; its schema (the ``certificates`` table among the
others), version and migrations are `labcal.store.labdb`'s, and every statement here names its
columns. Its path: the --db option, else $LABCAL_DB, else the lab file's (`labcal.config.lab`).
A stored certificate is the exact JSON issued; reading it back verifies schema and digest, so
history never shows a value that was altered in the database.

Drift rule: consecutive calibrations disagree when |Δ| > k·√(u₁² + u₂²), with u the standard
uncertainties and k = t₀.₉₇₅(ν) at the Welch–Satterthwaite degrees of freedom of the difference
(GUM G.4): a change larger than the combined expanded uncertainty.
"""

from __future__ import annotations

from contextlib import closing
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import ROW_NAMES, SENSORS
from labcal.documents.certificate import COVERAGE, Certificate, certificate_from_doc, parse_json
from labcal.documents.issuing import SIMULATED_SERIAL
from labcal.documents.plotfile import check_folder, save
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labdb, labquery
from labcal.store.journal import db_path

if TYPE_CHECKING:
    from matplotlib import dates as mdates
    from matplotlib import figure
else:
    # matplotlib only for `--plot`: storing a certificate's row and reading the history draw nothing
    mdates = lazy("matplotlib.dates")
    figure = lazy("matplotlib.figure")

RULE = "|Δ| > k·√(u₁² + u₂²), k = t₀.₉₇₅(ν) at the Welch–Satterthwaite ν of the difference"


def store(cert: Certificate, db: str | Path | None = None) -> Path:
    """Insert a certificate, or replace the one issued before for the same calibration."""
    path = db_path(db)
    doc = cert.model_dump_json(indent=2)
    with closing(labdb.connect(path)) as conn, conn:
        conn.execute("INSERT OR REPLACE INTO certificates (certificate_id, serial, calibrated_utc,"
                     " issued_utc, sha256, document) VALUES (?, ?, ?, ?, ?, ?)",
                     (cert.certificate_id, cert.instrument.serial, cert.calibrated_utc.isoformat(),
                      cert.issued_utc.isoformat(), cert.digest.value, doc))
    return path


def stored_digest(certificate_id: str, db: str | Path | None = None) -> str | None:
    """The digest of the certificate stored under ``certificate_id`` (None: not in the history)."""
    path = db_path(db)
    if not path.is_file():
        return None
    with closing(labdb.connect(path)) as conn:
        row = conn.execute("SELECT sha256 FROM certificates WHERE certificate_id = ?",
                           (certificate_id,)).fetchone()
    return None if row is None else row[0]


@dataclass(frozen=True)
class Stored:
    """An instrument's or a device's rows as the lab database holds them: where they were read
    (``shown``), and the line saying the lab could not be reached (None: read from the lab)."""

    shown: str
    rows: list[tuple]
    stale: str | None


def stored_rows(db: str | Path | None, table: str, column: str, key: str, columns: tuple[str, ...],
                order: tuple[str, ...], missing: str, known_label: str, stored_by: str) -> Stored:
    """The lab database's rows for one instrument or calibration device (``column`` = ``key``):
    every bench's, where the lab is a server (`labcal.store.labquery`); a missing database, or a key
    it does not hold, is one line naming what it does hold. The instrument's and the device's
    histories both read through here."""
    found = labquery.records(db, table, columns, {column: key}, order, must_exist=False)
    if not found.exists:
        raise LabcalError(f"{found.source.shown}: no such database; {stored_by} (or give {{0}} / set "
                          "LABCAL_DB)", "db")
    if not found.rows:
        held = ", ".join(labquery.distinct(db, table, column)) or "none"
        raise LabcalError(f"{missing} in {found.source.shown}; {known_label}: {held}")
    return Stored(found.source.shown, found.rows, found.source.stale)


def certificates_for(serial: str, db: str | Path | None = None, include_simulated: bool = False
                     ) -> list[Certificate]:
    """The instrument's certificates, oldest calibration first, each verified (`certificates_read`)."""
    return certificates_read(serial, db, include_simulated)[0]


def certificates_read(serial: str, db: str | Path | None = None, include_simulated: bool = False
                      ) -> tuple[list[Certificate], str | None]:
    """The instrument's certificates, oldest calibration first, each verified, and the line saying
    the lab could not be reached (None: read from it). A dry run's certificate is left out unless
    ``include_simulated`` (or the serial is the simulator's own): a simulated calibration must never
    pass for one of the real instrument."""
    found = stored_rows(
        db, "certificates", "serial", serial, ("certificate_id", "document"),
        ("calibrated_utc", "certificate_id"),
        f"no certificates for instrument {serial!r}", "known serials",
        "`labcal report RUN` stores certificates there")
    where = found.shown
    certs = [certificate_from_doc(parse_json(doc, f"{where}: certificate {cid}"),
                                  f"{where}: certificate {cid}") for cid, doc in found.rows]
    replaced = {c.replaces for c in certs if c.replaces}
    certs = [c for c in certs if c.number not in replaced]  # a correction stands for the one it replaces
    if include_simulated or serial == SIMULATED_SERIAL:
        return certs, found.stale
    real = [c for c in certs if not c.station.simulated]
    if not real:
        raise LabcalError(f"instrument {serial!r} has only simulated certificates in {where} ({len(certs)} "
                          "dry run(s)); give {0} to see them", "include_simulated")
    return real, found.stale


@dataclass(frozen=True)
class Change:
    """One coefficient between two consecutive calibrations."""

    row: int
    sensor: int
    before: str  # certificate ids
    after: str
    delta: float
    u_combined: float
    nu: float
    k: float

    @property
    def limit(self) -> float:
        return self.k * self.u_combined

    @property
    def flagged(self) -> bool:
        return abs(self.delta) > self.limit

    @property
    def name(self) -> str:
        return f"{ROW_NAMES[self.row]} of sensor {SENSORS[self.sensor]}"

    def to_json(self) -> dict:
        return {"coefficient": ROW_NAMES[self.row], "row": self.row, "sensor": SENSORS[self.sensor],
                "before": self.before, "after": self.after, "delta": self.delta,
                "u_combined": self.u_combined, "nu": self.nu, "k": self.k, "limit": self.limit,
                "flagged": self.flagged}


def changes(certs: list[Certificate]) -> list[Change]:
    """Every coefficient's change between consecutive calibrations, judged by the drift rule."""
    found = []
    for a, b in zip(certs, certs[1:], strict=False):
        # by sensor: a package's absent sensors NaN, and not compared (a change needs both)
        ua, ub = a.by_sensor(a.standard_uncertainty), b.by_sensor(b.standard_uncertainty)
        nu_a, nu_b = (c.by_sensor(np.array(c.expanded_uncertainty.nu_eff, float)[None, :]) for c in (a, b))
        var = ua**2 + ub**2
        with np.errstate(invalid="ignore"):  # u = 0 (noise-free data): ν = ∞, any change is flagged
            nu = np.where(var > 0, var**2 / (ua**4 / nu_a + ub**4 / nu_b), np.inf)  # WS, GUM eq. G.2b
        k = t_quantile(0.5 + COVERAGE / 2, nu)
        delta = b.by_sensor(b.coefficients) - a.by_sensor(a.coefficients)
        for i in range(delta.shape[0]):
            for j in range(delta.shape[1]):
                if np.isnan(delta[i, j]):
                    continue
                found.append(Change(i, j, a.certificate_id, b.certificate_id, float(delta[i, j]),
                                    float(np.sqrt(var[i, j])), float(nu[i, j]), float(k[i, j])))
    return found


def history_json(serial: str, certs: list[Certificate], found: list[Change]) -> dict:
    return {
        "serial": serial, "rule": RULE,
        "calibrations": [{"certificate_id": c.certificate_id, "calibrated_utc": c.calibrated_utc.isoformat(),
                          "simulated": c.station.simulated,
                          "digest": c.digest.value, "coefficients": c.fit.coefficients,
                          "standard_uncertainty": c.fit.standard_errors, "U": c.expanded_uncertainty.U,
                          "k": c.expanded_uncertainty.k, "sensors": list(c.sensors)} for c in certs],
        "rows": ["B", "S row g_x", "S row g_y", "S row g_z"], "columns": ["sensor x", "sensor y", "sensor z"],
        "changes": [c.to_json() for c in found],
        "flagged": [c.to_json() for c in found if c.flagged],
    }


def plot_history(serial: str, certs: list[Certificate], found: list[Change], path: str | Path) -> None:
    """Each coefficient against calibration date with ±U error bars; flagged changes in red."""
    check_folder(path)
    dates = [c.calibrated_utc for c in certs]
    X = np.array([c.by_sensor(c.coefficients) for c in certs])  # a package's absent sensors: gaps
    U = np.array([c.by_sensor(c.U) for c in certs])
    index = {c.certificate_id: n for n, c in enumerate(certs)}
    fig = figure.Figure(figsize=(12, 10))
    fig.subplots_adjust(left=0.09, right=0.98, top=0.93, bottom=0.08, hspace=0.3, wspace=0.42)
    axes = fig.subplots(4, 3, sharex=True, squeeze=False)
    for i, row in enumerate(ROW_NAMES):
        for j, sensor in enumerate(SENSORS):
            ax = axes[i, j]
            ax.errorbar(dates, X[:, i, j], yerr=U[:, i, j], fmt="o-", ms=4, capsize=3)
            for ch in found:
                if ch.flagged and (ch.row, ch.sensor) == (i, j):
                    n0, n1 = index[ch.before], index[ch.after]
                    ax.plot([dates[n0], dates[n1]], X[[n0, n1], i, j], color="tab:red", lw=2.5,
                            label="change > combined U")
            ax.set_title(f"{row} of sensor {sensor}", fontsize=9)
            ax.set_ylabel(f"{row} ({'V' if i == 0 else 'V/g'})")
            ax.ticklabel_format(axis="y", useOffset=True, style="plain")
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=7)
            if i == len(ROW_NAMES) - 1:
                ax.set_xlabel("calibration date (UTC)", labelpad=14)  # below the date offset
                ax.xaxis.set_major_formatter(mdates.ConciseDateFormatter(ax.xaxis.get_major_locator()))
    fig.suptitle(f"Instrument {serial}: coefficients ± U (95 %) over time; red: {RULE}", fontsize=10,
                 parse_math=False)  # the serial as typed: "$" is no mathtext
    save(fig, path, dpi=110)

"""The instrument register as the lab server's pages show it: the register with each instrument's
next due date (searchable by serial, customer and model), one instrument's page (every calibration
across the lab's benches, each certificate revision with its documents, each coefficient ± U over
time with drift flagged), and what falls due; pure reads.

Every rule is the command line's: the search is `labcal instrument list --search`'s, the due dates
and the suggested interval are `labcal instrument show`'s and `labcal due`'s (`labcal.app.instruments`:
the last real calibration + the interval, ILAC-G24 method 1 for the suggestion), the drift flags are
`labcal history`'s (`labcal.app.histories.instrument_history`: a change larger than the combined
expanded uncertainty). A dry run's certificate is listed on the instrument's page, marked, but never
makes an instrument current. The coefficients' plot is `labcal history --plot`'s figure.
"""

from __future__ import annotations

import tempfile
import threading
from dataclasses import dataclass
from datetime import date
from functools import lru_cache
from pathlib import Path

from labcal.app import instruments
from labcal.app.desk import approval_of, documents_of, parsed_certificate
from labcal.app.histories import History, InstrumentHistory, instrument_history
from labcal.app.labdatabase import LabDatabase
from labcal.errors import LabcalError
from labcal.store import lab_certificates, lab_view
from labcal.store.instruments import Instrument

SOON_DAYS = 30  # the register marks an instrument due within this many days
SEARCH_MAX = 100  # the longest search the register takes (a serial is at most 64 characters)


def location(lab: LabDatabase) -> str:
    """The lab database as the history's readers take it (a SQLite path or the server's URL)."""
    return str(lab.file) if lab.server is None else lab.server.url


@dataclass(frozen=True)
class RegisterRow:
    instrument: Instrument
    last: date | None  # the last real calibration
    next_due: date | None  # None: no interval set
    days_left: int | None

    @property
    def state(self) -> str:
        """overdue, due (within `SOON_DAYS`), current, no interval, or the register's status."""
        if self.instrument.status != "active":
            return self.instrument.status
        if self.days_left is None:
            return "no interval"
        return "overdue" if self.days_left < 0 else "due" if self.days_left <= SOON_DAYS else "current"


def register(lab: LabDatabase, search: str | None, today: date) -> list[RegisterRow]:
    """The register (or the instruments whose serial, customer or model holds ``search``), by serial,
    each with its last calibration and next due date as `labcal instrument show` states them."""
    db = location(lab)
    found = []
    for i in instruments.listed(lab, search):
        history = instruments.calibrations(i.serial, db)
        due = instruments.next_due(i.interval_days, history, today)
        found.append(RegisterRow(i, history[-1].on if history else None, due,
                                 None if due is None else (due - today).days))
    return found


def due(lab: LabDatabase, within: str, today: date) -> list[instruments.Due]:
    """`labcal due --within`: the active instruments overdue or due within ``within``, soonest first."""
    return instruments.due(lab, location(lab), within, today)


@dataclass(frozen=True)
class Calibrated:
    """One certificate revision of the instrument, as its page lists it."""

    certificate_id: str
    number: str
    calibrated_utc: str
    issued_utc: str
    run_id: int | None  # the lab's run number (None: a run the lab database does not hold)
    bench: str | None  # the bench (station) that measured it
    device: str  # the calibration device as the certificate describes it
    model: str  # linear or device
    simulated: bool
    verdict: bool | None  # the conformity verdict (None: no tolerance given)
    approval: dict | None
    replaced: bool
    documents: tuple[str, ...]


@dataclass(frozen=True)
class InstrumentPage:
    card: instruments.Card
    calibrations: tuple[Calibrated, ...]  # every revision, newest calibration first
    history: History | None  # the coefficients over time (None: no real calibration yet)
    why_no_history: str | None


def instrument_page(lab: LabDatabase, serial: str, today: date) -> InstrumentPage:
    """One instrument (one line if it is not registered): its card, every certificate revision the lab
    holds for it across benches, and its coefficients over its real calibrations."""
    db = location(lab)
    card = instruments.card(lab, serial, db, today)
    registered = card.instrument.serial
    listed = []
    with lab.engine.connect() as conn:
        rows = lab_certificates.serial_documents(conn, registered)  # in any case
        certs = [c for c in (parsed_certificate(d, f"certificate {cid}") for cid, d in rows) if c is not None]
        replaced = {c.replaces for c in certs if c.replaces}
        for c in sorted(certs, key=lambda c: (c.calibrated_utc, c.issued_utc), reverse=True):
            uuid = c.data.journal.run_uuid if c.data.journal is not None else None
            run = None if uuid is None else lab_view.run_place(conn, uuid=uuid)
            run_id, bench, run_dir = (None, None, None) if run is None else (run.id, run.station, run.run_dir)
            listed.append(Calibrated(
                c.certificate_id, c.number, c.calibrated_utc.isoformat(), c.issued_utc.isoformat(), run_id,
                bench, c.station.description, c.fit.model, c.station.simulated,
                None if c.conformity is None else c.conformity.passed, approval_of(c), c.number in replaced,
                documents_of(conn, c, run_dir)))
    try:
        history, why = instrument_history(InstrumentHistory(registered, db)), None
    except LabcalError as exc:
        history, why = None, str(exc)
    return InstrumentPage(card, tuple(listed), history, why)



_DRAWING = threading.Lock()  # one plot drawn at a time: the others wait, then find theirs drawn


def coefficients_png(lab: LabDatabase, serial: str) -> bytes | None:
    """PNG of each coefficient ± U over the instrument's real calibrations, a change beyond the combined
    expanded uncertainty in red (`labcal history --plot`'s figure); None: not registered, or no real
    calibration. Drawn once per set of certificates (a figure costs about half a second of CPU)."""
    db = location(lab)
    try:
        registered = instruments.registered(lab, serial).serial
        history = instrument_history(InstrumentHistory(registered, db))
    except LabcalError:
        return None
    digests = tuple(c["digest"] for c in history.document["calibrations"])
    with _DRAWING:
        return _drawn(db, registered, digests)


@lru_cache(maxsize=16)
def _drawn(db: str, serial: str, digests: tuple[str, ...]) -> bytes:
    """The plot of ``serial``'s history while its certificates are ``digests`` (the cache's key)."""
    with tempfile.TemporaryDirectory(prefix="labcal-plot-") as folder:
        path = Path(folder) / "coefficients.png"
        instrument_history(InstrumentHistory(serial, db, plot=str(path)))
        return path.read_bytes()

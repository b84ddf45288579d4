"""A certificate's number in the lab's own format (the lab file's ``[laboratory] certificate_number``,
`labcal.config.numbering`), from the lab's one gap-free sequence in the lab database
(`labcal.store.certificate_numbers`): a run's number is assigned once, when its certificate is first
issued, and kept by every reissue and revision.

Where the lab database is a server, the number comes from the server, so that every bench counts in one
sequence; a server out of reach gives none (the certificate then carries labcal's own identifier, and
`labcal report RUN` numbers it once the server answers): a sequence counted at a bench alone would
not be the lab's. A dry run (on the simulated rig or the emulators) is numbered in a sequence of its
own, prefixed SIMULATED-, so that the customers' sequence has no gap for it.
"""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

from labcal.config.lab import load_lab_config
from labcal.config.numbering import number, scope
from labcal.store import labdb
from labcal.store.certificate_numbers import assigned
from labcal.store.record import RunRecord

DRY_RUN_PREFIX = "SIMULATED-"


def lab_number(record: RunRecord, serial: str | None, db: str | Path | None) -> str | None:
    """The run's number in the lab's format (None: the lab sets no format, or its server is out of
    reach). ``db``: where the certificate's history is kept (a SQLite lab database), unless the lab
    database is a server."""
    lab = load_lab_config().laboratory
    uuid, started = record.meta.run_uuid, record.meta.started_utc
    if not lab.certificate_number or not uuid or not started:
        return None  # (a run without its start is refused by the certificate, in one line)
    year = datetime.fromisoformat(str(started)).year
    where = scope(lab.certificate_number, year)
    simulated = record.simulated
    if simulated:  # a sequence of its own: below every year's (and the single sequence, 0)
        where = -1 - where
    serial = serial or str(record.meta.instrument_serial or "SIMULATED")

    def make(seq: int) -> str:
        made = number(lab.certificate_number, lab.code, year, seq, serial)
        return DRY_RUN_PREFIX + made if simulated else made

    try:
        engine = labdb.lab_engine(None if labdb.lab_server(None) is not None else db)
    except labdb.Unreachable:
        return None
    try:
        return assigned(engine, str(uuid), where, make)
    finally:
        engine.dispose()

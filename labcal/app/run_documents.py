"""The documents of a finished run issued: its certificate, DCC, report and history entry, the use
case behind `labcal report` and the end of `labcal run` (`write_run_outputs`).

Building and rendering them is `labcal.documents.report`'s; this decides what is issued: which revision,
which fit, the Type B inputs of which station, and what an approved certificate keeps.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.app.numbering import lab_number
from labcal.config.settings import CertificateSettings
from labcal.documents.administration import ItemGiven
from labcal.documents.certificate import Certificate, read_certificate
from labcal.documents.issuing import build_certificate, changed_fields, identification, kept_identification
from labcal.documents.report import CERTIFICATE, RunOutputs, fitted, replaced_by, write_documents, write_file
from labcal.documents.uncertainty import bench_section, type_b_inputs
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.record import RunRecord, load_run

if TYPE_CHECKING:
    from labcal.documents import device_history
else:
    device_history = lazy("labcal.documents.device_history")  # start-up without scipy, numpy, pydantic


def write_run_outputs(run_dir: str | Path, settings: CertificateSettings | None = None, *,
                      serial: str | None = None, operator: str | None = None,
                      db: str | Path | None = None, station: str | Path | None = None,
                      monte_carlo: int = 0, item: ItemGiven | None = None,
                      record: RunRecord | None = None) -> RunOutputs:
    """Certificate, report and history entry of a finished run (called at the end of `labcal run`
    and by `labcal report`); ``db`` None means $LABCAL_DB or the lab file's database. The Type B
    inputs come from ``station`` (a station file), else the station the run was journaled with;
    ``monte_carlo`` trials check the budget by JCGM 101. ``record``: the run as `load_run` read it
    just before (the end of a run: read once for the device's estimate and for this, not fitted twice)."""
    record = record or load_run(run_dir)
    fit, device, model_note = fitted(record)
    if device is None:  # a plan that corrects for the device: not from a correction the run saw move
        device_history.refuse_if_moved(record, fit)
    section = bench_section(record, station)
    inputs = type_b_inputs(section, record, device)
    revision, replaced = 1, None
    previous = _issued(record.directory / CERTIFICATE)
    if previous is not None and previous.approval is not None:
        # An approved certificate is never changed: what follows is a correction, a new revision
        # naming the one it replaces; the approved one stays beside it and in the history.
        revision, replaced = (previous.revision or 1) + 1, previous
        write_file(record.directory / f"certificate.rev{previous.revision or 1}.json", previous)
    elif previous is not None and (previous.revision or 1) > 1:
        # a revision's draft reported again is still that revision, replacing the same approved one
        revision, replaced = previous.revision or 1, replaced_by(record.directory, previous)
    item, serial, operator = kept_identification(previous, item or ItemGiven(), serial, operator)
    number = (previous.lab_number if previous is not None and previous.lab_number else
              lab_number(record, serial, db))  # a run keeps its number through reissues and revisions
    cert = build_certificate(record, fit, settings, serial=serial, operator=operator, inputs=inputs,
                             monte_carlo=monte_carlo, revision=revision,
                             replaces=None if replaced is None else replaced.number, section=section,
                             item=item, device=device, model_note=model_note, replaced=replaced,
                             lab_number=number)
    outputs = write_documents(cert, record, fit, device, db)
    if previous is None:
        return outputs
    return replace(outputs, compared_with=previous.number,
                   changes=tuple(changed_fields(identification(previous), identification(cert))))


def _issued(path: Path) -> Certificate | None:
    """The certificate already in the run directory, if one is there and reads back intact."""
    if not path.is_file():
        return None
    try:
        return read_certificate(path)
    except LabcalError:
        return None  # a damaged draft is replaced; an approved one would have read back

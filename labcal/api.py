"""labcal from Python: the use cases the command line runs, as functions with keyword arguments.

    import labcal.api as labcal

    finished = labcal.run(sim=True, plan="one-mount-16", seed=1, out="runs")
    certificate = labcal.read_certificate(finished.run_dir / "certificate.json")

A run started here has nobody at the station (`labcal.app.unattended.Unattended`): remounts are
taken as done, a pause stops the run where it is (it resumes later), an unmet checklist item
refuses it before anything moves; what a technician would read goes to the ``labcal.run`` logger and
to ``say``. Every refusal is a `LabcalError` (the command line prints its message as one line); one that asks
for a value names the keyword argument (``serial=``), and its ``options`` list those names. The
options are the command line's, by the same names (`labcal run --help`); each function returns the
use case's typed result.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any, ParamSpec, TypeVar

from labcal.app.calibration import (
    AlreadyComplete,
    Ended,
    Estimated,
    Finished,
    ResumeRun,
    StartRun,
    resume_run,
    start_run,
)
from labcal.app.certificates import (
    ApproveCertificate,
    Approved,
    IssueCertificate,
    Issued,
    Verified,
    VerifyCertificate,
    approve_certificate,
    issue_certificate,
    read_certificate,
    verify_certificate,
)
from labcal.app.runs import ListRuns, ReadLog, RunList, RunLog, list_runs, read_log
from labcal.app.unattended import Unattended
from labcal.errors import LabcalError

__all__ = [
    "AlreadyComplete", "Approved", "Ended", "Estimated", "Finished", "Issued", "LabcalError", "RunList",
    "RunLog", "Unattended", "Verified", "approve", "issue", "list_runs_of", "open_run", "read_certificate",
    "resume", "run", "verify",
]

Say = Callable[[str], None]
P = ParamSpec("P")
R = TypeVar("R")


def _python_spelling(use_case: Callable[P, R]) -> Callable[P, R]:
    """A refusal names the keyword argument to give (``serial=``), not the command line's option."""
    @functools.wraps(use_case)
    def call(*args: P.args, **kwargs: P.kwargs) -> R:
        try:
            return use_case(*args, **kwargs)
        except LabcalError as exc:
            raise exc.spelled("python") from None
    return call


@_python_spelling
def run(*, say: Say | None = None, **options: Any) -> Finished | Ended | Estimated:
    """A calibration: ``run(sim=True)`` on the simulated rig, ``run(station="bench.toml")`` on a
    station's devices (``emulate=True``: on their emulators); ``dry_run=True`` only estimates it.
    ``options`` are `labcal.app.calibration.StartRun`'s fields (`labcal run`'s options)."""
    request = StartRun(**options)
    return start_run(request, Unattended(say, request.db, request.out))


@_python_spelling
def resume(run_dir: str | Path, *, say: Say | None = None,
           **options: Any) -> Finished | Ended | AlreadyComplete:
    """An interrupted run continued at its first missing point (`labcal resume`)."""
    request = ResumeRun(str(run_dir), **options)
    return resume_run(request, Unattended(say, request.db))


@_python_spelling
def open_run(run: str | int | Path, db: str | None = None) -> RunLog:
    """A run by its id or its folder: what it is, how it ended, and its journaled events. A read."""
    return read_log(ReadLog(str(run), db))


@_python_spelling
def list_runs_of(serial: str | None = None, db: str | None = None, statuses: tuple[str, ...] = ()) -> RunList:
    """The lab's runs, newest first, optionally of one instrument or in some statuses. A read."""
    return list_runs(ListRuns(db, serial, statuses))


@_python_spelling
def issue(run_dir: str | Path, **options: Any) -> Issued:
    """A complete run's certificate, report and DCC written (again), as `labcal report` does;
    ``options`` are `labcal.app.certificates.IssueCertificate`'s fields."""
    return issue_certificate(IssueCertificate(str(run_dir), **options))


@_python_spelling
def approve(run_dir: str | Path, *, by: str, role: str, key: str | Path, db: str | None = None,
            station: str | None = None) -> Approved:
    """Sign the run's certificate with an approver's registered key (`labcal certificate approve`)."""
    return approve_certificate(ApproveCertificate(str(run_dir), by, role, str(key), db, station))


@_python_spelling
def verify(certificate: str | Path, *, public_key: str | Path | None = None,
           db: str | None = None) -> Verified:
    """Check an approved certificate's signature against the lab's register of approvers (or a
    given public key), and its DCC's digest. A read."""
    key = None if public_key is None else str(public_key)
    return verify_certificate(VerifyCertificate(str(certificate), key, None, db))

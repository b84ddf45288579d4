"""Make tests/data/certificates/: certificate.json files as labcal wrote them before the certificate's
sections were typed (commit f6969bc), so that the typed model is tested against documents
it did not write. Not run by the tests; run by hand, once, from the repository root, with that
labcal installed in .venv:

    .venv/bin/python tests/data/certificates/make_certificates.py

It writes:

- ``simulated.json``: ``labcal run --sim --yes`` (four-mount-64, the device model; a dry run's
  notice, its simulated truth and sequencer settings);
- ``replicated.json``: ``labcal run --sim --yes --plan one-mount-16 --replicates 3 --tolerance-deg 0.5
  --monte-carlo``-free: the linear model with its replication analysis and a statement of conformity;
- ``approved.json``: a one-mount run on the emulated bench (`tests/simulated_runs.bench_run`, no
  simulated truth: it may be approved) approved with a fresh key (``approver.pub`` is its public key);
- ``reissued.json`` and ``reissued.rev1.json``: that approved run reported again with a customer:
  revision 2, replacing the approved one kept beside it.

The v0 certificate (labcal a8863ee) is in ``tests/data/v0/labcal.sqlite``.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))  # tests/, for simulated_runs and emulators

from simulated_runs import bench_run  # noqa: E402

from labcal.cli import main  # noqa: E402


def run(*args: str) -> None:
    assert main(list(args)) == 0, args


def make() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp)
        os.environ["LABCAL_DB"] = str(base / "lab.sqlite")
        run("run", "--sim", "--yes", "--out", str(base / "sim"), "--db", str(base / "lab.sqlite"))
        shutil.copy(base / "sim" / "certificate.json", HERE / "simulated.json")
        run("run", "--sim", "--yes", "--plan", "one-mount-16", "--replicates", "3", "--tolerance-deg", "0.5",
            "--out", str(base / "rep"), "--db", str(base / "lab.sqlite"))
        shutil.copy(base / "rep" / "certificate.json", HERE / "replicated.json")
        run_dir = bench_run(base / "run", base / "lab.sqlite", "AX-2041")
        run("certificate", "keygen", "--out", str(base / "approver"))
        run("certificate", "approvers", "add", "A. Metrologist", "--role", "Technical manager",
            "--public-key", str(base / "approver.pub"), "--db", str(base / "lab.sqlite"))
        run("certificate", "approve", str(run_dir), "--by", "A. Metrologist", "--role", "Technical manager",
            "--key", str(base / "approver.key"), "--db", str(base / "lab.sqlite"))
        shutil.copy(run_dir / "certificate.json", HERE / "approved.json")
        shutil.copy(base / "approver.pub", HERE / "approver.pub")
        run("report", str(run_dir), "--customer", "ACME Surveying", "--db", str(base / "lab.sqlite"))
        shutil.copy(run_dir / "certificate.json", HERE / "reissued.json")
        shutil.copy(run_dir / "certificate.rev1.json", HERE / "reissued.rev1.json")


if __name__ == "__main__":
    make()

"""An approved certificate's DCC, as the approver's desk gives it, is the one the approval signed: a
run folder's certificate.dcc.xml edited after the approval is not served (its SHA-256 is not the
approval's ``dcc_sha256``); the DCC written anew from the certificate, which the approval's digest
binds, is. The run is measured through the real drivers and approved at its bench with a
registered key; the digest is checked here with hashlib against the approval as the certificate
file states it."""

from __future__ import annotations

import hashlib
import json

import pytest
from simulated_runs import bench_run

from labcal.app.desk import certificate_document
from labcal.app.labdatabase import OpenLab, open_lab
from labcal.cli import main

pytestmark = pytest.mark.slow  # a run through the drivers: about 15 s

DCC = "certificate.dcc.xml"


def test_a_dcc_edited_after_approval_is_not_what_the_desk_serves(tmp_path):
    db = tmp_path / "lab.sqlite"
    run = bench_run(tmp_path / "run", db, "ACC-0042")
    assert main(["certificate", "keygen", "--out", str(tmp_path / "ada")]) == 0
    assert main(["certificate", "approvers", "add", "ada", "--role", "approver", "--public-key",
                 str(tmp_path / "ada.pub"), "--db", str(db)]) == 0
    assert main(["certificate", "approve", str(run), "--by", "ada", "--role", "approver", "--key",
                 str(tmp_path / "ada.key"), "--db", str(db)]) == 0
    approved = json.loads((run / "certificate.json").read_text())
    signed = approved["approval"]["dcc_sha256"]
    assert hashlib.sha256((run / DCC).read_bytes()).hexdigest() == signed  # as approved, untouched
    edited = (run / DCC).read_bytes().replace(b"</", b"<!-- edited after approval --></", 1)
    (run / DCC).write_bytes(edited)

    lab = open_lab(OpenLab(str(db)))
    try:
        found = certificate_document(lab, approved["certificate_id"], DCC)
    finally:
        lab.close()
    assert found is not None
    media, content = found
    assert media == "application/xml" and content != edited
    assert hashlib.sha256(content).hexdigest() == signed

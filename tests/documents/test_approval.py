"""Approval with a real signature: keygen, approve, verify; a forgery with a recomputed digest is
refused; DRAFT and "page X of Y" on every PDF page; a correction is a new revision and history
keeps both."""

from __future__ import annotations

import json
import os
import re
import shutil
import sqlite3
import stat
from pathlib import Path

import pytest
from pypdf import PdfReader
from simulated_runs import bench_run

from labcal.app.run_documents import write_run_outputs
from labcal.cli import main
from labcal.documents.certificate import certificate_from_doc, content_digest, read_certificate

SERIAL = "ACC-0042"  # the bench run's instrument


def _pdf_pages(run, pdf: Path) -> list[str]:
    """The text of every page of the report's PDF once ``run`` has written it, as a PDF reader
    (pypdf, not labcal's writer) extracts it through the font's ToUnicode map."""
    run()
    return [page.extract_text() for page in PdfReader(pdf).pages]


def _approve(base, key: str = "approver.key") -> list[str]:
    return ["certificate", "approve", str(base / "run"), "--by", "A. Metrologist", "--role",
            "Technical manager", "--key", str(base / key), "--db", str(base / "lab.sqlite")]


@pytest.fixture(scope="module")
def issued(tmp_path_factory):
    """A run on a bench (a dry run is never approved), its draft certificate (the PDF's pages kept),
    and a key pair registered to the approver."""
    base = tmp_path_factory.mktemp("approval")
    run_dir = bench_run(base / "run", base / "lab.sqlite", SERIAL, report=False)  # one mount; issued below
    pages = _pdf_pages(lambda: write_run_outputs(run_dir, db=base / "lab.sqlite"), run_dir / "report.pdf")
    assert main(["certificate", "keygen", "--out", str(base / "approver")]) == 0
    assert main(["certificate", "approvers", "add", "A. Metrologist", "--role", "Technical manager",
                 "--public-key", str(base / "approver.pub"), "--db", str(base / "lab.sqlite")]) == 0
    return base, pages


@pytest.fixture(scope="module")
def approved(issued, tmp_path_factory):
    """A copy of the issued run, approved (the PDF's pages kept)."""
    base = tmp_path_factory.mktemp("approved") / "lab"
    shutil.copytree(issued[0], base)
    pages = _pdf_pages(lambda: main(_approve(base)), base / "run" / "report.pdf")
    return base, pages


def _one_line(capsys, *args: str) -> str:
    assert main(list(args)) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and len(captured.err.strip().splitlines()) == 1
    return captured.err


def test_keygen_makes_a_private_key_only_its_owner_reads(issued, capsys):
    base, _ = issued
    assert stat.S_IMODE((base / "approver.key").stat().st_mode) == 0o600
    assert "already exists" in _one_line(capsys, "certificate", "keygen", "--out", str(base / "approver"))


def test_approved_certificate_verifies_and_a_forgery_does_not(approved, tmp_path, capsys):
    base, _ = approved
    cert_path = base / "run" / "certificate.json"
    assert main(["certificate", "verify", str(cert_path), "--public-key", str(base / "approver.pub")]) == 0
    assert "signature valid" in " ".join(capsys.readouterr().out.split())
    # A forger edits a value and recomputes the digest: the seal is satisfied, the signature is not.
    doc = json.loads(cert_path.read_text())
    doc["fit"]["coefficients"][0][0] += 1e-6
    doc["digest"]["value"] = content_digest(doc)
    certificate_from_doc(doc, "forged")  # the SHA-256 seal alone would accept it
    forged = tmp_path / "forged.json"
    forged.write_text(json.dumps(doc))
    err = _one_line(capsys, "certificate", "verify", str(forged), "--public-key", str(base / "approver.pub"))
    assert "signature does not match the content" in err
    doc = json.loads(cert_path.read_text())  # the approver's name is signed too
    doc["approval"]["by"] = "Someone Else"
    doc["digest"]["value"] = content_digest(doc)
    forged.write_text(json.dumps(doc))
    err = _one_line(capsys, "certificate", "verify", str(forged), "--public-key", str(base / "approver.pub"))
    assert "signature does not match" in err
    assert main(["certificate", "keygen", "--out", str(tmp_path / "other")]) == 0
    capsys.readouterr()
    err = _one_line(capsys, "certificate", "verify", str(cert_path), "--public-key",
                    str(tmp_path / "other.pub"))
    assert "signed by another key" in err
    assert "already approved" in _one_line(capsys, *_approve(base))


def test_bad_keys_are_one_line_and_change_nothing(issued, tmp_path, capsys):
    base = tmp_path / "lab"
    shutil.copytree(issued[0], base)
    cert_path = base / "run" / "certificate.json"
    before = cert_path.read_bytes()
    assert "no such private key file" in _one_line(capsys, *_approve(base, "missing.key"))
    os.chmod(base / "approver.key", 0o644)
    assert "let others read the private key" in _one_line(capsys, *_approve(base))
    (base / "approver.key").write_text("not a key")
    os.chmod(base / "approver.key", 0o600)
    assert "not an unencrypted PEM private key" in _one_line(capsys, *_approve(base))
    assert cert_path.read_bytes() == before
    pub = str(base / "approver.pub")
    err = _one_line(capsys, "certificate", "verify", str(cert_path), "--public-key", pub)
    assert "not approved (a DRAFT)" in err


def test_every_pdf_page_says_page_x_of_y_and_draft_until_approved(issued, approved):
    draft, signed = issued[1], approved[1]
    assert len(draft) >= 5 and len(signed) == len(draft)  # text pages, then the four figures
    for n, (d, a) in enumerate(zip(draft, signed, strict=True), start=1):
        assert f"page {n} of {len(draft)}" in d and "DRAFT" in d
        assert f"page {n} of {len(draft)}" in a and "DRAFT" not in a and "approved by A. Metrologist" in a


def test_a_correction_is_a_new_revision_and_history_keeps_both(approved, tmp_path, capsys):
    base = tmp_path / "lab"
    shutil.copytree(approved[0], base)
    first = read_certificate(base / "run" / "certificate.json")
    assert main(["report", str(base / "run"), "--db", str(base / "lab.sqlite"), "--json"]) == 0
    second = read_certificate(base / "run" / "certificate.json")
    assert second.revision == 2 and second.replaces == first.number and second.draft
    assert re.fullmatch(r".+-R2", second.certificate_id)
    assert read_certificate(base / "run" / "certificate.rev1.json") == first  # the approved one, kept
    with sqlite3.connect(base / "lab.sqlite") as conn:
        ids = {cid for (cid,) in conn.execute("SELECT certificate_id FROM certificates")}
    assert {first.certificate_id, second.certificate_id} <= ids
    capsys.readouterr()
    assert main(["history", SERIAL, "--db", str(base / "lab.sqlite"), "--json"]) == 0
    listed = [c["certificate_id"] for c in json.loads(capsys.readouterr().out)["calibrations"]]
    assert second.certificate_id in listed and first.certificate_id not in listed  # superseded


def test_administrative_contents_come_from_the_lab_file_station_file_and_command_line(issued, tmp_path,
                                                                                       monkeypatch):
    from datetime import date

    from labcal.analysis.fit import fit_readings
    from labcal.config.station import load_certificate_section, shipped_stations
    from labcal.documents.administration import ItemGiven
    from labcal.documents.issuing import build_certificate
    from labcal.store.record import load_run

    lab_file = tmp_path / "lab.toml"
    lab_file.write_text('[laboratory]\nname = "Example Lab"\naddress = "1 Metrology Way"\n'
                        'accreditation_id = "UKAS 0000"\n')
    monkeypatch.setenv("LABCAL_CONFIG", str(lab_file))
    station = tmp_path / "station.toml"
    station.write_text(shipped_stations()["lab-example"].read_text().replace("due = 2027-06-30",
                                                                             "due = 2020-01-01"))
    record = load_run(issued[0] / "run")
    cert = build_certificate(record, fit_readings(record.readings), section=load_certificate_section(station),
                             item=ItemGiven("ACME Ltd", "Acme", "AX-3", date(2026, 11, 20)))
    a = cert.administration
    assert a.laboratory.accreditation_id == "UKAS 0000" and a.customer == "ACME Ltd"
    assert a.item.model == "AX-3" and a.item.received == date(2026, 11, 20) and a.item.serial == SERIAL
    assert [t.certificate for t in a.traceability] == ["CAL-2026-0193", "ANG-2026-0041"]
    # said as the PDF's first page and `labcal station check` say it (one function)
    day = cert.calibrated_utc.date()  # dates as people write them (%B: the C locale's English month)
    calibrated = f"{day.day} {day:%B %Y}"
    assert ("Reference standard DMM (34972A) (Keysight 34972A, serial MY00000000, certificate CAL-2026-0193) "
            f"was overdue for calibration: due 1 January 2020, used {calibrated}.") in cert.statements
    assert not any("ANG-2026-0041" in s for s in cert.statements)  # due 2027-03-31: in date
    assert "The results relate only to the item calibrated." in cert.statements
    assert cert.number.endswith("rev. 1") and cert.draft


DATA = Path(__file__).parent.parent / "data" / "dcc"


def test_dcc_validates_against_ptb_schema_and_a_broken_copy_does_not(issued):
    import xml.etree.ElementTree as ET

    import xmlschema

    schema = xmlschema.XMLSchema(str(DATA / "dcc.xsd"))  # the vendored reference copy, not labcal's
    path = issued[0] / "run" / "certificate.dcc.xml"
    schema.validate(str(path))
    tree = ET.parse(path)
    text = path.read_text(encoding="utf-8")
    cert = read_certificate(issued[0] / "run" / "certificate.json")
    assert cert.number in text and "\\volt" in text and "<si:covarianceMatrix>" in text
    reals = tree.getroot().findall(".//{https://ptb.de/si}real/{https://ptb.de/si}expandedUnc")
    assert len(reals) == 12  # every coefficient with U, k and p
    core = tree.getroot().find(".//{https://ptb.de/dcc}coreData")
    core.remove(core.find("{https://ptb.de/dcc}uniqueIdentifier"))  # a required element
    broken = ET.tostring(tree.getroot(), encoding="unicode")
    assert not schema.is_valid(broken)


@pytest.mark.parametrize("edit", [
    (b"<dcc:uniqueIdentifier>", b"<dcc:uniqueId>", b"</dcc:uniqueIdentifier>", b"</dcc:uniqueId>"),  # renamed
    (b"<si:value>", b"<si:value>x"),  # not a decimal
    (b"<si:coverageProbability>0.95", b"<si:coverageProbability>1.5"),  # not a probability
    (b"<dcc:issueDate>", b"<dcc:issueDate>x"),  # not a date
    (),  # as issued: valid
])
def test_labcals_validator_agrees_with_the_reference_validator(issued, edit):
    """labcal validates with libxml2 (lxml) against its shipped schema; xmlschema against the tests'
    copy is the reference: both accept the issued DCC and both refuse every broken copy."""
    import xmlschema

    from labcal.documents.dcc import validation_error

    document = (issued[0] / "run" / "certificate.dcc.xml").read_bytes()
    for old, new in zip(edit[::2], edit[1::2], strict=True):
        document = document.replace(old, new, 1)
    reference = xmlschema.XMLSchema(str(DATA / "dcc.xsd")).is_valid(document.decode("utf-8"))
    assert reference == (not edit)
    assert (validation_error(document) is None) == reference


def test_a_dcc_that_fails_validation_is_one_line_and_writes_nothing(issued, tmp_path, monkeypatch, capsys):
    from labcal.documents import dcc

    base = tmp_path / "lab"
    shutil.copytree(issued[0], base)
    before = {p.name: p.read_bytes() for p in (base / "run").iterdir() if p.is_file()}
    monkeypatch.setattr(dcc, "dcc_document",
                        lambda cert: b'<dcc:digitalCalibrationCertificate xmlns:dcc="https://ptb.de/dcc" '
                                     b'schemaVersion="3.2.0"/>')
    err = _one_line(capsys, "report", str(base / "run"), "--db", str(base / "lab.sqlite"))
    assert "fails PTB's DCC 3.2.0 schema" in err
    assert {p.name: p.read_bytes() for p in (base / "run").iterdir() if p.is_file()} == before


def test_the_journal_story_is_in_the_certificate_and_the_report(issued, tmp_path):
    from labcal.analysis.fit import fit_readings
    from labcal.documents.issuing import build_certificate
    from labcal.documents.report_tables import story_table
    from labcal.store.journal import Journal
    from labcal.store.record import load_run
    from labcal.store.rundir import read_run_json

    base = tmp_path / "lab"
    shutil.copytree(issued[0], base)
    info = read_run_json(base / "run")
    with Journal(info["journal"].replace(str(issued[0]), str(base))) as journal:
        journal.event(info["run_id"], "fault", "wrong mount: expected y=180°, u=0°, reads as y=0°, u=0°",
                      station_time=12.5)
        journal.event(info["run_id"], "pause", "operator paused", station_time=13.0)
        journal.event(info["run_id"], "resume", "operator resumed after the pause", station_time=40.0)
    (base / "run" / "run.json").write_text(json.dumps({**info, "journal": str(base / "lab.sqlite")}))
    record = load_run(base / "run")
    cert = build_certificate(record, fit_readings(record.readings))
    story = cert.story
    assert story.counts["fault"] == 1 and story.counts["pause"] == 1 and story.counts["resume"] == 1
    assert story.counts.get("prompt", 0) == story.counts.get("answer", 0) > 0  # the remount prompts, answered
    table = story_table(cert)
    fault = next(i for i, row in enumerate(table.rows) if row[2] == "fault")
    assert table.rows[fault][1] == "12.5" and "wrong mount" in table.rows[fault][3]
    assert (fault, 2) in table.emphasis and "1 fault" in table.caption


def test_monte_carlo_trials_out_of_range_is_one_line(issued, capsys):
    err = _one_line(capsys, "report", str(issued[0] / "run"), "--monte-carlo", "5")
    assert "--monte-carlo 5: give 100 … 1000000 trials" in err


def test_the_stated_attitude_u95_is_the_monte_carlo_one_where_they_disagree(issued):
    from labcal.documents.certificate import MonteCarloCheck
    from labcal.documents.uncertainty import stated_U95_arcsec

    budget = read_certificate(issued[0] / "run" / "certificate.json").uncertainty_budget
    linear = next(t for t in budget.totals if t.angle == "roll")
    assert stated_U95_arcsec(budget, "roll") == linear.U95_arcsec  # no Monte Carlo asked for
    check = MonteCarloCheck(trials=1000, seed=0, angle="roll", at_deg=linear.worst_at_deg,
                            linear_U95_arcsec=linear.U95_arcsec,
                            monte_carlo_U95_arcsec=1.1 * linear.U95_arcsec, agree_within_5_percent=False)
    disagreeing = budget.model_copy(update={"monte_carlo": [check]})
    assert stated_U95_arcsec(disagreeing, "roll") == pytest.approx(1.1 * linear.U95_arcsec)


def _report(base, *extra: str) -> dict:
    """`labcal report` of the run in ``base`` with --json, its summary."""
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["report", str(base / "run"), "--db", str(base / "lab.sqlite"), "--json", *extra]) == 0
    return json.loads(buf.getvalue())


ITEM = ("--customer", "ACME Ltd", "--manufacturer", "Acme", "--model", "AX-3", "--received", "2026-01-15")


def test_a_reissue_keeps_the_identification_unless_told_and_says_what_changed(approved, tmp_path, capsys):
    """Issue with the item's details, re-report the draft without them: kept; approve, re-issue
    without them: the revision keeps them too; re-issue with a new customer: that one field
    changes and both the certificate and the command's output name it (old → new)."""
    from datetime import date

    base = tmp_path / "lab"
    shutil.copytree(approved[0], base)
    (base / "run" / "certificate.json").unlink()  # start again from a first draft with the item given
    first = _report(base, *ITEM)
    assert first["compared_with"] is None
    again = _report(base)  # a draft reported again, nothing repeated
    draft = read_certificate(base / "run" / "certificate.json")
    a = draft.administration
    assert (a.customer, a.item.manufacturer, a.item.model, a.item.received) == \
        ("ACME Ltd", "Acme", "AX-3", date(2026, 1, 15))
    assert again["identification_changed"] == [] and draft.revision == 1 and draft.replaces is None
    capsys.readouterr()
    assert main(_approve(base)) == 0
    approved_one = read_certificate(base / "run" / "certificate.json")
    revision = _report(base)  # the re-issue of an approved certificate, nothing repeated
    second = read_certificate(base / "run" / "certificate.json")
    a = second.administration
    assert second.revision == 2 and second.replaces == approved_one.number
    assert (a.customer, a.item.manufacturer, a.item.model, a.item.received) == \
        ("ACME Ltd", "Acme", "AX-3", date(2026, 1, 15))
    assert revision["identification_changed"] == []
    assert f"This revision replaces certificate {approved_one.number}; its identification is unchanged." \
        in second.statements
    capsys.readouterr()
    assert main(["report", str(base / "run"), "--db", str(base / "lab.sqlite"), "--customer",
                 "Beta GmbH"]) == 0
    printed = capsys.readouterr().out
    third = read_certificate(base / "run" / "certificate.json")
    assert third.revision == 2 and third.replaces == approved_one.number  # still the same revision's draft
    assert third.administration.customer == "Beta GmbH" and third.administration.item.model == "AX-3"
    assert ("identification changed: customer ('ACME Ltd' → 'Beta GmbH')." in
            " ".join(third.statements))
    assert "Identification changed from" in printed and "customer ('ACME Ltd' → 'Beta GmbH')" in \
        " ".join(printed.split())
    assert not any("manufacturer (" in s or "model (" in s for s in third.statements)
    # the revision draft with its statement is what the journal gives: it can be approved
    capsys.readouterr()
    assert main(_approve(base)) == 0


def test_the_residual_page_names_the_linear_model_and_each_sensors_rms(issued):
    """The bench run's certificate rests on the linear model (one mount: the device is not
    identified): its residual figure's heading, in the HTML and on its PDF page, names that model and
    each sensor's residual RMS, computed here from the readings and the certified coefficients with
    gravity by hand on the top-forward mount, g = [sin p, cos p sin r, cos p cos r] (Soto §2)."""
    import html

    import numpy as np

    from labcal.store.record import load_run

    base, pages = issued
    cert = read_certificate(base / "run" / "certificate.json")
    assert cert.device is None and cert.fit.model == "linear"
    r = load_run(base / "run").readings
    assert not np.any(r.y_deg % 360) and not np.any(r.u_deg % 360)  # top-forward only
    p, q = np.radians(r.pitch_deg), np.radians(r.roll_deg)
    g = np.column_stack([np.sin(p), np.cos(p) * np.sin(q), np.cos(p) * np.cos(q)])
    X = np.array(cert.fit.coefficients)
    rms = np.sqrt(np.mean((r.volts - X[0] - g @ X[1:]) ** 2, axis=0))
    assert np.all((rms > 1e-7) & (rms < 1e-3))  # microvolts: stated in µV
    stated = ", ".join(f"{s} {v * 1e6:.3g} µV" for s, v in zip("xyz", rms, strict=True))
    text = (base / "run" / "report.html").read_text(encoding="utf-8")
    [heading] = re.findall(r"<h2>(Residuals per sensor of the [^<]*)</h2>", text)
    heading = html.unescape(heading)
    assert heading.startswith("Residuals per sensor of the linear model (V = B + gᵀS")
    assert heading.endswith(f"residual RMS {stated}")
    pdf = " ".join(" ".join(page.split()) for page in pages)
    assert "Residuals per sensor of the linear model" in pdf and stated in pdf

"""What the approver's desk says needs attention in a run: first what the run's journaled metadata
says (its checklist's overrides, in the checklist's order), then the faults journaled
during the run, a device correction used in place of remounts, and each conformity check that failed
(a passed check is not named); nothing for a clean run. The certificates are the stored test
certificate with a section set and sealed anew, as an issue would seal it."""

from __future__ import annotations

import json
from pathlib import Path

from labcal.app.desk import checklist_attention, needs_attention
from labcal.config.run_metadata import RunMetadata
from labcal.documents.certificate import seal
from labcal.store.journal import EventRow

STORED = Path(__file__).parent.parent / "data" / "certificates" / "simulated.json"
OVERRIDDEN = RunMetadata(checklist={"went_on_regardless": True, "items": [
    {"item": "warm-up", "status": "fail", "message": "warmed up 3 min of the 30 the station declares"},
    {"item": "DMM", "status": "ok", "message": "answers"}]})


def _certificate(**sections):
    doc = json.loads(STORED.read_text())
    doc.pop("digest")
    doc.update(sections)
    return seal(doc)


def test_a_clean_run_needs_nothing():
    assert needs_attention(RunMetadata(), [], _certificate()) == ()
    assert needs_attention(RunMetadata(), [], None) == ()  # no certificate issued yet


def test_the_command_lines_come_first_then_faults_correction_and_failed_checks():
    checks = [{"quantity": "pitch U95, largest over the usage envelope", "value": 0.02, "limit": 0.01,
               "unit": "°", "passed": False},
              {"quantity": "bias", "value": 0.001, "limit": 0.01, "unit": "V", "passed": True}]
    correction = {"device_id": "CD-1", "source": "run 7", "calibrated_utc": "2026-10-01T12:00:00+00:00",
                  "value_arcsec": dict.fromkeys("abdefk", 1.0), "U_arcsec": dict.fromkeys("abdefk", 0.5),
                  "u_arcsec": dict.fromkeys("abdefk", 0.25), "statement": "held at run 7's estimate"}
    cert = _certificate(conformity={"decision_rule": "simple acceptance", "checks": checks, "passed": False},
                        device_correction=correction)
    faults = ["DMM timeout", "pitch stalled", "roll stalled", "DMM garbled reply", "DMM timeout"]
    found = needs_attention(OVERRIDDEN, faults, cert)
    same = checklist_attention(OVERRIDDEN)
    assert same == ("went on regardless: warm-up: warmed up 3 min of the 30 the station declares",)
    assert found[:len(same)] == same
    assert found[len(same):] == (
        "5 fault(s) during the run: DMM timeout; pitch stalled; roll stalled; …",
        "a device correction was used in place of the remounts that identify the device",
        "out of tolerance: pitch U95, largest over the usage envelope 0.02 ° > 0.01 °")


def test_an_overdue_standard_a_resumed_run_went_on_under_needs_the_approvers_eye():
    """A resume journals its standard's override as an event, not in the run's metadata: the desk
    lists it as it lists one the run started under (the sentence the certificate states)."""
    held = {"serial": "DMM-1", "due_on": "2026-11-01", "valid_until": "2026-12-05", "approver": "Ann",
            "role": "approver", "reason": "recalibration booked", "key_id": "3013",
            "recorded_utc": "2026-11-20T09:00:00+00:00"}  # as `labcal.app.standards.override_json` writes it
    said = ("Override (reference standard) by Ann (approver): reference standard DMM-1 was overdue (due "
            "1 November 2026) and used under an override valid until 5 December 2026; reason: "
            "recalibration booked.")
    assert needs_attention(RunMetadata(), [], None) == ()
    resumed = EventRow("2026-11-20T09:00:01+00:00", 0.0, "standard_override", "resumed under an override",
                       held)
    assert needs_attention(RunMetadata(), [], None, [resumed]) == (said,)
    assert needs_attention(RunMetadata(standard_overrides=[held]), [], None) == (said,)

"""The typed certificate and its published JSON Schema.

Certificates written before the sections were typed (tests/data/certificates, by f6969bc's labcal;
tests/data/v0, by a8863ee's) must read back through the models to the very bytes they were issued
with: the digest and the Ed25519 signature are over the canonical JSON. The published schema
(schemas/certificate.schema.json) is checked against what the models generate, and real
certificates are validated against it with the `jsonschema` library — a second implementation of
the checks, not pydantic's.
"""

from __future__ import annotations

import base64
import copy
import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import jsonschema
import pytest
from cryptography.hazmat.primitives.serialization import load_pem_public_key

from labcal.cli import main
from labcal.documents.certificate import SCHEMA_FILE, json_schema, read_certificate, write_certificate
from labcal.documents.dcc import dcc_document
from labcal.errors import LabcalError

ROOT = Path(__file__).resolve().parents[2]
DATA = Path(__file__).parent.parent / "data"
ISSUED = DATA / "certificates"
WRITTEN_BEFORE = ("simulated", "replicated", "approved", "reissued", "reissued.rev1")


def canonical(doc: dict) -> bytes:
    """The canonical form the digest and the signature are over, written here from its definition
    (sorted keys, no spaces, UTF-8), not taken from labcal."""
    return json.dumps(doc, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode("utf-8")


def v0_certificate(tmp_path: Path) -> Path:
    """The certificate a8863ee's labcal stored in its database, as a file (read from a copy: even a
    read-only connection to a WAL database leaves files beside it)."""
    kept = Path(shutil.copy(DATA / "v0" / "labcal.sqlite", tmp_path / "v0.sqlite"))
    db = sqlite3.connect(kept)
    try:
        (text,) = db.execute("SELECT document FROM certificates").fetchone()
    finally:
        db.close()
    path = tmp_path / "v0.json"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def validator() -> jsonschema.Draft202012Validator:
    schema = json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_the_published_schema_is_the_one_the_models_generate():
    """Edit a model and not the published file (tools/schemas.py writes it): this fails."""
    assert json.loads((ROOT / SCHEMA_FILE).read_text(encoding="utf-8")) == json_schema()


@pytest.mark.parametrize("name", WRITTEN_BEFORE)
def test_a_certificate_issued_before_reads_back_to_the_same_bytes(name, tmp_path):
    path = ISSUED / f"{name}.json"
    before = json.loads(path.read_text(encoding="utf-8"))
    cert = read_certificate(path)
    assert canonical(cert.to_json()) == canonical(before)
    # and the file written again from the model is the file as issued, byte for byte
    assert write_certificate(tmp_path / "again.json", cert).read_bytes() == path.read_bytes()
    digest = hashlib.sha256(canonical({k: v for k, v in before.items() if k != "digest"})).hexdigest()
    assert cert.digest.value == digest


def test_the_v0_certificate_reads_back_to_the_same_bytes(tmp_path):
    path = v0_certificate(tmp_path)
    before = json.loads(path.read_text(encoding="utf-8"))
    assert "mode" not in before["station"]["sequencer_settings"]["settle"]  # a field added since
    assert canonical(read_certificate(path).to_json()) == canonical(before)


@pytest.mark.parametrize("name", ["approved", "reissued.rev1"])
def test_an_approved_certificate_still_verifies_after_the_model_rewrites_it(name, tmp_path):
    """The signature (cryptography's Ed25519, checked here over canonical bytes made in this test)
    holds over the document as the model writes it again; and the DCC the model makes of it is the
    one the approver signed (its SHA-256 is in the approval, made by f6969bc's labcal)."""
    cert = read_certificate(ISSUED / f"{name}.json")
    doc = json.loads(write_certificate(tmp_path / "again.json", cert).read_text(encoding="utf-8"))
    signed = {k: v for k, v in doc.items() if k != "digest"}
    signature = base64.b64decode(signed["approval"].pop("signature"))
    public = load_pem_public_key((ISSUED / "approver.pub").read_bytes())
    public.verify(signature, canonical(signed))  # raises InvalidSignature if one byte differs
    assert hashlib.sha256(dcc_document(cert)).hexdigest() == doc["approval"]["dcc_sha256"]


@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    """A dry run issued by this labcal (one mount, so quick): the schema holds for what it writes."""
    base = tmp_path_factory.mktemp("fresh")
    assert main(["run", "--sim", "--yes", "--plan", "one-mount-16", "--replicates", "2", "--out",
                 str(base / "run"), "--db", str(base / "lab.sqlite"), "--tolerance-deg", "0.5"]) == 0
    return base / "run" / "certificate.json"


@pytest.mark.parametrize("name", [*WRITTEN_BEFORE, "v0", "fresh"])
def test_real_certificates_are_valid_under_the_published_schema(name, validator, fresh, tmp_path):
    path = {"v0": lambda: v0_certificate(tmp_path), "fresh": lambda: fresh}.get(
        name, lambda: ISSUED / f"{name}.json")()
    errors = [e.message for e in validator.iter_errors(json.loads(path.read_text(encoding="utf-8")))]
    assert errors == []


def _drop(doc: dict, *keys: str) -> None:
    for key in keys[:-1]:
        doc = doc[key]
    del doc[keys[-1]]


def _set(value: object, *keys: str):
    def change(doc: dict) -> None:
        for key in keys[:-1]:
            doc = doc[key]
        doc[keys[-1]] = value
    return change


BROKEN = {
    "digest missing": lambda d: _drop(d, "digest"),
    "seed a word": _set("zero", "station", "sequencer_settings", "seed"),
    "settle without tau": lambda d: _drop(d, "station", "sequencer_settings", "settle", "tau_s"),
    "layout units a list": _set(["V"], "fit", "layout", "units"),
    "budget input a word": _set("tiny", "uncertainty_budget", "inputs", "pitch_index"),
    "budget input missing": lambda d: _drop(d, "uncertainty_budget", "inputs", "dmm_reading"),
    "F test df of three": _set([6, 174, 1], "device", "misalignment_test", "df"),
    "identifiability rank a float": _set(17.5, "device", "identifiability", "rank"),
    "sensitivity without u": lambda d: _drop(d, "device", "intrinsic", "sensitivity_v_per_g", "x", "u"),
    "an unknown field in the truth": _set(1, "station", "simulated_truth", "extra"),
}


@pytest.mark.parametrize("what", list(BROKEN))
def test_a_wrong_type_or_a_missing_field_fails_both_validators(what, validator, tmp_path):
    doc = copy.deepcopy(json.loads((ISSUED / "simulated.json").read_text(encoding="utf-8")))
    assert list(validator.iter_errors(doc)) == []
    BROKEN[what](doc)
    assert list(validator.iter_errors(doc)) != []
    path = tmp_path / "broken.json"
    path.write_text(json.dumps(doc), encoding="utf-8")
    with pytest.raises(LabcalError, match="invalid certificate"):  # labcal's own reading refuses it too
        read_certificate(path)


def test_replication_is_typed_in_the_schema(validator):
    doc = json.loads((ISSUED / "replicated.json").read_text(encoding="utf-8"))
    doc["fit"]["replication"]["x"]["lack_of_fit"]["significant"] = "yes"
    assert list(validator.iter_errors(doc)) != []


def test_a_fit_with_extensions_is_certified_under_the_schema(fresh, validator):
    """No fixture has model extensions (a run's certificate is fitted on the base model unless asked):
    a temperature term, fitted here, goes through the typed record and the published schema."""
    from labcal.analysis.fit import fit_readings
    from labcal.analysis.models import Model
    from labcal.documents.issuing import build_certificate
    from labcal.store.record import load_run

    record = load_run(fresh.parent)
    fit = fit_readings(record.readings, Model(extensions=("temperature",), t_ref=20.0))
    written = json.loads(json.dumps(fit.to_json()["extensions"]))
    cert = build_certificate(record, fit)
    assert cert.fit.extensions is not None and cert.fit.extensions.names == written["names"]
    assert cert.to_json()["fit"]["extensions"] == written
    assert list(validator.iter_errors(cert.to_json())) == []

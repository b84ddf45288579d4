"""Approval bound to the journal and to registered people: approvers are
registered in the lab database; `certificate approve` rebuilds the certificate from the journal and
refuses, in one line naming every reason, an edited draft (even with a recomputed digest), a key
that is not registered or is revoked, a name or role that is not the key's, and a simulated run; the
signature covers the DCC; `labcal attitude --cert` accepts only a signature by a registered key.

The signable run is a calibration through the real drivers against `labcal sim serve` in another
process, as against a bench: labcal does not know the devices are emulated (no simulated truth in its
journal), which is what a real run looks like to it. A dry run (`run --sim`) is the simulated one.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import sqlite3
from pathlib import Path

import pytest
from cli import cli
from second_ed25519 import holds, raw_public_key
from simulated_runs import bench_run, simulated_run

from labcal.cli import main
from labcal.documents.certificate import content_digest, read_certificate

NAME, ROLE = "A. Metrologist", "Technical manager"


def _refused(capsys, *args: str) -> str:
    """The command exits 2 with one line on stderr and nothing on stdout; the line."""
    code = main(list(args))
    captured = capsys.readouterr()
    assert code == 2, captured.err
    assert captured.out == "" and len(captured.err.strip().splitlines()) == 1, captured.err
    return " ".join(captured.err.split())


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    """A finished calibration on a 'bench' (emulators served by another process), its draft
    certificate, two key pairs (the approver's registered, a stranger's not) and a dry run."""
    base = tmp_path_factory.mktemp("bench")
    db = base / "lab.sqlite"
    bench_run(base / "run", db, "ACC-7")
    simulated_run(base / "dry", db, seed=5, plan="one-mount-16", serial="ACC-7")  # a real-looking serial
    for who in ("approver", "stranger"):
        assert main(["certificate", "keygen", "--out", str(base / who)]) == 0
    assert main(["certificate", "approvers", "add", NAME, "--role", ROLE, "--public-key",
                 str(base / "approver.pub"), "--db", str(db)]) == 0
    return base


@pytest.fixture
def lab(bench, tmp_path, monkeypatch):
    """A private copy of the bench's lab (run folders and database), the database as $LABCAL_DB."""
    base = tmp_path / "lab"
    shutil.copytree(bench, base)
    for run in ("run", "dry"):  # run.json names its journal: point it at the copy
        info = json.loads((base / run / "run.json").read_text())
        (base / run / "run.json").write_text(json.dumps({**info, "journal": str(base / "lab.sqlite")}))
    monkeypatch.setenv("LABCAL_DB", str(base / "lab.sqlite"))
    return base


def approve(base: Path, run: str = "run", by: str = NAME, role: str = ROLE, key: str = "approver"
            ) -> list[str]:
    return ["certificate", "approve", str(base / run), "--by", by, "--role", role,
            "--key", str(base / f"{key}.key")]


def level_volts(base: Path, cert) -> Path:
    """One reading at level attitude (V = B + S's z row, gravity +1 g on z) for `labcal attitude`."""
    volts = base / "volts.csv"
    row = cert.coefficients[0] + cert.coefficients[3]
    volts.write_text("vx,vy,vz\n" + ",".join(f"{float(v)!r}" for v in row) + "\n")
    return volts


def edit(path: Path, change) -> None:
    """Edit certificate.json and recompute its digest, as a forger would."""
    doc = json.loads(path.read_text())
    change(doc)
    doc["digest"]["value"] = content_digest(doc)
    path.write_text(json.dumps(doc))


def test_registered_approver_signs_a_real_run_and_the_signature_covers_the_dcc(lab, capsys):
    assert main(approve(lab)) == 0
    capsys.readouterr()
    cert_path, dcc = lab / "run" / "certificate.json", lab / "run" / "certificate.dcc.xml"
    cert = read_certificate(cert_path)
    assert cert.approval.by == NAME and cert.approval.dcc_sha256 is not None
    assert main(["certificate", "verify", str(cert_path), "--json"]) == 0  # against the registry
    assert json.loads(capsys.readouterr().out)["verified_against"] == "the registered key"
    dcc.write_bytes(dcc.read_bytes().replace(b"<si:value>", b"<si:value>1", 1))  # the DCC edited
    assert "the DCC is not the one approved" in _refused(capsys, "certificate", "verify", str(cert_path))
    # labcal attitude accepts the signed certificate
    volts = level_volts(lab, cert)
    assert main(["attitude", "--cert", str(cert_path), "--csv", str(volts), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["certificate"]["verified"] is True


def test_the_approval_signature_holds_in_a_second_implementation_over_everything_but_itself(lab, capsys):
    """libsodium (`second_ed25519`) accepts the approver's signature over the certificate as written,
    without its digest and the signature value, in canonical JSON (sorted keys, no spaces, UTF-8): the
    bytes are made here from the file. Another name, a nudged coefficient or another key: refused.
    The key id on the certificate is the SHA-256 of the raw key, computed here with hashlib."""
    assert main(approve(lab)) == 0
    doc = json.loads((lab / "run" / "certificate.json").read_text(encoding="utf-8"))
    signature = doc["approval"]["signature"]

    def covered(change=lambda d: None) -> bytes:
        content = json.loads(json.dumps({k: v for k, v in doc.items() if k != "digest"}))
        del content["approval"]["signature"]
        change(content)
        return json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=False).encode("utf-8")

    public = lab / "approver.pub"
    assert doc["approval"]["key_id"] == hashlib.sha256(raw_public_key(public)).hexdigest()
    assert holds(public, covered(), signature)
    assert not holds(public, covered(lambda d: d["approval"].update(by="B. Other")), signature)
    assert not holds(public, covered(lambda d: d["fit"]["coefficients"][0].__setitem__(0, 0.5)), signature)
    assert not holds(lab / "stranger.pub", covered(), signature)


def test_an_edited_draft_with_a_recomputed_digest_is_refused(lab, capsys):
    def nudge(doc):
        doc["fit"]["coefficients"][0][0] += 1e-6
    edit(lab / "run" / "certificate.json", nudge)
    err = _refused(capsys, *approve(lab))
    assert err.startswith(f"labcal: error: {lab / 'run'}: not approved: certificate.json is not what the "
                          "journal gives")
    assert "fit.coefficients[0][0]" in err and "simulated" not in err
    assert read_certificate(lab / "run" / "certificate.json").draft


def test_an_unregistered_key_is_refused(lab, capsys):
    err = _refused(capsys, *approve(lab, key="stranger"))
    assert "is not registered" in err and "approvers add" in err


def test_a_revoked_key_is_refused_and_its_signatures_no_longer_verify(lab, capsys):
    assert main(approve(lab)) == 0
    assert main(["certificate", "approvers", "revoke", NAME]) == 0
    capsys.readouterr()
    shutil.copy(lab / "run" / "certificate.rev1.json" if (lab / "run" / "certificate.rev1.json").exists()
                else lab / "run" / "certificate.json", lab / "signed.json")
    err = _refused(capsys, "certificate", "verify", str(lab / "signed.json"))
    assert "signature not accepted" in err and "was revoked on" in err
    assert main(["report", str(lab / "run")]) == 0  # a new revision, to approve again
    capsys.readouterr()
    err = _refused(capsys, *approve(lab))
    assert "was revoked on" in err and "not registered" not in err


def test_a_name_or_role_that_is_not_the_keys_is_refused(lab, capsys):
    err = _refused(capsys, *approve(lab, by="Someone Else", role="Director"))
    assert f"is registered to {NAME!r}, not 'Someone Else'" in err
    assert f"registered role is {ROLE!r}, not 'Director'" in err


def test_a_simulated_run_is_refused_and_every_reason_is_named(lab, capsys):
    err = _refused(capsys, *approve(lab, run="dry"))
    assert "the run is simulated" in err and "is not what the journal gives" not in err
    edit(lab / "dry" / "certificate.json", lambda doc: doc["statements"].append("All is well."))
    err = _refused(capsys, *approve(lab, run="dry", key="stranger"))
    assert "the run is simulated" in err and "is not what the journal gives (differs in statements" in err
    assert "is not registered" in err


def test_attitude_refuses_a_forged_or_unknown_key_certificate_unless_told(lab, capsys):
    assert main(approve(lab)) == 0
    capsys.readouterr()
    cert_path = lab / "run" / "certificate.json"
    cert = read_certificate(cert_path)
    volts = level_volts(lab, cert)
    forged = lab / "forged.json"
    shutil.copy(cert_path, forged)
    edit(forged, lambda doc: doc["fit"]["coefficients"][0].__setitem__(0, 0.5))
    for flags in ((), ("--allow-outliers",)):
        err = _refused(capsys, "attitude", "--cert", str(forged), "--csv", str(volts), *flags)
        assert "signature does not match the content" in err
    # signed by a key the lab does not know: the stranger registers nowhere, signs a copy
    with sqlite3.connect(lab / "lab.sqlite") as conn:
        conn.execute("DELETE FROM approvers")
    err = _refused(capsys, "attitude", "--cert", str(cert_path), "--csv", str(volts))
    assert "is not registered" in err
    # the explicit override: works, and every output says so
    code, out, err = cli(capsys, "attitude", "--cert", str(cert_path), "--csv", str(volts), "--unverified")
    assert code == 0 and out.startswith("# UNVERIFIED") and "UNVERIFIED" in err
    code, out, err = cli(capsys, "attitude", "--cert", str(cert_path), "--csv", str(volts), "--unverified",
                         "--json")
    assert code == 0 and json.loads(out)["certificate"]["verified"] is False and "UNVERIFIED" in err


def test_the_approvers_list_names_the_database_and_says_when_it_does_not_exist(tmp_path, capsys):
    """A mistyped --db is not an empty registry: the list names the database it read and says the
    file does not exist yet, and creates nothing."""
    missing = tmp_path / "nowhere" / "lab.sqlite"
    assert main(["certificate", "approvers", "list", "--db", str(missing)]) == 0
    assert capsys.readouterr().out.startswith(f"no approvers registered in {missing} (it does not exist yet)")
    assert main(["certificate", "approvers", "list", "--db", str(missing), "--json"]) == 0
    assert json.loads(capsys.readouterr().out) == {"database": str(missing), "approvers": []}
    assert not missing.parent.exists()
    made = tmp_path / "lab.sqlite"
    assert main(["db", "upgrade", "--db", str(made)]) == 0
    capsys.readouterr()
    assert main(["certificate", "approvers", "list", "--db", str(made)]) == 0
    assert capsys.readouterr().out.startswith(f"no approvers registered in {made} (`labcal certificate")


def test_approvers_list_add_revoke_through_the_cli(lab, capsys):
    assert main(["certificate", "approvers", "list", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["approvers"]
    assert [(a["name"], a["role"], a["revoked_utc"]) for a in listed] == [(NAME, ROLE, None)]
    err = _refused(capsys, "certificate", "approvers", "add", "B. Other", "--role", "Deputy", "--public-key",
                   str(lab / "approver.pub"))
    assert "already registered for A. Metrologist" in err  # one key, one name
    err = _refused(capsys, "certificate", "approvers", "add", NAME, "--role", ROLE, "--public-key",
                   str(lab / "stranger.pub"))
    assert "already registered with key" in err
    assert "no active approver" in _refused(capsys, "certificate", "approvers", "revoke", "Nobody")
    assert main(["certificate", "approvers", "revoke", NAME]) == 0
    assert main(["certificate", "approvers", "add", NAME, "--role", ROLE, "--public-key",
                 str(lab / "stranger.pub")]) == 0  # a new key after revocation
    capsys.readouterr()
    assert main(["certificate", "approvers", "list", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)["approvers"]
    assert [a["revoked_utc"] is None for a in listed] == [False, True]

"""Approval of a certificate with a real signature (Ed25519), and its verification.

The SHA-256 digest detects an accident but not a forgery: whoever edits a value can recompute it.
An approved certificate also carries an Ed25519 signature by the approver's private key over the
canonical JSON of everything but the digest and the signature itself — the approver's name, role,
time and key id included — so any change, with or without a recomputed digest, fails
verification against the laboratory's public key. The signed approval also holds the SHA-256 of
the Digital Calibration Certificate written with it (``dcc_sha256``), so the signature covers both
files: an edited DCC no longer matches the digest the approver signed.

Whose key signed is the lab database's to say: `labcal.documents.approvers.verify_registered`
accepts a signature only by a registered, unrevoked key whose registered name and role are the ones
the certificate states.

Keys are PEM files: the private key PKCS#8, created readable by its owner only (0600) and refused
when group or others may read it; the public key SubjectPublicKeyInfo, to hand to customers.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import stat
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from labcal.config.files import read_text
from labcal.documents.certificate import Certificate, certificate_from_doc, parse_json, seal
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.documents import dcc
else:
    dcc = lazy("labcal.documents.dcc")  # start-up without scipy, numpy, pydantic, …

ALGORITHM = "Ed25519"


def signed_bytes(doc: dict) -> bytes:
    """What the signature covers: canonical JSON (sorted keys, no spaces, UTF-8) of the document
    without its digest and without the signature value."""
    content = {k: v for k, v in doc.items() if k != "digest"}
    if isinstance(content.get("approval"), dict):
        content["approval"] = {k: v for k, v in content["approval"].items() if k != "signature"}
    return json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                      allow_nan=False).encode("utf-8")


def key_id(public: Ed25519PublicKey) -> str:
    """SHA-256 of the raw public key: names the key on the certificate."""
    raw = public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()


# --- keys ---------------------------------------------------------------------------------------
def keygen(prefix: str | Path) -> tuple[Path, Path]:
    """PREFIX.key (private, 0600, never overwritten) and PREFIX.pub."""
    private_path, public_path = Path(f"{prefix}.key"), Path(f"{prefix}.pub")
    for path in (private_path, public_path):
        if path.exists():
            raise LabcalError(f"{path}: already exists; a key is never overwritten (choose another {{0}})",
                              "out")
    key = Ed25519PrivateKey.generate()
    pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                            serialization.NoEncryption())
    try:
        fd = os.open(private_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "wb") as out:
            out.write(pem)
        public_path.write_bytes(
            key.public_key().public_bytes(
                serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo
            )
        )
    except OSError as exc:
        raise LabcalError(f"{exc.filename}: cannot write the key ({exc.strerror})") from None
    return private_path, public_path


def _key_bytes(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise LabcalError(f"{path}: no such {what} file (make a key pair with `labcal certificate keygen`)") \
            from None
    except OSError as exc:
        raise LabcalError(f"{path}: cannot read the {what} ({exc.strerror})") from None


def load_private_key(path: str | Path) -> Ed25519PrivateKey:
    """The approver's key; refused when others may read it (anyone who can would sign as them)."""
    path = Path(path)
    data = _key_bytes(path, "private key")
    mode = stat.S_IMODE(path.stat().st_mode)
    if os.name == "posix" and mode & 0o077:
        raise LabcalError(f"{path}: permissions {mode:04o} let others read the private key; "
                          f"`chmod 600 {path}` (and consider it compromised if others did)")
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError, UnsupportedAlgorithm):
        raise LabcalError(f"{path}: not an unencrypted PEM private key (make one with `labcal certificate "
                          "keygen`)") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise LabcalError(f"{path}: not an Ed25519 key; labcal signs with Ed25519 "
                          "(`labcal certificate keygen`)")
    return key


def load_public_key(path: str | Path) -> Ed25519PublicKey:
    path = Path(path)
    try:
        key = serialization.load_pem_public_key(_key_bytes(path, "public key"))
    except (ValueError, TypeError, UnsupportedAlgorithm):
        raise LabcalError(f"{path}: not a PEM public key (the .pub file of `labcal certificate keygen`)") \
            from None
    if not isinstance(key, Ed25519PublicKey):
        raise LabcalError(f"{path}: not an Ed25519 public key")
    return key


# --- approving and verifying ---------------------------------------------------------------------
def approve(cert: Certificate, by: str, role: str, key: Ed25519PrivateKey,
            when: datetime | None = None, server: dict | None = None) -> Certificate:
    """The certificate approved by ``by`` (``role``) and signed with ``key``, sealed again; the
    signature covers the DCC that `dcc_document` makes of it (its SHA-256 is in the approval).
    ``server``: the key is the lab server's, signing for ``by`` (`certificate.ServerSignature`)."""
    if cert.approval is not None:
        raise LabcalError(f"certificate {cert.number} is already approved by {cert.approval.by}; a change "
                          "is a new revision (`labcal report` issues it)")
    if not by.strip() or not role.strip():
        raise LabcalError("give the approver's name ({0}) and role ({1})", "by", "role")
    approval: dict[str, object] = {
        "by": by.strip(), "role": role.strip(),
        "approved_utc": (when or datetime.now(UTC)).isoformat(timespec="seconds"),
        "algorithm": ALGORITHM, "key_id": key_id(key.public_key()), "signature": ""}
    if server is not None:
        approval["server"] = server
    unsigned = {k: v for k, v in cert.to_json().items() if k != "digest"}
    # The DCC states who approved (not the signature nor its own digest): make it once to hash it.
    approval["dcc_sha256"] = dcc_sha256(dcc.dcc_document(seal({**unsigned, "approval": approval})))
    # Sign the document exactly as it will be written (validated and serialised once), so that the
    # verifier, which reads the written JSON, sees the same bytes.
    doc = seal({**unsigned, "approval": approval}).to_json()
    doc["approval"]["signature"] = base64.b64encode(key.sign(signed_bytes(doc))).decode("ascii")
    return seal({k: v for k, v in doc.items() if k != "digest"})


def dcc_sha256(document: bytes) -> str:
    return hashlib.sha256(document).hexdigest()


def signed_certificate(path: str | Path) -> tuple[dict, Certificate]:
    source = str(path)
    doc = parse_json(read_text(path, "certificate"), source)
    cert = certificate_from_doc(doc, source)  # schema and digest: an accident shows here
    if cert.approval is None:
        raise LabcalError(f"{source}: not approved (a DRAFT): nothing to verify; "
                          "`labcal certificate approve` signs it")
    return doc, cert


def signature_holds(doc: dict, cert: Certificate, public: Ed25519PublicKey, source: str) -> None:
    assert cert.approval is not None
    try:
        public.verify(base64.b64decode(cert.approval.signature, validate=True), signed_bytes(doc))
    except (InvalidSignature, ValueError):
        raise LabcalError(f"{source}: the signature does not match the content: the certificate was changed "
                          "after approval") from None


def check_dcc(cert: Certificate, dcc_path: str | Path) -> None:
    """The DCC at ``dcc_path`` is the one the approver signed (its SHA-256 is in the approval)."""
    approval = cert.approval
    if approval is None or approval.dcc_sha256 is None:
        raise LabcalError(f"{dcc_path}: the certificate's approval does not cover a DCC (approved before "
                          "labcal signed the DCC too)")
    try:
        actual = dcc_sha256(Path(dcc_path).read_bytes())
    except OSError as exc:
        raise LabcalError(f"{dcc_path}: cannot read the DCC ({exc.strerror})") from None
    if actual != approval.dcc_sha256:
        raise LabcalError(f"{dcc_path}: the DCC is not the one approved (sha256 {actual[:12]}…, signed "
                          f"{approval.dcc_sha256[:12]}…): it was changed after approval")


def verify(path: str | Path, public: Ed25519PublicKey) -> Certificate:
    """The certificate, if it is approved and its signature verifies with ``public``; otherwise one
    line saying what is wrong (edited, signed by another key, not approved)."""
    source = str(path)
    doc, cert = signed_certificate(path)
    assert cert.approval is not None
    expected = key_id(public)
    if cert.approval.key_id != expected:
        raise LabcalError(f"{source}: signed by another key (key id {cert.approval.key_id[:12]}…, this "
                          f"public key is {expected[:12]}…)")
    signature_holds(doc, cert, public, source)
    return cert

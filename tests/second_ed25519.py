"""Ed25519 signatures checked by a second implementation: libsodium (through PyNaCl), not the OpenSSL
that labcal signs and verifies with (through `cryptography`). The key is read from its PEM here, by
hand: a SubjectPublicKeyInfo of an Ed25519 key is a fixed 12-byte DER prefix (RFC 8410 §4 and its
example in §10.1: SEQUENCE, the algorithm 1.3.101.112, a BIT STRING of 33 bytes) and the raw
32-byte key (RFC 8032 §5.1.5). What each signature covers is written out in the tests that use it,
from the rule labcal documents."""

from __future__ import annotations

import base64
from pathlib import Path

from nacl.exceptions import BadSignatureError
from nacl.signing import VerifyKey

SPKI_PREFIX = bytes.fromhex("302a300506032b6570032100")  # RFC 8410 §4, id-Ed25519 = 1.3.101.112


def raw_public_key(pem: Path) -> bytes:
    """The 32 raw bytes of an Ed25519 public key in a PEM SubjectPublicKeyInfo file."""
    lines = pem.read_text(encoding="ascii").split()
    assert lines[:3] == ["-----BEGIN", "PUBLIC", "KEY-----"]
    assert lines[-3:] == ["-----END", "PUBLIC", "KEY-----"]
    der = base64.b64decode("".join(lines[3:-3]))
    assert len(der) == 44 and der[:12] == SPKI_PREFIX, der.hex()
    return der[12:]


def holds(pem: Path, message: bytes, signature_b64: str) -> bool:
    """Whether libsodium accepts the base64 ``signature_b64`` of ``message`` by the key in ``pem``."""
    try:
        VerifyKey(raw_public_key(pem)).verify(message, base64.b64decode(signature_b64))
    except BadSignatureError:
        return False
    return True

"""Interfaces others rely on (docs/design.md §5) keep the names the user documents state.

The expected names are read from the documents (docs/user/), what users and other programs go by, not
from the code's own constants: a rename inside labcal that changed an identifier on the wire or
on disk fails here.
"""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

from cli import LABCAL

CERTIFICATES = Path(__file__).resolve().parents[2] / "docs" / "user" / "certificates.md"


def test_a_certificate_carries_the_schema_id_the_documents_state(tmp_path):
    documented = re.search(r"\*\*Certificate\*\* \(schema `([^`]+)`\)",
                           CERTIFICATES.read_text(encoding="utf-8"))
    assert documented, "docs/user/certificates.md no longer states the certificate schema"
    run_dir = tmp_path / "run"
    done = subprocess.run([LABCAL, "run", "--sim", "--yes", "--seed", "2", "--plan", "one-mount-16",
                           "--out", str(run_dir)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    cert = json.loads((run_dir / "certificate.json").read_text(encoding="utf-8"))
    assert cert["schema"] == documented.group(1)

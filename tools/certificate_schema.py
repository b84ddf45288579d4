"""Write schemas/certificate.schema.json: the JSON Schema of certificate.json, generated from the
certificate's models (`labcal.documents.certificate.json_schema`). Run from the repository root
after changing a model; tests/documents/test_certificate_schema.py fails while the published file differs.

    .venv/bin/python tools/certificate_schema.py
"""

from __future__ import annotations

import json
from pathlib import Path

from labcal.documents.certificate import SCHEMA_FILE, json_schema


def text() -> str:
    return json.dumps(json_schema(), indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    Path(SCHEMA_FILE).write_text(text(), encoding="utf-8")
    print(SCHEMA_FILE)

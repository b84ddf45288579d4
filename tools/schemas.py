"""Write the published JSON Schemas under schemas/, each generated from its models:

- certificate.schema.json: certificate.json (`labcal.documents.certificate.json_schema`);
- run-metadata.schema.json: what a run records of itself (`labcal.config.run_metadata.json_schema`);
- run-events.schema.json: a run's events as a subscriber or a stream's client reads them
  (`labcal.run.events.json_schema`).

Run from the repository root after changing one of those models; a test for each
(tests/documents/test_certificate_schema.py, tests/config/test_run_metadata.py,
tests/run/test_events.py) fails while its published file differs.

    .venv/bin/python tools/schemas.py
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from labcal.config import run_metadata
from labcal.documents import certificate
from labcal.run import events

PUBLISHED: list[tuple[str, Callable[[], dict[str, Any]]]] = [
    (certificate.SCHEMA_FILE, certificate.json_schema),
    (run_metadata.SCHEMA_FILE, run_metadata.json_schema),
    (events.SCHEMA_FILE, events.json_schema),
]


def text(schema: dict[str, Any]) -> str:
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    for path, generate in PUBLISHED:
        Path(path).write_text(text(generate()), encoding="utf-8")
        print(path)

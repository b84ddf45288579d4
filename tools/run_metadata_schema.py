"""Write schemas/run-metadata.schema.json: the JSON Schema of a run's metadata (the journal's
``metadata`` column, the run's record), generated from its model
(`labcal.config.run_metadata.json_schema`). Run from the repository root after changing the model;
tests/config/test_run_metadata.py fails while the published file differs.

    .venv/bin/python tools/run_metadata_schema.py
"""

from __future__ import annotations

import json
from pathlib import Path

from labcal.config.run_metadata import SCHEMA_FILE, json_schema


def text() -> str:
    return json.dumps(json_schema(), indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    Path(SCHEMA_FILE).write_text(text(), encoding="utf-8")
    print(SCHEMA_FILE)

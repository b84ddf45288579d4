"""Write schemas/run-events.schema.json: the JSON Schema of a run's events as a subscriber or a
stream's client reads them, generated from their models (`labcal.run.events.json_schema`). Run from
the repository root after changing an event's model; tests/run/test_events.py fails while the
published file differs.

    .venv/bin/python tools/run_events_schema.py
"""

from __future__ import annotations

import json
from pathlib import Path

from labcal.run.events import SCHEMA_FILE, json_schema


def text() -> str:
    return json.dumps(json_schema(), indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    Path(SCHEMA_FILE).write_text(text(), encoding="utf-8")
    print(SCHEMA_FILE)

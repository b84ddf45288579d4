"""Values JSON can hold, without pydantic: `--json` output needs this and nothing else of
`labcal.config.files` (whose pydantic import cost a million-row `labcal fit --json` 70 ms)."""

from __future__ import annotations


def json_safe(value):
    """Replace NaN and infinities (no JSON for them) by null."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value

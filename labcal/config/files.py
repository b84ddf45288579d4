"""Reading user files (every failure one LabcalError line naming the file and the field) and
writing JSON documents safely."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path
from typing import TypeVar

from pydantic import BaseModel, ValidationError

from labcal.errors import LabcalError

Model = TypeVar("Model", bound=BaseModel)


def read_text(path: str | Path, kind: str) -> str:
    """The file's text; ``kind`` names the file in the message ("plan", "readings", ...)."""
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise LabcalError(f"{path}: no such {kind} file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LabcalError(f"{path}: cannot read {kind} file ({exc})") from None


def one_line(exc: ValidationError) -> str:
    """The first validation error as 'field.path: message (and N more)'."""
    err = exc.errors()[0]
    where = ".".join(str(part) for part in err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{where}: {msg}{more}" if where else f"{msg}{more}"


def parse_model(text: str, model: type[Model], source: str) -> Model:
    """Parse TOML text into a validated pydantic model."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise LabcalError(f"{source}: malformed TOML: {exc}") from None
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise LabcalError(f"{source}: {one_line(exc)}") from None


def load_model(path: str | Path, model: type[Model], kind: str) -> Model:
    return parse_model(read_text(path, kind), model, str(path))


def json_safe(value):
    """Replace NaN and infinities (no JSON for them) by null."""
    if isinstance(value, float):
        return value if value == value and abs(value) != float("inf") else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [json_safe(v) for v in value]
    return value


def write_json(path: Path, doc: dict) -> None:
    """Write a JSON document atomically: a reader never sees half a file."""
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(json_safe(doc), indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)

"""Reading user files: every failure becomes one LabcalError line naming the file and the field."""

from __future__ import annotations

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

"""Reading user files (every failure one LabcalError line naming the file and the field) and
writing JSON documents safely."""

from __future__ import annotations

import errno
import json
import os
import shutil
import tomllib
from collections.abc import Callable
from difflib import get_close_matches
from pathlib import Path
from types import UnionType
from typing import TYPE_CHECKING, Annotated, Any, BinaryIO, Literal, TypeVar, Union, get_args, get_origin

from pydantic import BaseModel, ValidationError
from pydantic.fields import FieldInfo

from labcal.config.json_values import json_safe
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.config import streams
else:
    streams = lazy("labcal.config.streams")  # start-up without 3 more modules

Model = TypeVar("Model", bound=BaseModel)


def read_text(path: str | Path, kind: str) -> str:
    """The file's text; ``kind`` names the file in the message ("plan", "readings", ...). A pipe is
    read as long as it delivers, a device or a folder refused (`labcal.config.streams`)."""
    if streams.kind_of(path, kind) == "pipe":
        return streams.read_pipe(path, kind)
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise LabcalError(f"{path}: no such {kind} file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise LabcalError(f"{path}: cannot read {kind} file ({exc})") from None


def one_line(exc: ValidationError, model: type[BaseModel] | None = None) -> str:
    """The first validation error as 'field.path: message (and N more)'.

    Given the ``model`` that was validated, the path is spelled as the file spells it (a tagged
    union's tag, which pydantic puts in the path, is left out) and an unknown key is answered with
    the nearest valid name at that place: a typo then says how to fix it instead of only that
    something is extra. An unknown key is reported before the other errors: a misspelt required
    field is also a missing one, and the spelling is what to fix."""
    errors = exc.errors()
    err = next((e for e in errors if e["type"] == "extra_forbidden"), errors[0]) if model else errors[0]
    loc = tuple(err["loc"])
    msg = err["msg"].removeprefix("Value error, ")
    if model is None:
        where = ".".join(str(part) for part in loc)
    else:
        path, holders = _located(model, loc)
        where = ".".join(path)
        if err["type"] == "extra_forbidden" and path:
            msg = _unknown_key(path[-1], holders)
    more = f" (and {exc.error_count() - 1} more)" if exc.error_count() > 1 else ""
    return f"{where}: {msg}{more}" if where else f"{msg}{more}"


def _unknown_key(key: str, holders: list[type[BaseModel]]) -> str:
    names = sorted({name for holder in holders for name in _keys(holder)})
    nearest = get_close_matches(key, names, n=1)
    if nearest:
        return f"unknown key; did you mean {nearest[0]}?"
    return f"unknown key; the valid keys here are {', '.join(names)}" if names else "unknown key"


def _keys(model: type[BaseModel]) -> dict[str, FieldInfo]:
    """The names a file may use for the model's fields: their names and aliases."""
    keys = dict(model.model_fields)
    keys.update({info.alias: info for info in model.model_fields.values() if info.alias})
    return keys


def _held(annotation: Any) -> list[Any]:
    """The types a field's values are made of, through unions, Annotated, sequences and dict values."""
    origin, args = get_origin(annotation), get_args(annotation)
    if origin is Annotated:
        return _held(args[0])
    if origin in (Union, UnionType, list, tuple, set, frozenset):
        return [held for arg in args if arg is not Ellipsis for held in _held(arg)]
    if origin is dict:
        return _held(args[1])
    return [annotation]


def _models(types: list[Any]) -> list[type[BaseModel]]:
    return [t for t in types if isinstance(t, type) and issubclass(t, BaseModel)]


def _tagged(model: type[BaseModel], tag: str) -> bool:
    """Whether ``tag`` names this member of a union (its discriminator's value, or its class name)."""
    return tag == model.__name__ or any(
        get_origin(info.annotation) is Literal and get_args(info.annotation) == (tag,)
        for info in model.model_fields.values())


def _located(model: type[BaseModel], loc: tuple[int | str, ...]) -> tuple[list[str], list[type[BaseModel]]]:
    """An error's location as the file spells it, and the models that may hold its last key."""
    path: list[str] = []
    holders: list[Any] = [model]
    for i, part in enumerate(loc):
        last = i == len(loc) - 1
        fields = {key: info for holder in _models(holders) for key, info in _keys(holder).items()}
        tagged = [m for m in _models(holders) if _tagged(m, str(part))] if not last else []
        if isinstance(part, str) and part in fields:
            path.append(part)
            if not last:
                holders = _held(fields[part].annotation)
        elif tagged and isinstance(part, str):
            holders = tagged  # pydantic names the union member it tried; the file does not
        else:
            path.append(str(part))  # a list index, a dict key, or the unknown key itself
    return path, _models(holders)


def validate_model(data: object, model: type[Model], source: str) -> Model:
    """Validate parsed data (a TOML file's, a journal snapshot's) into ``model``; every mistake is
    one LabcalError line naming ``source`` and the field."""
    try:
        return model.model_validate(data)
    except ValidationError as exc:
        raise LabcalError(f"{source}: {one_line(exc, model)}") from None


MAX_DEPTH = 32  # nesting of arrays and tables in a file labcal reads; the deepest it writes is 4


def check_depth(data: object, source: str, limit: int = MAX_DEPTH) -> None:
    """Refuse a parsed document nested deeper than ``limit`` (one line naming the file and the
    field), walking it without recursion: a hostile file must not exhaust the stack."""
    stack: list[tuple[object, tuple[str, ...]]] = [(data, ())]
    while stack:
        value, path = stack.pop()
        if len(path) > limit:
            where = ".".join(path[:3]) + (".…" if len(path) > 3 else "")
            raise LabcalError(f"{source}: field {where} is nested more than {limit} deep; labcal's files "
                              "are not nested like that")
        if isinstance(value, dict):
            stack.extend((v, (*path, str(k))) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((v, (*path, str(i))) for i, v in enumerate(value))


def parse_model(text: str, model: type[Model], source: str) -> Model:
    """Parse TOML text into a validated pydantic model."""
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise LabcalError(f"{source}: malformed TOML: {exc}") from None
    except RecursionError:
        raise LabcalError(f"{source}: nested more than {MAX_DEPTH} deep; labcal's files are not nested "
                          "like that") from None
    check_depth(data, source)
    return validate_model(data, model, source)


def load_model(path: str | Path, model: type[Model], kind: str) -> Model:
    return parse_model(read_text(path, kind), model, str(path))


def write_json(path: Path, doc: dict) -> None:
    """Write a JSON document atomically: a reader never sees half a file."""
    write_atomic(path, json.dumps(json_safe(doc), indent=2) + "\n")


def write_atomic(path: str | Path, content: str | bytes | Callable[[BinaryIO], object]) -> Path:
    """Write a whole file so that a reader, a crash or a full disk never leaves half of it.

    The content goes to a temporary file beside ``path`` (``content`` is text, bytes, or a function
    that writes into the open binary file), is fsynced once and renamed over ``path``; the folder is
    then fsynced so that the rename survives a power cut too. Every file labcal leaves in a run
    folder, and every document it issues, is written here. A failure removes the temporary file and
    is one LabcalError line naming the folder (and, when the disk is full, the space needed).
    """
    path = Path(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    data = content.encode("utf-8") if isinstance(content, str) else content
    try:
        with open(tmp, "wb") as file:
            if callable(data):
                data(file)
            else:
                file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(tmp, path)
        _fsync_folder(path.parent)
    except OSError as exc:
        needed = len(data) if isinstance(data, bytes) else _size(tmp) + MARGIN_BYTES
        _remove_quietly(tmp)
        raise LabcalError(_write_failure(path, exc, needed)) from None
    except BaseException:
        _remove_quietly(tmp)
        raise
    return path


def _fsync_folder(folder: Path) -> None:
    try:
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return  # a platform without directory handles: the rename is as durable as it gets there
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def size_text(n: int) -> str:
    """Bytes as people read them: 812 B, 8.3 kB, 1.2 MB, 3.4 GB."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} B"


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError:
        return 0


def _remove_quietly(path: Path) -> None:
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass


def _write_failure(path: Path, exc: OSError, needed: int) -> str:
    """One line for a failed write: which folder, and what to do."""
    folder = path.parent
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        try:
            free = shutil.disk_usage(folder if folder.exists() else Path.cwd()).free
        except OSError:
            free = 0
        return (f"{folder}: disk full writing {path.name}: {size_text(free)} free, {size_text(needed)} "
                "needed; free some space there and run the command again (nothing was lost)")
    if exc.errno == errno.ENOENT and not folder.exists():
        return f"{folder}: folder no longer exists; cannot write {path.name}"
    return f"{path}: cannot write ({exc.strerror or exc})"


MARGIN_BYTES = 1_000_000  # what a file written by a function may still have needed when the disk filled

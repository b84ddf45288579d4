"""Every dotted name the code's docstrings and comments point a reader at (`labcal.x.y`, quoted in
backticks) names something that exists, and so does every one the published certificate schema
carries: a maintainer who follows a name must arrive somewhere. Checked on the installed package
(labcal.drivers and labcal.sim inside it) by importing the module and walking the attributes, not
by a list of names kept here."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import labcal
import labcal.drivers
import labcal.sim
from labcal.documents.certificate import SCHEMA_FILE

REPOSITORY = Path(__file__).resolve().parents[2]
# a name in backticks, followed by its closing backtick or a call's parenthesis
DOTTED = re.compile(r"(?<=`)labcal(?:\.[A-Za-z_][A-Za-z_0-9]*)+(?=[`(])")


def resolves(name: str) -> bool:
    """The longest importable module prefix of ``name``, then the rest as attributes."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            found: object = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attribute in parts[cut:]:
            if not hasattr(found, attribute):
                return False
            found = getattr(found, attribute)
        return True
    return False


def sources() -> list[Path]:
    folders = {Path(package.__file__).resolve().parent for package in (labcal, labcal.drivers, labcal.sim)}
    files = {path.resolve() for folder in folders for path in folder.rglob("*.py")}
    return sorted(files) + [REPOSITORY / SCHEMA_FILE]


def names_in(path: Path) -> list[tuple[int, str]]:
    return [(number, name) for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
            for name in DOTTED.findall(line)]


def test_the_pattern_finds_a_quoted_name_and_the_check_tells_a_live_one_from_a_dead_one(tmp_path):
    sample = tmp_path / "sample.py"
    sample.write_text('"""See `labcal.devices.station.RotaryAxis` and `labcal.station.RotaryAxis`,\n'
                      'not labcal.sqlite."""\n')
    found = [name for _, name in names_in(sample)]
    assert found == ["labcal.devices.station.RotaryAxis", "labcal.station.RotaryAxis"]
    assert resolves(found[0]) and not resolves(found[1])


def test_every_dotted_name_in_the_code_and_the_schema_resolves():
    dead = [f"{path.name}:{number}: {name}" for path in sources() for number, name in names_in(path)
            if not resolves(name)]
    assert not dead, "names that point nowhere:\n" + "\n".join(dead)

"""A station file's ``[uncertainty]`` table (the Type B inputs of the budget) and its
``[[traceability]]`` entries (the reference standards behind them).

Every Type B value is written with its unit — ``pitch_index = "2 arcsec"``, ``dmm_reading =
"0.0035 %"`` — because a bare number in the wrong unit is the mistake that goes unnoticed: 2 read as
degrees instead of arcseconds is a budget 3600 times too large. A value in a unit of the wrong kind
is one line naming the field and the units it accepts. Half-widths of rectangular distributions
unless the key says otherwise (GUM 4.3.7).

The example is Keysight's published 1-year DC voltage specification of the 34970A's internal DMM on
its 10 V range: 0.0035 % of reading + 0.0005 % of range (34970A Specifications, "Example 1: basic
dcV accuracy"; 18–28 °C, integration ≥ 1 PLC).
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from datetime import date
from typing import Annotated, Literal, Protocol

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer

from labcal.config.dates import written_date

# Units by kind, to SI (rad, 1, V, 1/K, V/K); the first SI-like one is how a value is written back
# (the journal keeps a station as JSON and validates it again on resume).
UNITS: dict[str, dict[str, float]] = {
    "angle": {"arcsec": math.pi / 648000, '"': math.pi / 648000, "″": math.pi / 648000,
              "arcmin": math.pi / 10800, "deg": math.pi / 180, "°": math.pi / 180,
              "µrad": 1e-6, "urad": 1e-6, "mrad": 1e-3, "rad": 1.0},
    "relative": {"%": 1e-2, "ppm": 1e-6},
    "voltage": {"V": 1.0, "mV": 1e-3, "µV": 1e-6, "uV": 1e-6},
    "per kelvin": {"%/K": 1e-2, "ppm/K": 1e-6, "%/°C": 1e-2, "ppm/°C": 1e-6, "1/K": 1.0},
    "voltage per kelvin": {"V/K": 1.0, "mV/K": 1e-3, "µV/K": 1e-6, "uV/K": 1e-6, "V/°C": 1.0,
                           "mV/°C": 1e-3, "µV/°C": 1e-6, "uV/°C": 1e-6},
}
_QUANTITY = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S+)\s*$")


SI_UNIT = {"angle": "rad", "relative": "ppm", "voltage": "V", "per kelvin": "1/K",
           "voltage per kelvin": "V/K"}


def _in(kind: str):
    units = UNITS[kind]

    def parse(value: object) -> float:
        example = f'"2 {next(iter(units))}"'
        if isinstance(value, int | float) and not isinstance(value, bool):
            raise ValueError(f"give the unit with the number, e.g. {example} ({kind}: {', '.join(units)})")
        match = _QUANTITY.match(value) if isinstance(value, str) else None
        if match is None:
            raise ValueError(f"{value!r} is not a number with a unit, e.g. {example}")
        number, unit = float(match[1]), match[2]
        if unit not in units:
            raise ValueError(f"{value!r}: {unit!r} is not a unit of {kind}; use one of {', '.join(units)}")
        if not (math.isfinite(number) and number >= 0):
            raise ValueError(f"{value!r} must be a finite half-width ≥ 0")
        return number * units[unit]
    return BeforeValidator(parse)


def _out(kind: str):
    unit = SI_UNIT[kind]
    scale = UNITS[kind][unit]
    return PlainSerializer(lambda value: f"{value / scale!r} {unit}", return_type=str)


Angle = Annotated[float, _in("angle"), _out("angle")]
Relative = Annotated[float, _in("relative"), _out("relative")]
Voltage = Annotated[float, _in("voltage"), _out("voltage")]
PerKelvin = Annotated[float, _in("per kelvin"), _out("per kelvin")]
VoltagePerKelvin = Annotated[float, _in("voltage per kelvin"), _out("voltage per kelvin")]


class UncertaintyInputs(BaseModel):
    """The Type B inputs of the bench (SI after validation; zero: not a source here)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    dmm_reading: Relative = Field(default=0.0, description="DMM accuracy, % of reading (rectangular)")
    dmm_range: Relative = Field(default=0.0,
                                description="DMM accuracy, % of range (range from [dmm] range_v)")
    dmm_noise: Voltage = Field(default=0.0, description="rms noise of one averaged reading (shown; already "
                                                        "in the fit's Type A)")
    pitch_index: Angle = Field(default=0.0, description="pitch table index accuracy, ± half-width")
    pitch_wobble: Angle = 0.0
    roll_index: Angle = 0.0
    roll_wobble: Angle = 0.0
    mount_repeatability: Angle = Field(default=0.0, description="± half-width of each of the plate's pitch, "
                                                                "roll and yaw at a remount")
    common: list[Literal["dmm_reading", "dmm_range"]] | None = Field(
        default=None, description="inputs whose error is one and the same in the three channels (a scanning "
                                  "DMM measures them through one ADC); default: dmm_reading where the DMM is "
                                  "a scanning one (keysight-34970a), else none; [] declares every one "
                                  "independent per channel")
    bias_tempco: VoltagePerKelvin = Field(default=0.0, description="instrument bias temperature coefficient")
    sensitivity_tempco: PerKelvin = Field(default=0.0, description="instrument sensitivity temperature "
                                                                   "coefficient")


class Traceability(BaseModel):
    """A reference standard or calibrated piece of equipment behind the results (ISO/IEC 17025
    §6.5, §7.8.2.1 and §7.8.4.1 of what a certificate states)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    equipment: str = Field(min_length=1, description="what it is: 'pitch table', 'DMM', 'reference level'")
    identity: str = Field(default="", description="manufacturer, model, serial")
    certificate: str = Field(min_length=1, description="number of its calibration certificate")
    issued_by: str = Field(default="", description="the laboratory that calibrated it")
    due: date = Field(description="calibration due date")


class Standard(Protocol):
    """A reference standard as a station file (`Traceability`) or a certificate states it."""

    @property
    def equipment(self) -> str: ...
    @property
    def identity(self) -> str: ...
    @property
    def certificate(self) -> str: ...
    @property
    def due(self) -> date: ...


def overdue_standards(standards: Iterable[Standard], on: date, today: bool = False) -> list[str]:
    """One line for each reference standard whose calibration was due before ``on``: the day a
    certificate's calibration was made (its first page says it), or ``today`` (`labcal station
    check`, before a run uses it). One function, so the two never disagree about what is overdue."""
    when = "today" if today else "used"
    return [f"Reference standard {t.equipment} ({t.identity}, certificate {t.certificate}) "
            f"{'is' if today else 'was'} overdue for calibration: due {written_date(t.due)}, {when} "
            f"{written_date(on)}."
            for t in standards if t.due < on]

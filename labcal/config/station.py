"""The station file: which driver runs each table and the DMM, on which link, with which settings.

TOML validated by pydantic; `load_station` turns every mistake into one `LabcalError` line naming
the file and the field. Devices that name the same port or TCP address share one bus (one owner):
two AZ drives on one RS-485 line, two SMC100 controllers daisy-chained on one serial port.
"""

from __future__ import annotations

from collections.abc import Sequence
from importlib import resources
from pathlib import Path
from typing import Annotated, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator

from labcal.analysis.packages import PACKAGES
from labcal.config.emulation import EmulationSettings, FaultKind
from labcal.config.files import parse_model, read_text
from labcal.config.readings_csv import UNITS, unit_named
from labcal.config.settings import CertificateSettings, SequencerSettings, ThermalGate
from labcal.config.uncertainty import Traceability, UncertaintyInputs
from labcal.errors import LabcalError

# The 34970A's settable integration times (power-line cycles) and DC volts ranges: others are
# answered with error -222 (34970A/34972A User's Guide, DC voltage measurements).
DEFAULT_CABLE_WRAP_DEG = 360.0  # a table without slip rings: a turn either way from home
NPLC_VALUES = (0.02, 0.2, 1.0, 2.0, 10.0, 20.0, 100.0, 200.0)
RANGES_V = (0.1, 1.0, 10.0, 100.0, 300.0)


PTY_PREFIX = "pty:"  # port = "pty:NAME": an emulator's pty, linked as NAME in a folder of the run's own


def tcp_address(text: str) -> tuple[str, int]:
    """'host:port' → (host, port); raises ValueError with a readable message."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r} is not host:port")
    return host.strip("[]"), int(port)


class LinkSettings(BaseModel):
    """How to reach a device: ``port`` (a serial device or pyserial URL) or ``tcp`` (host:port)."""

    model_config = ConfigDict(extra="forbid")

    # The fields that make a device the one a run's readings were taken with, as opposed to how it
    # is reached: a resumed run may change the link (a USB adapter back on another port), not these.
    IDENTITY: ClassVar[tuple[str, ...]] = ()

    port: str | None = Field(default=None, description="serial device path or pyserial URL "
                                                        "(socket://host:port, rfc2217://, loop://)")
    tcp: str | None = Field(default=None, description="host:port of a TCP connection")
    baudrate: int = Field(default=57600, gt=0)
    parity: Literal["N", "E", "O"] = "N"
    bytesize: Literal[7, 8] = 8
    stopbits: Literal[1, 2] = 1
    xonxoff: bool = False
    timeout_s: float = Field(default=0.5, gt=0, le=60, description="reply timeout of one exchange")
    retries: int = Field(default=2, ge=0, le=10, description="repeats of an exchange that is safe to repeat")
    reconnect_s: float = Field(default=5.0, ge=0, le=600, description="how long to try reopening a lost port")

    @model_validator(mode="after")
    def _one_link(self):
        if (self.port is None) == (self.tcp is None):
            raise ValueError("give exactly one of port (a serial device or URL) and tcp (host:port)")
        if self.tcp is not None:
            tcp_address(self.tcp)
        return self

    @property
    def where(self) -> str:
        """The link in words, for messages: ``tcp 10.0.0.5:502`` or the port as given."""
        return f"tcp {self.tcp}" if self.tcp else str(self.port)

    @property
    def chosen_by_emulators(self) -> bool:
        """``tcp = "127.0.0.1:0"``, ``port = "socket://127.0.0.1:0"`` or ``port = "pty:NAME"``: a
        link the emulators choose as they start (any free TCP port; a pty linked in a folder of
        their own), so that two emulated runs of one station file never meet. Real hardware has
        no such link."""
        if self.tcp is not None:
            return tcp_address(self.tcp)[1] == 0
        port = self.port or ""
        if port.startswith("socket://"):
            try:
                return tcp_address(port.removeprefix("socket://").split("?")[0])[1] == 0
            except ValueError:
                return False
        return port.startswith(PTY_PREFIX)

    @property
    def bus(self) -> str:
        """What identifies the physical link; devices with the same bus share it. On port 0 (any
        free port, `chosen_by_emulators`) the devices of one driver share one (one gateway, one
        daisy chain), and a DMM or another driver gets a port of its own."""
        bus = f"tcp:{self.tcp}" if self.tcp else f"port:{self.port}"
        if self.chosen_by_emulators and not (self.port or "").startswith(PTY_PREFIX):
            bus += f"#{getattr(self, 'driver', '')}"
        return bus

    def line_settings(self) -> tuple:
        return self.baudrate, self.parity, self.bytesize, self.stopbits, self.xonxoff, self.timeout_s


class AxisSettings(LinkSettings):
    speed_dps: float = Field(default=20.0, gt=0, le=3600)
    accel_dps2: float = Field(default=40.0, gt=0, le=100000)
    limits_deg: tuple[float, float] | None = Field(
        default=None, description="soft limits [low, high] in the table's own degrees; none: free to wrap")
    in_position_arcsec: float = Field(default=5.0, gt=0, le=36000, description="read-back tolerance")
    poll_s: float = Field(default=0.05, gt=0, le=10, description="status polling interval while moving")
    slip_ring: bool = Field(default=False, description="the table's cables pass through slip rings: it may "
                            "turn without bound")
    cable_wrap_deg: float | None = Field(default=None, gt=0, le=36000, allow_inf_nan=False, description=(
        f"the table's accumulated rotation from home stays within ± this (default {DEFAULT_CABLE_WRAP_DEG:g} "
        "without slip_ring)"))

    @field_validator("limits_deg")
    @classmethod
    def _ordered(cls, limits):
        if limits is not None and not limits[0] < limits[1]:
            raise ValueError("limits_deg must be [low, high] with low < high")
        return limits

    @model_validator(mode="after")
    def _cables(self):
        if self.slip_ring and self.cable_wrap_deg is not None:
            raise ValueError("a table on slip rings has no cable wrap: give slip_ring = true or "
                             "cable_wrap_deg, not both")
        return self

    @property
    def wrap_deg(self) -> float | None:
        """How far from home the table's cables let it turn, either way; None: slip rings."""
        if self.slip_ring:
            return None
        return DEFAULT_CABLE_WRAP_DEG if self.cable_wrap_deg is None else self.cable_wrap_deg


class AzSettings(AxisSettings):
    """Oriental Motor AZ drive (Modbus RTU on ``port``, Modbus TCP on ``tcp``)."""

    IDENTITY: ClassVar[tuple[str, ...]] = ("driver", "unit", "steps_per_degree", "wrap", "limits_deg")
    driver: Literal["oriental-az"]
    unit: int = Field(default=1, ge=1, le=247, description="Modbus slave address (unit id)")
    steps_per_degree: float = Field(gt=0, le=1e9, allow_inf_nan=False,
                                    description="table steps per degree (motor steps × gear)")
    wrap: bool = Field(default=True, description="the drive's wrap setting: one table turn, 0..N−1")
    baudrate: int = 115200
    parity: Literal["N", "E", "O"] = "E"

    @model_validator(mode="after")
    def _wrap(self):
        turn = 360 * self.steps_per_degree
        if abs(turn - round(turn)) > 1e-6:
            raise ValueError(f"steps_per_degree × 360 = {turn:g} is not a whole number of steps per turn")
        if self.wrap and self.limits_deg is not None:
            raise ValueError("a wrapping table has no limits: set wrap = false to use limits_deg")
        return self


class Smc100Settings(AxisSettings):
    """Newport SMC100 controller with a rotation stage (ASCII over serial or TCP)."""

    IDENTITY: ClassVar[tuple[str, ...]] = ("driver", "address", "limits_deg")
    driver: Literal["newport-smc100"]
    address: int = Field(default=1, ge=1, le=31, description="controller address on the RS-485 chain")
    home_timeout_s: float = Field(default=60.0, gt=0)
    xonxoff: bool = True


class DmmSettings(LinkSettings):
    """Keysight 34970A-family DMM with a multiplexer card."""

    IDENTITY: ClassVar[tuple[str, ...]] = ("driver", "channels", "temperature_channel", "temperature_probe",
                                           "nplc", "range_v")
    driver: Literal["keysight-34970a"]
    channels: tuple[int, ...] = Field(default=(101, 102, 103), min_length=1, max_length=3, description=(
        "one channel per sensor of the instrument's package, in x, y, z order: x, y, z outputs of a "
        "three-axis package, [x] of a single-axis one, [x, y] or [x, z] of a two-axis one"))
    temperature_channel: int | None = Field(default=None, description="optional temperature sensor channel")
    temperature_probe: str = Field(default="RTD,85",
                                   description="CONF:TEMP arguments, e.g. RTD,85 or THER,10000")
    nplc: float = 10.0
    range_v: float = 10.0
    line_hz: Literal[50, 60] = 50
    xonxoff: bool = True
    visa: str | None = Field(default=None, description="a VISA resource instead of port/tcp: "
                             "GPIB0::9::INSTR, TCPIP0::host::inst0::INSTR, TCPIP0::host::5025::SOCKET, "
                             "USB0::...::INSTR, ASRL/dev/ttyUSB0::INSTR")
    visa_library: str = Field(default="@py", description="the VISA library: @py (pyvisa-py, installed with "
                              "labcal), @ivi, or the path of a vendor's libvisa")

    @model_validator(mode="after")
    def _one_link(self):
        """Exactly one of port, tcp and visa (the base class's rule, with VISA as a third way)."""
        given = [name for name in ("port", "tcp", "visa") if getattr(self, name) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of port (a serial device or URL), tcp (host:port) and visa "
                             "(a VISA resource string)")
        if self.tcp is not None:
            tcp_address(self.tcp)
        return self

    @property
    def where(self) -> str:
        return f"VISA {self.visa}" if self.visa else super().where

    @property
    def bus(self) -> str:
        return f"visa:{self.visa}" if self.visa else super().bus

    @property
    def serial_line(self) -> bool:
        """RS-232 (a serial port, or a VISA ASRL resource), where the unit needs SYST:REM."""
        return self.port is not None or (self.visa or "").upper().startswith("ASRL")

    @field_validator("nplc", "range_v")
    @classmethod
    def _settable(cls, value: float, info: ValidationInfo) -> float:
        """Only the values the unit has (the 34970A answers others with error -222)."""
        allowed = NPLC_VALUES if info.field_name == "nplc" else RANGES_V
        if value not in allowed:
            raise ValueError(f"{info.field_name} must be one of {', '.join(f'{v:g}' for v in allowed)}")
        return value

    @model_validator(mode="after")
    def _channels(self):
        scan = [*self.channels, *([self.temperature_channel] if self.temperature_channel else [])]
        if any(not (1 <= c // 100 <= 3 and 1 <= c % 100 <= 40) for c in scan):
            raise ValueError("channels are slot × 100 + channel, e.g. 101 (slots 1-3, channels 1-40)")
        if len(set(scan)) != len(scan):
            raise ValueError("each channel may appear once")
        return self


AxisConfig = Annotated[AzSettings | Smc100Settings, Field(discriminator="driver")]


class InstrumentSettings(BaseModel):
    """The instrument under calibration, as far as a run needs to know it: the unit its outputs are
    read in (a run's fit, fit.json and certificate state B in it and S per g in it; only volts are
    held to a DMM's range) and how long it must be powered before it is calibrated (the pre-run
    checklist asks when it was switched on)."""

    model_config = ConfigDict(extra="forbid")

    units: Literal["V", "mV", "counts", "m/s2"] = Field(
        default="V", description="the outputs' unit: V, mV, counts or m/s2 (as `labcal fit --units`)")
    warm_up_min: float | None = Field(default=None, gt=0, le=7 * 24 * 60, description=(
        "minutes the instrument must be powered before a run (its data sheet's warm-up time)"))
    package: Literal["three-axis", "two-axis-xy", "two-axis-xz", "single-axis"] = Field(
        default="three-axis", description="the axes its accelerometers lie along: three-axis (x, y, z), "
        "two-axis-xy, two-axis-xz or single-axis (x), Tripp & Tcheng §6")
    roll_in_use: Literal["inferred", "none", "table", "sensor"] | None = Field(
        default=None, description="how roll is obtained where the instrument is used: inferred from its "
        "own outputs (the default with two or three axes), none (pitch at roll 0 only, single-axis), or "
        "measured independently by the roll table or a roll sensor (with roll_sd_deg)")
    roll_sd_deg: float | None = Field(default=None, gt=0, le=10, description=(
        "standard deviation σ_R (°) of the independently measured roll (Tripp eq. 81)"))
    thermal_gate: ThermalGate | None = Field(default=None, description=(
        "before each mount's points, wait until the instrument's temperature changes by less than "
        "rate_c_per_min over hold_s, e.g. { rate_c_per_min = 0.05, hold_s = 300 }"))

    @model_validator(mode="after")
    def _roll_stated(self):
        """A package's roll in use is part of what its certificate states: a single sensor cannot infer
        roll, so it must say how roll is obtained; a measured roll brings its σ_R, and only then."""
        roll = self.roll_source
        if roll is None:
            raise ValueError("a single-axis package cannot infer roll: state roll_in_use = \"none\" (pitch "
                             "at roll 0), \"table\" or \"sensor\" (roll measured independently, with "
                             "roll_sd_deg)")
        if roll == "none" and self.package != "single-axis":
            raise ValueError(f"roll_in_use = \"none\" is for a single-axis package; a {self.package} package "
                             "infers roll or is used at a measured roll")
        measured = roll in ("table", "sensor")
        if measured and self.roll_sd_deg is None:
            raise ValueError(f"roll_in_use = \"{roll}\" needs roll_sd_deg, the measured roll's standard "
                             "deviation (°)")
        if not measured and self.roll_sd_deg is not None:
            raise ValueError("roll_sd_deg is for a roll measured by the table or a sensor, not "
                             f"roll_in_use = \"{roll}\"")
        return self

    @property
    def axes(self) -> tuple[int, ...]:
        """The output columns (0 x, 1 y, 2 z) of the sensors the package has, a DMM channel each."""
        return tuple("xyz".index(a) for a in PACKAGES[self.package])

    @property
    def roll_source(self) -> str | None:
        """roll_in_use as given, else inferred for a package of two or three axes."""
        if self.roll_in_use is not None:
            return self.roll_in_use
        return None if self.package == "single-axis" else "inferred"

    @field_validator("units", mode="before")
    @classmethod
    def _spelled(cls, value: object) -> object:
        """"millivolts", "m/s^2", "LSB": spelled as a readings file's ``# units =`` line may be."""
        if not isinstance(value, str):
            return value
        try:
            return unit_named(value, "units")
        except LabcalError:
            raise ValueError(f"{value!r} is not one of {', '.join(UNITS)}") from None


class StationFile(BaseModel):
    """A rig: the two tables, the DMM, how long to settle, and how to emulate it."""

    model_config = ConfigDict(extra="forbid")

    description: str = ""
    pitch: AxisConfig
    roll: AxisConfig
    dmm: DmmSettings
    instrument: InstrumentSettings = Field(default_factory=InstrumentSettings, description="the instrument "
                                           "under calibration: its output units and warm-up time")
    sequencer: SequencerSettings = Field(default_factory=SequencerSettings, description="read by `labcal "
                                         "run`: the sequencer's settings on this station (timeouts)")
    emulation: EmulationSettings = Field(default_factory=EmulationSettings, description="read by `labcal "
                                         "sim serve` and `--emulate`: time_scale, seed, [emulation.rig]")
    certificate: CertificateSettings = Field(default_factory=CertificateSettings, description="read by "
                                             "`labcal run` and `labcal report`: laboratory, tolerances")
    uncertainty: UncertaintyInputs = Field(default_factory=UncertaintyInputs, description="Type B inputs "
                                           "of the uncertainty budget, each with its unit")
    traceability: list[Traceability] = Field(default_factory=list, description="reference standards: "
                                             "certificate number and due date")
    standards: list[str] = Field(default_factory=list, description="serials of the lab's registered "
                                 "reference standards this station uses besides those registered to its "
                                 "bench (`labcal standard add SERIAL --bench NAME`); an overdue one stops a "
                                 "run")

    @model_validator(mode="after")
    def _buses(self):
        pitch, roll = self.pitch, self.roll
        if self.dmm.bus in (pitch.bus, roll.bus):
            raise ValueError(f"the DMM cannot share {self.dmm.where} with a table")
        if pitch.bus == roll.bus:
            if pitch.driver != roll.driver:
                raise ValueError(f"pitch and roll share {pitch.where} but not a driver")
            if pitch.line_settings() != roll.line_settings():
                raise ValueError(f"pitch and roll share {pitch.where}: give them the same line settings")
            if self.address(pitch) == self.address(roll):
                raise ValueError(f"pitch and roll share {pitch.where} and address {self.address(pitch)}")
        return self

    @model_validator(mode="after")
    def _channels_per_sensor(self):
        """The DMM reads one channel per sensor the package has: a channel more would be scanned
        and never journaled, a channel less would leave a sensor unread."""
        sensors = PACKAGES[self.instrument.package]
        if len(self.dmm.channels) != len(sensors):
            raise ValueError(f"[dmm] channels lists {len(self.dmm.channels)} channel(s) "
                             f"({', '.join(map(str, self.dmm.channels))}); the {self.instrument.package} "
                             f"package has {len(sensors)} sensor(s) ({', '.join(sensors)}): give one "
                             "channel each, in that order")
        return self

    @model_validator(mode="after")
    def _power_cycles(self):
        """The emulators switch off and on the DMM and an SMC100 controller (back NOT REFERENCED);
        an AZ drive's power cycle is not emulated."""
        for spec in self.emulation.faults:
            device = getattr(self, spec.device)
            if spec.kind == FaultKind.POWER_CYCLE and isinstance(device, AzSettings):
                raise ValueError(f"a power-cycle fault is emulated on the dmm and on SMC100 controllers, not "
                                 f"on the {spec.device} table's AZ drive")
        return self

    @staticmethod
    def address(axis: AzSettings | Smc100Settings) -> int:
        return axis.unit if isinstance(axis, AzSettings) else axis.address

    def devices(self) -> dict[str, LinkSettings]:
        return {"pitch": self.pitch, "roll": self.roll, "dmm": self.dmm}

    def identity_differences(self, new: StationFile, new_name: str, emulated: bool = False) -> list[str]:
        """How ``new`` is another bench than this one, a run's station: each identity field that
        differs, as ``pitch.steps_per_degree: 1000 in the run, 500 in new.toml``. Links, timeouts
        and retries may differ. For an emulated run the simulated rig is the bench too."""
        ours: dict[str, object] = {}
        theirs: dict[str, object] = {}
        for name in ("pitch", "roll", "dmm"):
            device, other = getattr(self, name), getattr(new, name)
            for field in device.IDENTITY if device.driver == other.driver else ("driver",):
                ours[f"{name}.{field}"] = getattr(device, field)
                theirs[f"{name}.{field}"] = getattr(other, field)
        # which sensors the DMM's channels read: the same channels wired to x, z are not x, y
        ours["instrument.package"] = self.instrument.package
        theirs["instrument.package"] = new.instrument.package
        if emulated:
            ours.update(leaves(self.emulation.rig.model_dump(mode="json"), "emulation.rig"))
            theirs.update(leaves(new.emulation.rig.model_dump(mode="json"), "emulation.rig"))
        return [f"{key}: {spelled(ours.get(key))} in the run, {spelled(theirs.get(key))} in {new_name}"
                for key in dict.fromkeys([*ours, *theirs]) if ours.get(key) != theirs.get(key)]


def spelled(value: object) -> str:
    """A setting's value as a station file spells it: 1000, [101, 102, 103], true, none."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, list | tuple):
        return f"[{', '.join(spelled(item) for item in value)}]"
    return str(value)


def leaves(tree: dict, prefix: str) -> dict[str, object]:
    """A nested table's values by dotted name (lists are values)."""
    flat: dict[str, object] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            flat.update(leaves(value, f"{prefix}.{key}"))
        else:
            flat[f"{prefix}.{key}"] = value
    return flat


# DMMs that scan their channels through one ADC: their gain error is common to the three channels
SCANNING_DMMS = frozenset({"keysight-34970a"})


class DmmRange(BaseModel):
    model_config = ConfigDict(extra="ignore")

    driver: str | None = None
    range_v: float = 10.0
    nplc: float = 10.0

    def common_inputs(self, declared: Sequence[str] | None) -> tuple[str, ...]:
        """The Type B inputs common to the three channels: as declared, else the DMM gain of a
        scanning DMM."""
        if declared is not None:
            return tuple(declared)
        return ("dmm_reading",) if self.driver in SCANNING_DMMS else ()


class CertificateSection(BaseModel):
    """A station file read for what a certificate takes from it: the ``[certificate]`` table, the
    Type B inputs, the traceability entries, and the DMM range the "% of range" applies to."""

    model_config = ConfigDict(extra="ignore")

    description: str = ""
    certificate: CertificateSettings = Field(default_factory=CertificateSettings)
    uncertainty: UncertaintyInputs = Field(default_factory=UncertaintyInputs)
    traceability: list[Traceability] = Field(default_factory=list)
    dmm: DmmRange = Field(default_factory=DmmRange)
    instrument: InstrumentSettings = Field(default_factory=InstrumentSettings)


def load_certificate_settings(path: str | Path) -> CertificateSettings:
    """The ``[certificate]`` table of a station file. `labcal report` makes the documents of a
    finished run, often away from the bench whose devices the rest of the file describes: only
    this table is read, validated by the same model as when the whole station is read."""
    return load_certificate_section(path).certificate


def load_certificate_section(path: str | Path) -> CertificateSection:
    return parse_model(read_text(path, "station"), CertificateSection, str(path))


def shipped_stations() -> dict[str, resources.abc.Traversable]:
    """The example stations that ship with labcal, by name."""
    folder = resources.files("labcal.stations")
    entries = sorted(folder.iterdir(), key=lambda e: e.name)
    return {entry.name.removesuffix(".toml"): entry for entry in entries if entry.name.endswith(".toml")}


def load_station(name_or_path: str | Path) -> tuple[StationFile, str]:
    """A station file by path or by the name of a shipped example; returns it and its TOML text."""
    path = Path(name_or_path)
    if path.suffix == ".toml" or path.exists():
        text = read_text(path, "station")
        return parse_model(text, StationFile, str(path)), text
    examples = shipped_stations()
    if str(name_or_path) not in examples:
        raise LabcalError(f"unknown station {str(name_or_path)!r}; give a station file (.toml) or one of the "
                          f"examples: {', '.join(examples)}")
    text = examples[str(name_or_path)].read_text(encoding="utf-8")
    return parse_model(text, StationFile, f"station {name_or_path}"), text

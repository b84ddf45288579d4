"""The station a run journals (its snapshot), typed: parsed once, read by attribute.

A run's journal keeps, as JSON, the station it started on, so that a resume rebuilds the same one
and the documents say what the bench was. It is one of two kinds, told apart by ``kind``: labcal's
simulated rig (``"simulated rig"``: its rig-file settings and seed) or a station file's devices
(``"station"``: the file's settings, and whether they ran on the device emulators, at what time
scale and with what seed).

The settings stay as journaled (a plain document): an older journal lacks fields added since, and
a station that no longer validates must still be shown and issued from. Today's models validate
them where a reader needs their values (`SimulatedRigSnapshot.rig_config`,
`StationFileSnapshot.section`), their defaults filling what an older snapshot leaves out.
"""

from __future__ import annotations

import math
from functools import cached_property
from typing import TYPE_CHECKING, Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from labcal.config.emulation import RigConfig
from labcal.config.files import validate_model
from labcal.config.run_metadata import RunMetadata
from labcal.config.station import CertificateSection, StationFile
from labcal.config.uncertainty import UncertaintyInputs
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.analysis import device_fit
    from labcal.analysis.device_fit import AngleErrors
else:
    device_fit = lazy("labcal.analysis.device_fit")  # start-up without scipy, numpy


class SimulatedRigSnapshot(BaseModel):
    """The simulated rig of ``labcal run --sim``: its rig-file settings and the seed of its noise."""

    model_config = ConfigDict(frozen=True)

    kind: Literal["simulated rig"]
    rig: dict[str, Any] = Field(default_factory=dict)
    seed: int | None = None

    @property
    def simulated(self) -> bool:
        return True

    def rig_config(self) -> RigConfig:
        return validate_model(self.rig, RigConfig, "the journaled simulated rig")

    def simulator_rig(self) -> dict[str, Any] | None:
        """The rig settings whose physics made the readings."""
        return self.rig


class JournaledDevice(BaseModel):
    """One device of a journaled station file (its ``[pitch]``, ``[roll]`` or ``[dmm]``), as the
    documents and the run's checks read it: the settings they name, each None where an older
    journal's station lacks it, and every other setting kept as journaled."""

    model_config = ConfigDict(extra="allow", frozen=True)

    driver: str | None = None
    unit: int | str | None = None  # an AZ drive's Modbus unit
    address: int | str | None = None  # an SMC100's address on its RS-485 chain
    tcp: str | None = None  # host:port where the link is a socket
    port: str | None = None  # the serial port where it is a serial line
    in_position_arcsec: float | None = None  # a table's read-back tolerance
    range_v: float | None = None  # the DMM's range and integration time
    nplc: float | None = None


class StationFileSnapshot(BaseModel):
    """A station file's devices, through the drivers, on hardware or (``emulate``) on the emulators."""

    model_config = ConfigDict(frozen=True)

    kind: Literal["station"]
    station: dict[str, Any]
    emulate: bool = False
    time_scale: float | None = None  # the emulators' pace; None on hardware
    seed: int | None = None  # what drew the emulated rig's noise; None on hardware

    @property
    def simulated(self) -> bool:
        return self.emulate

    def section(self, where: str = "the run's station") -> CertificateSection:
        """What the certificate takes from the station file (``where``: how an error names it)."""
        return validate_model(self.station, CertificateSection, where)

    def device(self, role: str) -> JournaledDevice:
        """The station's ``role`` device (pitch, roll, dmm) as journaled (none: every setting None)."""
        return JournaledDevice.model_validate(self.station.get(role) or {})

    @cached_property
    def config(self) -> StationFile:
        """The whole station file, validated with today's model once (pydantic's ValidationError where
        it no longer validates: a resume names the field, `labcal.bench.setup.read_snapshot`)."""
        return StationFile.model_validate(self.station)

    def simulator_rig(self) -> dict[str, Any] | None:
        """The emulators' rig settings whose physics made the readings; None on hardware."""
        if not self.emulate:
            return None
        return (self.station.get("emulation") or {}).get("rig") or {}


StationSnapshot = Annotated[SimulatedRigSnapshot | StationFileSnapshot, Field(discriminator="kind")]
_SNAPSHOT: TypeAdapter[SimulatedRigSnapshot | StationFileSnapshot] = TypeAdapter(StationSnapshot)


def parse_snapshot(text: str | None) -> StationSnapshot | None:
    """A run's journaled station snapshot; None where there is none or the text is not one labcal
    wrote (a run journaled before snapshots were kept)."""
    if not text:
        return None
    try:
        return _SNAPSHOT.validate_json(text)
    except ValidationError:
        return None


def is_simulated(metadata: RunMetadata, snapshot: StationSnapshot | None) -> bool:
    """A dry run (the simulated rig or its emulators), by its metadata or its station snapshot: either
    is enough, so that a run folder's metadata edited cannot make the journal's station real."""
    if "simulated_truth" in metadata.model_fields_set:  # recorded, whatever its value
        return True
    return snapshot is not None and snapshot.simulated


def simulator_inputs(rig: dict, samples: int) -> UncertaintyInputs:
    """The Type B inputs the simulated ``rig`` really applies, for readings averaged over ``samples``
    samples (`labcal.documents.simulated` says how each is read): its tables' index and wobble
    amplitudes as the ± half-widths, the plate's seating σ as the rectangular half-width of the same
    variance (√3·σ), its noise per reading, its largest temperature coefficients."""
    config = RigConfig.model_validate(rig)  # defaults fill what an older snapshot leaves out
    device, inst = config.device, config.instrument
    arcsec = lambda x: f"{x!r} arcsec"  # noqa: E731 - the station file's own notation
    return UncertaintyInputs.model_validate({
        "pitch_index": arcsec(device.index_arcsec), "roll_index": arcsec(device.index_arcsec),
        "pitch_wobble": arcsec(device.wobble_arcsec), "roll_wobble": arcsec(device.wobble_arcsec),
        "mount_repeatability": arcsec(math.sqrt(3) * device.mount_repeat_arcsec),
        "dmm_noise": f"{inst.noise_v / math.sqrt(max(samples, 1))!r} V",
        "bias_tempco": f"{max(abs(x) for x in inst.tc_bias_v_per_c)!r} V/K",
        "sensitivity_tempco": f"{max(abs(x) for x in inst.tc_scale_per_c)!r} 1/K",
    })


def stated_angle_errors(snapshot: StationSnapshot | None) -> AngleErrors | None:
    """The tables' index accuracy and wobble for the device model's covariance: a station file's
    ``[uncertainty]`` table, or the simulated rig's own amplitudes (its errors are bounded by them:
    the half-widths). None where neither states any."""
    if isinstance(snapshot, StationFileSnapshot):
        u = snapshot.section().uncertainty
    elif isinstance(snapshot, SimulatedRigSnapshot):
        snapshot.rig_config()  # one line naming the field where the journaled rig no longer validates
        u = simulator_inputs(snapshot.rig, 1)
    else:
        return None
    errors = device_fit.AngleErrors(u.pitch_index, u.pitch_wobble, u.roll_index, u.roll_wobble)
    return errors if errors else None


def stated_mount_repeatability(snapshot: StationSnapshot | None) -> float:
    """The ± half-width (rad) of each of the plate's pitch, roll and yaw at a remount, as the station
    file's ``[uncertainty]`` states it, or the simulated rig's own seating scatter; 0 where unstated."""
    if isinstance(snapshot, StationFileSnapshot):
        u = snapshot.section().uncertainty
    elif isinstance(snapshot, SimulatedRigSnapshot):
        u = simulator_inputs(snapshot.rig, 1)
    else:
        return 0.0
    return float(u.mount_repeatability)


def output_units(snapshot: StationSnapshot | None) -> str:
    """The unit a run's outputs were read in: a station file's ``[instrument] units``; volts for the
    simulated rig and for runs journaled before the key."""
    if not isinstance(snapshot, StationFileSnapshot):
        return "V"
    return snapshot.section().instrument.units

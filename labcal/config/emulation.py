"""What a station file's ``[emulation]`` table and a ``--rig`` file say about the simulated rig:
the instrument's and the calibration device's truth, the rig's pace and lab, and the faults to
inject. Data only: the simulator (`labcal.sim`) gives it behaviour. It lives here, with the station
model, so that a station file is validated whole when it is read, emulation included.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator

from labcal.analysis.kinematics import MISALIGNMENT_NAMES, Misalignment
from labcal.analysis.packages import PACKAGES
from labcal.config.files import load_model


def coning_axes(omega: NDArray, azimuth: NDArray) -> NDArray:
    """Unit sensitive axes u_x, u_y, u_z as columns (3×3) from coning angles Ω and azimuths A (rad)."""
    (ox, oy, oz), (ax, ay, az) = np.asarray(omega, float), np.asarray(azimuth, float)
    ux = [np.cos(ox), -np.sin(ox) * np.cos(ax), -np.sin(ox) * np.sin(ax)]
    uy = [-np.sin(oy) * np.sin(ay), np.cos(oy), np.sin(oy) * np.cos(ay)]
    uz = [-np.sin(oz) * np.cos(az), np.sin(oz) * np.sin(az), np.cos(oz)]
    return np.column_stack([ux, uy, uz])


class InstrumentTruth(BaseModel):
    """True coefficients and imperfections. B in V; S (3×3) in V/g, column j = sensor j.

    Static model V = B + gᵀS (Soto eq. 4), or equivalently per sensor v = b + S·(u·g) with the
    coning unit vectors of docs/design.md §3 (Tripp eqs. 2, 4, 5). On top: a first-order low-pass
    output, white noise, slow offset drift and temperature coefficients."""

    model_config = ConfigDict(extra="forbid")

    B: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    S: list[list[float]] = Field(default=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    noise_v: float = Field(default=0.0, ge=0, description="white noise per sample, V rms")
    tau_s: float = Field(default=0.5, gt=0, description="first-order output time constant, s")
    drift_v_per_h: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    tc_bias_v_per_c: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    tc_scale_per_c: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    t_ref_c: float = 20.0
    package: Literal["three-axis", "two-axis-xy", "two-axis-xz", "single-axis"] = Field(
        default="three-axis", description="which of the three sensors the package has (Tripp & Tcheng "
        "§6.1–6.6: x; x, y; x, z; x, y, z): a DMM channel each, the others are not read")
    warmup_c: float = Field(default=0.0, description="the instrument's own heating above the lab at "
                            "switch-on, decaying with warmup_tau_s (a warm-up the thermal gate waits out)")
    warmup_tau_s: float = Field(default=1800.0, gt=0)

    @property
    def channels(self) -> tuple[int, ...]:
        """The columns (0 x, 1 y, 2 z) of the sensors the package has."""
        return tuple("xyz".index(a) for a in PACKAGES[self.package])

    @field_validator("S")
    @classmethod
    def _square(cls, s: list[list[float]]) -> list[list[float]]:
        if np.shape(s) != (3, 3):
            raise ValueError("S must be 3 rows of 3 numbers")
        if abs(np.linalg.det(np.array(s))) < 1e-12:
            raise ValueError("S is singular: the three sensors must not be coplanar")
        return s

    @classmethod
    def from_coning(cls, b: list[float], sensitivity: list[float], omega_deg: list[float],
                    azimuth_deg: list[float], **rest) -> InstrumentTruth:
        """Per-sensor offset b, sensitivity S, coning angle Ω and azimuth A (Tripp eq. 2)."""
        axes = coning_axes(np.radians(omega_deg), np.radians(azimuth_deg))
        return cls(B=list(b), S=(axes * np.asarray(sensitivity)[None, :]).tolist(), **rest)

    @property
    def X(self) -> NDArray:
        """The true coefficients in Soto's layout [Bᵀ; S] (4×3)."""
        return np.vstack([self.B, self.S])

    def static_volts(self, g: NDArray, elapsed_s: NDArray | float = 0.0,
                     temp_c: NDArray | float | None = None) -> NDArray:
        """Noise-free settled output for gravity g (..., 3) after ``elapsed_s`` at ``temp_c`` (each a
        number, or an array of the shape of g without its last axis: a scan of samples at once)."""
        dt = np.asarray(0.0 if temp_c is None else np.asarray(temp_c) - self.t_ref_c)[..., None]
        bias = np.asarray(self.B) + np.asarray(self.drift_v_per_h) * np.asarray(elapsed_s)[..., None] / 3600 \
            + np.asarray(self.tc_bias_v_per_c) * dt
        return bias + (np.asarray(g) @ np.asarray(self.S)) * (1 + np.asarray(self.tc_scale_per_c) * dt)


def default_instrument() -> InstrumentTruth:
    """A plausible servo-accelerometer package (~5 V/g) for dry runs: small coning, µV noise."""
    return InstrumentTruth.from_coning(
        b=[0.0123, -0.0081, 0.0047],
        sensitivity=[4.9871, 5.0124, 4.9958],
        omega_deg=[0.21, 0.14, 0.09],
        azimuth_deg=[35.0, -120.0, 200.0],
        noise_v=20e-6,
        tau_s=0.5,
        drift_v_per_h=[2e-6, -1e-6, 1.5e-6],
        tc_bias_v_per_c=[5e-6, -4e-6, 3e-6],
        tc_scale_per_c=[15e-6, 12e-6, -10e-6],
    )


class DeviceTruth(BaseModel):
    """The calibration device's true geometry (Soto Table 1). The default misalignments are a
    plausible machined two-axis device's, tens of arcseconds (36″, −18″, 25.2″, 43.2″, −28.8″,
    21.6″), with ±2″ index errors and wobble at every table angle: large enough that a dry run shows
    the device model estimating them, as the certificate then reports."""

    model_config = ConfigDict(extra="forbid")

    misalignment_deg: dict[str, float] = Field(
        default={"a": 0.010, "b": -0.005, "d": 0.007, "e": 0.012, "f": -0.008, "k": 0.006})
    index_arcsec: float = Field(default=2.0, ge=0)
    wobble_arcsec: float = Field(default=2.0, ge=0)
    mount_repeat_arcsec: float = Field(default=0.0, ge=0, description="plate tilt/yaw scatter per remount")

    @field_validator("misalignment_deg")
    @classmethod
    def _known(cls, angles: dict[str, float]) -> dict[str, float]:
        """Checked when the file is read, so a typo names the file and the table."""
        unknown = set(angles) - set(MISALIGNMENT_NAMES)
        if unknown:
            raise ValueError(f"unknown misalignment(s) {', '.join(sorted(unknown))}; use "
                             f"{', '.join(MISALIGNMENT_NAMES)}")
        return angles

    def misalignment(self) -> Misalignment:
        return Misalignment.from_degrees(**self.misalignment_deg)


class OutputSlip(BaseModel):
    """A table's output slipping against its motor: a clamp or a coupling gives way by ``degrees``
    at rig time ``at_s`` and is re-seated at ``until_s`` (None: not during the run). The drive's
    position sensor is on the motor (an AZ's ABZO sensor, an SMC100's encoder), so the table's
    position and status do not see it; only the instrument does."""

    model_config = ConfigDict(extra="forbid")

    table: Literal["pitch", "roll"]
    degrees: float
    at_s: float = Field(default=0.0, ge=0)
    until_s: float | None = Field(default=None, ge=0)
    at_point: str | None = Field(default=None, description="instead of at_s: as the window of this point "
                                 "begins (its key, 'SEQ:ATTEMPT', e.g. '6:1'), whenever that is")

    def offset(self, t: NDArray | float, at_s: float | None = None) -> NDArray:
        """The output's slip (degrees) at rig time(s) t; ``at_s``: when it slipped, if not ``self.at_s``."""
        t = np.asarray(t, dtype=float)
        start = self.at_s if at_s is None else at_s
        on = (t >= start) & (t < (np.inf if self.until_s is None else self.until_s))
        return np.where(on, self.degrees, 0.0)


class RigConfig(BaseModel):
    """Everything about the simulated rig; defaults describe a plausible lab."""

    model_config = ConfigDict(extra="forbid")

    device: DeviceTruth = DeviceTruth()
    instrument: InstrumentTruth = Field(default_factory=default_instrument)
    speed_dps: float = Field(default=20.0, gt=0)
    accel_dps2: float = Field(default=40.0, gt=0)
    clamp_s: float = Field(default=1.0, ge=0)
    nplc: float = Field(default=10.0, gt=0, description="DMM integration per sample, power-line cycles")
    line_hz: float = Field(default=50.0, gt=0)
    output_ohm: float = Field(default=5000.0, ge=0, description="the instrument outputs' source impedance, "
                              "which the DMM's input resistance loads (a servo-accelerometer's output "
                              "resistor, ~5 kΩ)")
    remount_s: float = Field(default=300.0, ge=0, description="operator time for one remount")
    slip_rings: bool = Field(default=False, description="--sim: the tables may turn without bound")
    cable_wrap_deg: float = Field(default=360.0, gt=0, le=36000, description="--sim: each table's "
                                  "accumulated rotation from home stays within ± this (a station's default)")
    lab_temp_c: float = 21.0
    lab_temp_swing_c: float = Field(default=0.3, ge=0)
    lab_temp_period_h: float = Field(default=6.0, gt=0)
    lab_temp_drift_c_per_h: float = Field(default=0.0, description="a steady rise (or fall) of the lab's "
                                          "temperature on top of its swing")
    seed: int = 0
    output_slips: list[OutputSlip] = Field(default_factory=list, description="faults: a table's output "
                                           "slipping against its motor, unseen by its drive")


def load_rig_config(path: str | Path) -> RigConfig:
    return load_model(path, RigConfig, "rig")


class FaultKind(StrEnum):
    """What goes wrong with a request to an emulated device (see `labcal.sim.faults`)."""

    NO_REPLY = "no-reply"
    LATE_REPLY = "late-reply"
    GARBLED = "garbled"
    ALARM = "alarm"
    EXCEPTION = "exception"
    CLOSE_PORT = "close-port"
    LOST_REQUEST = "lost-request"
    TRUNCATED = "truncated"
    POWER_CYCLE = "power-cycle"
    DROPPED_BYTE = "dropped-byte"


class FaultSpec(BaseModel):
    """A fault to inject from the start (``[[emulation.faults]]``): see `labcal.sim.faults`."""

    model_config = ConfigDict(extra="forbid")

    device: Literal["pitch", "roll", "dmm"]
    kind: FaultKind
    count: int = Field(default=1, ge=1)
    after: int = Field(default=0, ge=0, description="matching requests let through first")
    match: str | None = Field(default=None, description="regular expression on the request")
    delay_s: float = Field(default=1.0, ge=0)
    code: int | str | None = None
    reopen_s: float | None = Field(default=None, ge=0)



class EmulationSettings(BaseModel):
    """A station file's ``[emulation]`` table, read by `labcal sim serve` and ``--emulate``."""

    model_config = ConfigDict(extra="forbid")

    time_scale: float = Field(default=1.0, gt=0, le=1e5, description="rig time per second of wall time")
    seed: int | None = Field(default=None, description="the rig's random seed (default: the rig's own)")
    rig: RigConfig = Field(default_factory=RigConfig)
    faults: list[FaultSpec] = Field(default_factory=list)
    tables_exchanged: bool = Field(default=False, description="fault: the controller at each table's address "
                                   "drives the other table (a station file whose addresses are swapped "
                                   "against its devices; both answer alike)")

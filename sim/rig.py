"""The simulated calibration rig: device kinematics + instrument physics + tables + DMM.

It exposes the same `Station` the hardware drivers build, so the sequencer cannot tell.
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from labcal.analysis.kinematics import ARCSEC, IndexWobble, Misalignment, Mount, gravity
from labcal.config.files import load_model
from labcal.errors import LabcalError
from labcal.run.station import Scan, Station
from labcal.sim.clock import RigClock, VirtualClock
from labcal.sim.instrument import InstrumentTruth, default_instrument
from labcal.sim.tables import SimAxis


class DeviceTruth(BaseModel):
    """The calibration device's true geometry (Soto Table 1)."""

    model_config = ConfigDict(extra="forbid")

    misalignment_deg: dict[str, float] = Field(
        default={"a": 0.0012, "b": -0.0008, "d": 0.0005, "e": 0.0015, "f": -0.001, "k": 0.0009})
    index_arcsec: float = Field(default=2.0, ge=0)
    wobble_arcsec: float = Field(default=2.0, ge=0)
    mount_repeat_arcsec: float = Field(default=0.0, ge=0, description="plate tilt/yaw scatter per remount")

    def misalignment(self) -> Misalignment:
        unknown = set(self.misalignment_deg) - set("abdefk")
        if unknown:
            raise LabcalError(f"unknown misalignment(s) {', '.join(sorted(unknown))}; use a, b, d, e, f, k")
        return Misalignment.from_degrees(**self.misalignment_deg)


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
    remount_s: float = Field(default=300.0, ge=0, description="operator time for one remount")
    lab_temp_c: float = 21.0
    lab_temp_swing_c: float = Field(default=0.3, ge=0)
    lab_temp_period_h: float = Field(default=6.0, gt=0)
    seed: int = 0


def load_rig_config(path: str | Path) -> RigConfig:
    return load_model(path, RigConfig, "rig")


class SimRig:
    """Physics of the whole rig on a virtual clock."""

    measures_temperature = True  # the simulated DMM scans a lab thermometer too

    def __init__(self, config: RigConfig | None = None, seed: int | None = None,
                 clock: RigClock | None = None):
        """``clock``: the virtual clock of a dry run by default; protocol emulators pass a
        `ScaledClock` so that the physics runs in (scaled) wall time."""
        self.config = config = config or RigConfig()
        self.seed = config.seed if seed is None else seed
        self.clock: RigClock = clock or VirtualClock()
        sync = self._catch_up
        self.pitch = SimAxis("pitch", self.clock, config.speed_dps, config.accel_dps2, config.clamp_s, sync)
        self.roll = SimAxis("roll", self.clock, config.speed_dps, config.accel_dps2, config.clamp_s, sync)
        self.instrument: InstrumentTruth = config.instrument
        self.misalignment = config.device.misalignment()
        self.index_wobble = IndexWobble(config.device.index_arcsec, config.device.wobble_arcsec, self.seed)
        self._rng = np.random.default_rng([self.seed, 0x5EED])
        self._noise = np.random.default_rng([self.seed, 0x5A11])
        self.mount = Mount(0, 0)
        self._mount_error = Misalignment()
        self._gravity_key: tuple | None = None
        self._gravity = np.zeros(3)
        self._t_filter = 0.0
        self._g_filtered = self.true_gravity(0.0, 0.0)

    # --- physics -------------------------------------------------------------------------
    def true_gravity(self, pitch_deg: NDArray | float, roll_deg: NDArray | float) -> NDArray:
        """Gravity the sensors feel at these table angles, every misalignment included."""
        p, r = np.radians(pitch_deg), np.radians(roll_deg)
        y, u = self.mount.radians
        mis = self.misalignment + self._mount_error + self.index_wobble.misalignment(p, r)
        return gravity(p, r, y, u, mis)

    def _still_gravity(self, pitch_deg: float, roll_deg: float) -> NDArray:
        """`true_gravity`, remembered while the tables stand still and the mount is unchanged (a
        DMM scan asks the same question for every sample)."""
        key = (pitch_deg, roll_deg, self.mount, id(self._mount_error))
        if key != self._gravity_key:
            self._gravity_key, self._gravity = key, self.true_gravity(pitch_deg, roll_deg)
        return self._gravity

    def _catch_up(self) -> None:
        self._advance_filter(self.clock.now())

    def lab_temperature(self, t: float) -> float:
        c = self.config
        return c.lab_temp_c + c.lab_temp_swing_c * math.sin(2 * math.pi * t / (c.lab_temp_period_h * 3600))

    def _advance_filter(self, t: float) -> None:
        """Carry the instrument's first-order output response forward to time t.

        Exact for an input held constant over each step: x ← u + (x − u)·exp(−dt/τ). While a
        table moves the input is sampled at the midpoints of steps of τ/10.
        """
        t0, tau = self._t_filter, self.instrument.tau_s
        if t <= t0:
            return
        moving = self.pitch.moving_between(t0, t) or self.roll.moving_between(t0, t)
        if moving:
            t_still = min(t, max(self.pitch.motion_end, self.roll.motion_end))
            n = max(1, math.ceil((t_still - t0) / (tau / 10)))
            edges = np.linspace(t0, t_still, n + 1)
            mids = 0.5 * (edges[:-1] + edges[1:])
            inputs = self.true_gravity(self.pitch.angle_at(mids), self.roll.angle_at(mids))
            decay = math.exp(-(edges[1] - edges[0]) / tau)
            x = self._g_filtered
            for u in inputs:
                x = u + (x - u) * decay
            self._g_filtered, t0 = x, t_still
        u = self._still_gravity(float(self.pitch.angle_at(t)), float(self.roll.angle_at(t)))
        self._g_filtered = u + (self._g_filtered - u) * math.exp(-(t - t0) / tau)
        self._t_filter = t

    def read(self, n_samples: int) -> Scan:
        """n consecutive DMM samples (implements `labcal.station.Voltmeter`)."""
        t_int = self.config.nplc / self.config.line_hz
        times = np.empty(n_samples)
        for i in range(n_samples):
            times[i] = self.clock.now() + 0.5 * t_int
            self.clock.sleep(t_int)
        return self.sample_at(times)

    def sample_at(self, times: NDArray) -> Scan:
        """The instrument's outputs (noise included) and the lab temperature at the given rig
        times, which must not decrease and not precede earlier samples (the output filter only
        runs forward). Emulated DMMs sample each channel at its own time through this."""
        volts = np.empty((len(times), 3))
        temps = np.empty(len(times))
        for i, t in enumerate(times):
            self._advance_filter(t)
            temps[i] = self.lab_temperature(t)
            volts[i] = self.instrument.static_volts(self._g_filtered, t, temps[i])
        volts += self._noise.normal(0.0, self.instrument.noise_v, size=volts.shape)
        return Scan(volts=volts, temp_c=temps)

    def remounted(self, mount: Mount) -> None:
        """The simulated technician remounts the instrument; takes operator time."""
        self._catch_up()
        self.clock.sleep(self.config.remount_s)
        self.set_mount(mount)

    def set_mount(self, mount: Mount) -> None:
        """The instrument is now in ``mount`` (the operator's time is not the rig's business)."""
        self._catch_up()
        self.mount = mount
        scatter = self.config.device.mount_repeat_arcsec * ARCSEC
        if scatter:
            e, f, k = self._rng.normal(0.0, scatter, 3)
            self._mount_error = Misalignment(e=e, f=f, k=k)
        self._t_filter = self.clock.now()
        self._g_filtered = self.true_gravity(self.pitch.position(), self.roll.position())

    def at_point(self, key: str) -> None:
        """Draw this point's noise from the seed and the point's identity, not from one stream, so
        that a resumed run measures every point as the uninterrupted run would have."""
        self._noise = np.random.default_rng([self.seed, zlib.crc32(key.encode())])

    def station(self) -> Station:
        return Station(pitch=self.pitch, roll=self.roll, dmm=self, clock=self.clock,
                       remounted=self.remounted, at_point=self.at_point, description="simulated rig")

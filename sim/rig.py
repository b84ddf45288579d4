"""The simulated calibration rig: device kinematics + instrument physics + tables + DMM.

It exposes the same `Station` the hardware drivers build, so the sequencer cannot tell.
"""

from __future__ import annotations

import math
import zlib

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import ARCSEC, IndexWobble, Misalignment, Mount, gravity
from labcal.config.emulation import InstrumentTruth, RigConfig
from labcal.devices.station import Scan, Station
from labcal.devices.winding import Reach
from labcal.sim.clock import RigClock, VirtualClock
from labcal.sim.tables import SimAxis


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
        reach = Reach.of(None if config.slip_rings else config.cable_wrap_deg)
        pace = (config.speed_dps, config.accel_dps2, config.clamp_s)
        self.pitch = SimAxis("pitch", self.clock, *pace, sync, reach)
        self.roll = SimAxis("roll", self.clock, *pace, sync, reach)
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
        self._slipped: dict[int, float] = {}  # when each output slip keyed to a point happened

    # --- physics -------------------------------------------------------------------------
    def true_gravity(self, pitch_deg: NDArray | float, roll_deg: NDArray | float) -> NDArray:
        """Gravity the sensors feel at these table angles, every misalignment included."""
        p, r = np.radians(pitch_deg), np.radians(roll_deg)
        y, u = self.mount.radians
        mis = self.misalignment + self._mount_error + self.index_wobble.misalignment(p, r)
        return gravity(p, r, y, u, mis)

    def output_angles(self, t: NDArray | float) -> tuple[NDArray, NDArray]:
        """Where the tables' outputs are at rig time(s) t: their motors' angles plus any slip of a
        clamp or coupling (`RigConfig.output_slips`), which the drives do not see."""
        pitch, roll = self.pitch.angle_at(t), self.roll.angle_at(t)
        for i, slip in enumerate(self.config.output_slips):
            at = self._slipped.get(i, math.inf) if slip.at_point is not None else None
            if slip.table == "pitch":
                pitch = pitch + slip.offset(t, at)
            else:
                roll = roll + slip.offset(t, at)
        return pitch, roll

    def _still_gravity(self, pitch_deg: float, roll_deg: float) -> NDArray:
        """`true_gravity`, remembered while the tables stand still and the mount is unchanged (a
        DMM scan asks the same question for every sample)."""
        key = (pitch_deg, roll_deg, self.mount, id(self._mount_error))
        if key != self._gravity_key:
            self._gravity_key, self._gravity = key, self.true_gravity(pitch_deg, roll_deg)
        return self._gravity

    def _catch_up(self) -> None:
        self._advance_filter(self.clock.now())

    def lab_temperature(self, t: NDArray | float) -> NDArray | float:
        """The instrument's temperature at rig time t: the lab's (its daily swing and any steady
        drift) plus the instrument's own warm-up since switch-on at rig time 0, decaying
        exponentially."""
        c, inst = self.config, self.instrument
        lab = c.lab_temp_c + c.lab_temp_swing_c * np.sin(2 * math.pi * t / (c.lab_temp_period_h * 3600)) \
            + c.lab_temp_drift_c_per_h * np.asarray(t) / 3600
        return lab + inst.warmup_c * np.exp(-np.asarray(t) / inst.warmup_tau_s) if inst.warmup_c else lab

    def _advance_filter(self, t: float) -> None:
        """Carry the instrument's first-order output response forward to time t.

        Exact for an input held constant over each step: x ← u + (x − u)·exp(−dt/τ). While a
        table moves the input is sampled at the midpoints of steps of τ/10.

        The number of steps must not depend on where the rig's clock stands: a 5 s motion is 100
        steps whether it ends at rig time 1400 s or 2049 s, where (t_still − t0)/(τ/10) rounds to
        100.0000000000045 and a bare ceil made it 101, a grid whose midpoint-rule error differs by
        ~3e-11 V in the next window mean; a resumed run, whose clock runs on from another instant,
        then measured a point otherwise than the uninterrupted run (the soak, point 44). So a
        quotient within rounding (1e-9 step) of a whole number is that number.
        """
        t0, tau = self._t_filter, self.instrument.tau_s
        if t <= t0:
            return
        moving = self.pitch.moving_between(t0, t) or self.roll.moving_between(t0, t)
        if moving:
            t_still = min(t, max(self.pitch.motion_end, self.roll.motion_end))
            n = max(1, math.ceil((t_still - t0) / (tau / 10) - 1e-9))  # not the clock's rounding
            edges = np.linspace(t0, t_still, n + 1)
            mids = 0.5 * (edges[:-1] + edges[1:])
            inputs = self.true_gravity(*self.output_angles(mids))
            decay = math.exp(-(edges[1] - edges[0]) / tau)
            x = self._g_filtered
            for u in inputs:
                x = u + (x - u) * decay
            self._g_filtered, t0 = x, t_still
        u = self._still_gravity(*(float(a) for a in self.output_angles(t)))
        self._g_filtered = u + (self._g_filtered - u) * math.exp(-(t - t0) / tau)
        self._t_filter = t

    def read(self, n_samples: int) -> Scan:
        """n consecutive DMM samples (implements `labcal.devices.station.Voltmeter`)."""
        t_int = self.config.nplc / self.config.line_hz
        times = self.clock.now() + (np.arange(n_samples) + 0.5) * t_int
        self.clock.sleep(n_samples * t_int)
        return self.sample_at(times)

    def sample_at(self, times: NDArray) -> Scan:
        """The instrument's outputs (noise included) and the lab temperature at the given rig
        times, which must not decrease and not precede earlier samples (the output filter only
        runs forward). Emulated DMMs sample each channel at its own time through this."""
        times = np.asarray(times, dtype=float)
        if len(times) and not (self.pitch.moving_between(self._t_filter, times[-1])
                               or self.roll.moving_between(self._t_filter, times[-1])):
            return self._still_scan(times)
        volts = np.empty((len(times), 3))
        temps = np.empty(len(times))
        for i, t in enumerate(times):
            self._advance_filter(t)
            temps[i] = self.lab_temperature(t)
            volts[i] = self.instrument.static_volts(self._g_filtered, t, temps[i])
        volts += self._noise.normal(0.0, self.instrument.noise_v, size=volts.shape)
        return Scan(volts=self._package(volts), temp_c=temps)

    def _package(self, volts: NDArray) -> NDArray:
        """The outputs as the DMM reads them: a package's absent sensors have no channel, NaN
        (drawn and discarded, so that a package's present channels see the noise of the three-axis
        instrument's at the same seed)."""
        absent = [i for i in range(3) if i not in self.instrument.channels]
        volts[:, absent] = np.nan
        return volts

    def _still_scan(self, times: NDArray) -> Scan:
        """`sample_at` while both tables stand still, in closed form: the output relaxes towards the
        still gravity u as u + (x − u)·e^{−(t − t₀)/τ}, every sample at once."""
        self._advance_filter(float(times[0]))
        u = self._still_gravity(*(float(a) for a in self.output_angles(times[0])))
        fade = np.exp(-(times - times[0]) / self.instrument.tau_s)[:, None]
        outputs = u + (self._g_filtered - u) * fade
        self._g_filtered, self._t_filter = outputs[-1], float(times[-1])
        temps = np.asarray(self.lab_temperature(times), dtype=float)
        volts = self.instrument.static_volts(outputs, times, temps)
        volts += self._noise.normal(0.0, self.instrument.noise_v, size=volts.shape)
        return Scan(volts=self._package(volts), temp_c=temps)

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
        self._g_filtered = self.true_gravity(*self.output_angles(self.clock.now()))

    def at_point(self, key: str) -> None:
        """Draw this point's noise from the seed and the point's identity, not from one stream, so
        that a resumed run measures every point as the uninterrupted run would have."""
        self._noise = np.random.default_rng([self.seed, zlib.crc32(key.encode())])
        for i, slip in enumerate(self.config.output_slips):
            if slip.at_point == key and i not in self._slipped:
                self._catch_up()
                self._slipped[i] = self.clock.now()

    def station(self) -> Station:
        return Station(pitch=self.pitch, roll=self.roll, dmm=self, clock=self.clock,
                       remounted=self.remounted, at_point=self.at_point, description="simulated rig")

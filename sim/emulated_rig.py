"""The simulated rig as the emulators share it: physics in scaled wall time, behind one lock.

Each emulator serves its port from its own thread; they all move and read the same tables and
instrument, so every access to the rig holds `lock` (briefly: nobody sleeps while holding it).
"""

from __future__ import annotations

import threading

from labcal.analysis.kinematics import Mount
from labcal.config.emulation import RigConfig
from labcal.sim.clock import ScaledClock
from labcal.sim.rig import SimRig
from labcal.sim.tables import SimAxis


class EmulatedRig:
    def __init__(self, config: RigConfig | None = None, time_scale: float = 1.0, seed: int | None = None,
                 start_s: float = 0.0):
        self.clock = ScaledClock(time_scale, start_s)
        self.rig = SimRig(config, seed=seed, clock=self.clock)
        self.lock = threading.RLock()

    @property
    def time_scale(self) -> float:
        return self.clock.scale

    def axis(self, name: str) -> SimAxis:
        return {"pitch": self.rig.pitch, "roll": self.rig.roll}[name]

    def set_mount(self, mount: Mount) -> None:
        """The operator has remounted the instrument (the remount callback of an emulated station)."""
        with self.lock:
            self.rig.set_mount(mount)

"""Index-table motion: trapezoidal velocity profile, shortest way round, then a clamp delay."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from labcal.errors import LabcalError
from labcal.run.motion import trapezoid_duration, trapezoid_travel
from labcal.sim.clock import RigClock

__all__ = ["SimAxis", "trapezoid_duration", "trapezoid_travel"]  # the tables move by labcal's profile


class SimAxis:
    """A simulated index table on the rig's clock (implements `labcal.station.RotaryAxis`)."""

    def __init__(self, name: str, clock: RigClock, speed_dps: float = 20.0,
                 accel_dps2: float = 40.0, clamp_s: float = 1.0,
                 before_move: Callable[[], None] = lambda: None):
        self.name = name
        self._before_move = before_move  # lets the rig integrate its physics up to the move
        self.clock = clock
        self.speed, self.accel, self.clamp_s = speed_dps, accel_dps2, clamp_s
        self._start_angle = 0.0  # continuous (unwrapped) angle at the start of the last move
        self._distance = 0.0
        self._t_start = -math.inf
        self._t_motion_end = -math.inf
        self.travel_deg = 0.0

    def angle_at(self, t: NDArray | float) -> NDArray:
        """True table angle (deg, unwrapped) at time(s) t."""
        return self._start_angle + trapezoid_travel(np.asarray(t) - self._t_start, self._distance,
                                                    self.speed, self.accel)

    def moving_between(self, t0: float, t1: float) -> bool:
        return t0 < self._t_motion_end and t1 > self._t_start

    @property
    def motion_end(self) -> float:
        return self._t_motion_end

    def move_to(self, angle_deg: float, way: str = "shortest") -> None:
        """Start a move: the ``shortest`` way round (angles mod 360), ``direct`` to the unwrapped
        angle (a table with limits), or ``forward`` / ``reverse`` round (emulated drives need all)."""
        self._before_move()
        now = self.clock.now()
        current = float(self.angle_at(now))
        delta = {"shortest": (angle_deg - current + 180.0) % 360.0 - 180.0,
                 "direct": angle_deg - current,
                 "forward": (angle_deg - current) % 360.0,
                 "reverse": -((current - angle_deg) % 360.0)}[way]
        self._start_angle, self._distance, self._t_start = current, delta, now
        self._t_motion_end = now + float(trapezoid_duration(delta, self.speed, self.accel))
        self.travel_deg += abs(delta)

    def wait_in_position(self, timeout_s: float) -> float:
        ready = self._t_motion_end + self.clamp_s
        if ready - self.clock.now() > timeout_s:
            raise LabcalError(f"{self.name} table not in position within {timeout_s:g} s")
        self.clock.advance_to(ready)
        return self.position()

    def position(self) -> float:
        return float(self.angle_at(self.clock.now())) % 360.0

    def send_stop(self) -> None:
        """A simulated table takes its stop at once: `stop` then finds it still."""
        self._halt()

    def stop(self) -> None:
        self._halt()

    def _halt(self) -> None:
        now = self.clock.now()
        if now < self._t_motion_end:  # freeze where it is (an instant stop is enough for a sim)
            here = float(self.angle_at(now))
            self._start_angle, self._distance, self._t_start, self._t_motion_end = here, 0.0, now, now

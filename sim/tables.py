"""Index-table motion: trapezoidal velocity profile, the way round it is told (the shortest by
default), then a clamp delay. A table's angle is continuous (unwrapped): it is its accumulated
rotation from home, what its cables feel, and `SimAxis.record` keeps every turning point of it."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from labcal.devices.station import TableState
from labcal.devices.winding import Reach
from labcal.errors import LabcalError
from labcal.run.motion import trapezoid_duration, trapezoid_travel
from labcal.sim.clock import RigClock

__all__ = ["SimAxis", "trapezoid_duration", "trapezoid_travel"]  # the tables move by labcal's profile


class SimAxis:
    """A simulated index table on the rig's clock (implements `labcal.devices.station.RotaryAxis`)."""

    def __init__(self, name: str, clock: RigClock, speed_dps: float = 20.0,
                 accel_dps2: float = 40.0, clamp_s: float = 1.0,
                 before_move: Callable[[], None] = lambda: None, reach: Reach | None = None):
        self.name = name
        self.reach = reach or Reach()  # what labcal is told of its cables (the simulator never refuses)
        self._before_move = before_move  # lets the rig integrate its physics up to the move
        self.clock = clock
        self.speed, self.accel, self.clamp_s = speed_dps, accel_dps2, clamp_s
        self._start_angle = 0.0  # continuous (unwrapped) angle at the start of the last move
        self._distance = 0.0
        self._t_start = -math.inf
        self._t_motion_end = -math.inf
        self.travel_deg = 0.0
        self.tolerance_arcsec = 5.0  # as a station's in_position_arcsec by default
        self._target: float | None = None
        self._slip = (0.0, math.inf, 0.0)  # (start time, duration, degrees): a drift no move commanded
        self._brake: tuple[float, float, float] | None = None  # a decelerating stop: (start, angle, speed)
        # (time, unwrapped angle) where each move began and where it ended or was stopped: a
        # trapezoid is monotonic, so these hold the extremes of the table's accumulated rotation
        self.record: list[tuple[float, float]] = [(clock.now(), 0.0)]

    def place(self, angle_deg: float) -> None:
        """Put the table at rest at this accumulated angle (a resumed run's tables stayed where the
        interrupted one left them; the simulator starts afresh)."""
        self._start_angle, self._distance = angle_deg, 0.0
        self._target, self._brake, self._slip = None, None, (0.0, math.inf, 0.0)
        self.record = [(self.clock.now(), angle_deg)]

    def angle_at(self, t: NDArray | float) -> NDArray:
        """True table angle (deg, unwrapped) at time(s) t."""
        t = np.asarray(t)
        t0, duration, slip_deg = self._slip
        slipped = slip_deg * np.clip((t - t0) / duration, 0.0, 1.0) if slip_deg else 0.0
        if self._brake is not None:  # v·τ − a·τ²/2 until the speed is spent
            start, here, v = self._brake
            tau = np.clip(t - start, 0.0, abs(v) / self.accel)
            return here + v * tau - math.copysign(0.5 * self.accel, v) * tau**2 + slipped
        return self._start_angle + trapezoid_travel(t - self._t_start, self._distance, self.speed,
                                                    self.accel) + slipped

    def slip(self, degrees: float, duration_s: float) -> None:
        """The table creeps ``degrees`` over ``duration_s`` from now, though nothing commanded it (a
        slipping coupling, a servo pushed off its position): what a fault scenario injects. The next
        move starts from where the creep left it."""
        self._slip = (self.clock.now(), max(duration_s, 1e-9), degrees)

    def moving_between(self, t0: float, t1: float) -> bool:
        return t0 < self._t_motion_end and t1 > self._t_start

    @property
    def motion_end(self) -> float:
        return self._t_motion_end

    def move_to(self, angle_deg: float, way: str = "shortest", *, travel_deg: float | None = None) -> None:
        """Start a move: the ``shortest`` way round (angles mod 360), ``direct`` to the unwrapped
        angle (a table with limits), or ``forward`` / ``reverse`` round (emulated drives need all);
        or by ``travel_deg``, the turn labcal chose, to the equivalent of the angle nearest it."""
        self._before_move()
        now = self.clock.now()
        current = float(self.angle_at(now))
        self._brake = None
        if travel_deg is not None:
            delta = angle_deg + 360.0 * round((current + travel_deg - angle_deg) / 360.0) - current
        else:
            delta = {"shortest": (angle_deg - current + 180.0) % 360.0 - 180.0,
                     "direct": angle_deg - current,
                     "forward": (angle_deg - current) % 360.0,
                     "reverse": -((current - angle_deg) % 360.0)}[way]
        self._start_angle, self._distance, self._t_start = current, delta, now
        self._slip, self._target = (0.0, math.inf, 0.0), current + delta
        self._t_motion_end = now + float(trapezoid_duration(delta, self.speed, self.accel))
        self.travel_deg += abs(delta)
        self.record += [(now, current), (self._t_motion_end, current + delta)]

    def wait_in_position(self, timeout_s: float) -> float:
        ready = self._t_motion_end + self.clamp_s
        if ready - self.clock.now() > timeout_s:
            raise LabcalError(f"{self.name} table not in position within {timeout_s:g} s")
        self.clock.advance_to(ready)
        return self.position()

    def position(self) -> float:
        return float(self.angle_at(self.clock.now())) % 360.0

    def winding(self) -> None:
        """The simulated tables report no turns, as AZ drives with their wrap setting on: the
        journal's moves say which turn they are on (what a dry run then exercises)."""
        return None

    def window_opens(self) -> None:
        """A simulated table has no faults to remember."""

    def prepare(self) -> None:
        """A simulated table never loses its reference: nothing to do."""

    def state(self) -> TableState:
        now = self.clock.now()
        here = float(self.angle_at(now))
        off = None if self._target is None else ((here - self._target + 180.0) % 360.0 - 180.0) * 3600.0
        moving, in_position = now < self._t_motion_end, now >= self._t_motion_end + self.clamp_s
        return TableState(f"{self.name} table (simulated)", None, moving, in_position, here % 360.0, off,
                          self.tolerance_arcsec, "moving" if moving else "in position" if in_position
                          else "clamping")

    def send_stop(self) -> None:
        """A simulated table takes its stop at once: `stop` then finds it still."""
        self._halt()

    def stop(self) -> None:
        self._halt()

    def decelerate(self) -> None:
        """A decelerating stop, as a drive's STOP input and an SMC100's ``ST`` make one: from the
        speed it has now the table slows at its acceleration, and is still only once that is spent."""
        now = self.clock.now()
        if now >= self._t_motion_end:
            return
        self._before_move()
        h = 1e-6  # the speed now, by a central difference (exact on each parabolic piece of the profile)
        speed = float(self.angle_at(now + h) - self.angle_at(now - h)) / (2 * h)
        here = float(self.angle_at(now))
        self._slip = (0.0, math.inf, 0.0)  # the creep so far is in ``here``
        self._brake = (now, here, speed)
        self._t_motion_end = now + abs(speed) / self.accel
        self.record[-1] = (self._t_motion_end, here + speed * abs(speed) / (2 * self.accel))

    def _halt(self) -> None:
        now = self.clock.now()
        if now < self._t_motion_end:  # freeze where it is (an instant stop is enough for a sim)
            here = float(self.angle_at(now))
            self._brake = None
            self._start_angle, self._distance, self._t_start, self._t_motion_end = here, 0.0, now, now
            self.record[-1] = (now, here)
            self._slip = (0.0, math.inf, 0.0)  # the creep so far is in ``here``

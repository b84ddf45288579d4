"""A virtual clock: a dry run takes seconds of wall time while accounting real-rig time."""

import time
from typing import Protocol


class RigClock(Protocol):
    """What the simulated rig and its tables need of a clock: `labcal.devices.station.Clock`, and a
    way to let time pass up to a given instant. `VirtualClock`, `PacedClock` and `ScaledClock` are."""

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...

    def advance_to(self, t: float) -> None: ...


class VirtualClock:
    def __init__(self, start: float = 0.0):
        self._t = start

    def now(self) -> float:
        return self._t

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._t += seconds

    def advance_to(self, t: float) -> None:
        self._t = max(self._t, t)


class PacedClock(VirtualClock):
    """A virtual clock that never runs ahead of wall time × ``pace`` (`labcal run --sim --pace X`:
    1 = a rig second takes a wall second, 10 = ten times faster): each sleep first waits, on the wall's
    clock, until the rig may be at its end, then moves rig time there. The rig's physics and readings
    are the virtual clock's, so a paced run measures what an unpaced one with the same seed does.

    Time the rig spends waiting for a person (a prompt, where the virtual clock stands still) is not
    made up afterwards by running faster than the pace: once the rig is more than ``CATCH_UP_S`` of
    wall time behind, the pace counts again from where it is."""

    CATCH_UP_S = 0.5

    def __init__(self, pace: float, start: float = 0.0):
        if not pace > 0:
            raise ValueError("pace must be > 0")
        super().__init__(start)
        self.pace = pace
        self._anchor: tuple[float, float] | None = None  # (wall, rig) from which the pace counts

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self._wait_until(self._t + seconds)

    def advance_to(self, t: float) -> None:
        if t > self._t:
            self._wait_until(t)

    def _wait_until(self, t: float) -> None:
        wall = time.monotonic()
        wall0, rig0 = self._anchor or (wall, self._t)  # from the rig's first motion, not from its making
        if wall0 + (self._t - rig0) / self.pace < wall - self.CATCH_UP_S:  # far behind: count from here
            wall0, rig0 = wall, self._t
        self._anchor = (wall0, rig0)
        due = wall0 + (t - rig0) / self.pace
        while (left := due - time.monotonic()) > 0:
            time.sleep(left)
        self._t = t


class ScaledClock:
    """Rig time that runs at wall time × ``scale``: emulators serve real bytes in real time while
    the rig's motion, settling and integration times shrink by the scale factor."""

    def __init__(self, scale: float = 1.0, start: float = 0.0):
        if not scale > 0:
            raise ValueError("time scale must be > 0")
        self.scale = scale
        self._start = start
        self._wall0 = time.monotonic()

    def now(self) -> float:
        return self._start + (time.monotonic() - self._wall0) * self.scale

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.scale)

    def advance_to(self, t: float) -> None:
        self.sleep(t - self.now())

"""A virtual clock: a dry run takes seconds of wall time while accounting real-rig time."""

import time
from typing import Protocol


class RigClock(Protocol):
    """What the simulated rig and its tables need of a clock: `labcal.run.station.Clock`, and a
    way to let time pass up to a given instant. `VirtualClock` and `ScaledClock` both are one."""

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

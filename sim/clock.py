"""A virtual clock: a dry run takes seconds of wall time while accounting real-rig time."""


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

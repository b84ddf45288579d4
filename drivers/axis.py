"""What every index-table driver shares: soft limits, cable wrap, which way round, waiting, and
read-back.

A driver supplies four device exchanges (status, angle, go to an absolute angle, halt); this base
turns them into `labcal.devices.station.RotaryAxis`. A move is checked against the table's reach (its soft
limits and its cable wrap, `labcal.devices.winding`) before anything is sent, goes the way round the
caller chose (``travel_deg``), and is only over when the device reports it in position *and* the
position read back lies within the tolerance of the target.
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from dataclasses import dataclass

from labcal.devices.station import Clock, TableState
from labcal.devices.winding import Reach
from labcal.drivers.errors import DeviceFault, OutOfLimits

log = logging.getLogger(__name__)
ARCSEC_PER_DEG = 3600.0
START_GRACE_S = 1.0  # a device may report its old in-position state this long after a move starts
STALL_S = 2.0  # still, short of its target and not in position this long: stalled, not settling


@dataclass(frozen=True)
class AxisStatus:
    """A table's state in the driver's terms, whatever the device's own words."""

    ready: bool  # would accept a move
    moving: bool
    in_position: bool  # stopped, clamped and settled
    fault: str | None  # what is wrong, in words; None when healthy
    words: str  # the device's own status, for people ("READY IN-POS", "READY from MOVING (33h)")
    needs_homing: bool = False  # the fault is only that the table is not referenced (a run homes it)


def wrapped(delta_deg: float) -> float:
    """An angle difference folded into [-180, 180)."""
    return (delta_deg + 180.0) % 360.0 - 180.0


class IndexAxis(ABC):
    """An index table behind `labcal.devices.station.RotaryAxis`."""

    model = "index table"
    counts_turns = True  # its angle is unwrapped: its accumulated rotation from home (an AZ with wrap: not)

    def __init__(self, name: str, where: str, clock: Clock, *, limits_deg: tuple[float, float] | None,
                 tolerance_arcsec: float, poll_s: float, cable_wrap_deg: float | None = None):
        self.name = name
        self.device = f"{name} table ({self.model}, {where})"
        self.clock = clock
        self.limits = limits_deg
        self.cable_wrap_deg = cable_wrap_deg  # None: slip rings
        self.reach = Reach.of(cable_wrap_deg, limits_deg)
        self.tolerance_arcsec = tolerance_arcsec
        self.poll_s = poll_s
        self._target: float | None = None
        self._window: object | None = None  # the device's fault memory as the window opened (`window_opens`)
        self.commanded = False  # this process has told the table to move (a move, a homing)

    # --- the device's part ------------------------------------------------------------------
    @abstractmethod
    def status(self) -> AxisStatus:
        """Read the device's status."""

    @abstractmethod
    def angle(self) -> float:
        """The device's position in degrees, unwrapped where the device counts turns."""

    @abstractmethod
    def _go(self, target_deg: float, travel_deg: float = 0.0) -> None:
        """Start an absolute move to ``target_deg`` (unwrapped, already within the limits), turning
        by ``travel_deg`` from where the device said it was (the way round, for a wrapping drive)."""

    @abstractmethod
    def _halt(self) -> None:
        """Tell the device to stop, and make sure it took the stop (retried where safe)."""

    @abstractmethod
    def send_stop(self) -> None:
        """Put a stop on the line once, waiting for no acknowledgement and retrying nothing, so that
        the other table's stop follows at once whatever this device does (`stop` confirms it)."""

    @abstractmethod
    def identify(self) -> str:
        """Who answers, in words (model, address, firmware where the device says)."""

    def _fault_memory(self) -> object | None:
        """What the device keeps of its faults, read now (an alarm history, a controller state);
        None where it keeps nothing."""
        return None

    def _fault_since(self, memory: object, status: AxisStatus) -> str | None:
        """The fault the device remembers since it kept ``memory`` (`_fault_memory`), in words;
        None when it remembers none. ``status``: the status just read."""
        return None

    def not_ready_why(self) -> str:
        """What keeps a table without a fault from being ready, where its controller can say
        ("; its STOP input is on ..."); empty when it cannot."""
        return ""

    def prepare(self) -> None:
        """Make the table ready for a run (home it, enable it); refuses when it reports a fault."""
        status = self.status()
        if status.fault:
            raise DeviceFault(status.fault, self.device)

    # --- shared logic -----------------------------------------------------------------------
    def check_angle(self, angle_deg: float) -> float:
        """The angle equivalent to ``angle_deg`` (mod 360) within the table's reach nearest to it;
        raises `OutOfLimits` when there is none. No I/O: plans are checked with it before anything moves."""
        if self.limits is not None and Reach.of(None, self.limits).nearest(angle_deg, angle_deg) is None:
            lo, hi = self.limits
            raise OutOfLimits(f"{angle_deg:g}° is outside the soft limits [{lo:g}°, {hi:g}°]; "
                              "change the plan or the limits in the station file", self.device)
        found = self.reach.nearest(angle_deg, angle_deg)
        if found is None:
            raise OutOfLimits(f"{angle_deg:g}° is beyond its cable wrap ({self.reach}); change the plan, "
                              "or cable_wrap_deg (slip_ring) in the station file if its cables allow it",
                              self.device)
        return found

    def move_to(self, angle_deg: float, *, travel_deg: float | None = None) -> None:
        """Start a move turning the table by ``travel_deg`` (signed; the caller's choice of the way
        round) to ``angle_deg`` (any equivalent); without it the shortest way round within the
        reach. A device that counts turns (its angle unwrapped) is sent the unwrapped target, which
        must lie within the soft limits; a wrapping AZ drive is told which way round instead."""
        self.check_angle(angle_deg)  # refuse before any exchange with the device
        here = self.angle()
        if travel_deg is None and not self.counts_turns:  # no turns to keep within the reach
            target = here + wrapped(angle_deg - here)
        elif travel_deg is None:
            found = self.reach.nearest(angle_deg, here)
            assert found is not None  # check_angle found one
            target = found
        else:
            target = angle_deg + 360.0 * round((here + travel_deg - angle_deg) / 360.0)
            if self.limits is not None and not self.limits[0] - 1e-9 <= target <= self.limits[1] + 1e-9:
                raise OutOfLimits(f"a turn of {travel_deg:+g}° to {angle_deg:g}° from {here:g}° would leave "
                                  f"the soft limits [{self.limits[0]:g}°, {self.limits[1]:g}°]", self.device)
        self._target = target
        self.commanded = True
        self._window = None  # a window's trace is of that window: the next one is noted afresh
        self._go(target, target - here)

    def wait_in_position(self, timeout_s: float) -> float:
        """Poll until in position and on target; returns the position read back (0..360°). A table
        that stands still short of its target without its controller saying in position (a bind
        the controller cannot close, with no alarm yet) is a stall after `STALL_S`: said then, not
        at the end of the move's timeout."""
        start = self.clock.now()
        deadline = start + timeout_s
        still: tuple[float, float] | None = None  # (since when, at what angle) it has stood still off target
        while True:
            expired = self.clock.now() >= deadline
            status = self.status()
            if status.fault:
                raise DeviceFault(status.fault, self.device)
            if not status.moving and not status.in_position and self._target is not None:
                still = self._stalled(still, start, status.words)
            else:
                still = None
            if status.in_position and not status.moving:
                here = self.angle()
                if self._target is None:
                    return here % 360.0
                off = wrapped(here - self._target) * ARCSEC_PER_DEG
                if abs(off) <= self.tolerance_arcsec:
                    return here % 360.0
                if not status.ready and (expired or self.clock.now() - start > START_GRACE_S):
                    raise DeviceFault(  # it stands still because it would not start: not a stall
                        f"the move to {self._target % 360.0:g}° did not start: the table is at "
                        f"{here % 360.0:.5f}° and its controller is not ready ({status.words})"
                        f"{self.not_ready_why()}", self.device)
                if expired or self.clock.now() - start > START_GRACE_S:
                    raise DeviceFault(
                        f"in position at {here % 360.0:.5f}°, {off:+.1f}″ from the target "
                        f"{self._target % 360.0:g}° (tolerance {self.tolerance_arcsec:g}″); "
                        "check for a stall or a slipping coupling", self.device)
            elif expired:
                raise DeviceFault(f"not in position {timeout_s:g} s after the move to "
                                  f"{(self._target or 0.0) % 360.0:g}° began ({status.words})", self.device)
            self.clock.sleep(self.poll_s)

    def _stalled(self, still: tuple[float, float] | None, start: float, words: str
                 ) -> tuple[float, float] | None:
        """One poll of a table that is neither moving nor in position: where it stands, and since
        when, while it stands off its target; `DeviceFault` once it has stood there `STALL_S`
        (after the start's grace, in which a device may still report the state before the move)."""
        assert self._target is not None
        now, here = self.clock.now(), self.angle()
        off = wrapped(here - self._target) * ARCSEC_PER_DEG
        if abs(off) <= self.tolerance_arcsec:
            return None  # on target: settling, clamping
        if still is None or abs(wrapped(here - still[1])) * ARCSEC_PER_DEG > self.tolerance_arcsec / 10:
            return now, here  # still getting there
        if now - still[0] >= STALL_S and now - start > START_GRACE_S:
            raise DeviceFault(f"stalled at {here % 360.0:.5f}°, {off:+.1f}″ from the target "
                              f"{self._target % 360.0:g}° (tolerance {self.tolerance_arcsec:g}″): not moving "
                              f"and not in position for {now - still[0]:.1f} s ({words}); check for a bind, "
                              "the clamp or the coupling", self.device)
        return still

    def position(self) -> float:
        return self.angle() % 360.0

    def winding(self) -> float | None:
        return self.angle() if self.counts_turns else None

    def window_opens(self) -> None:
        """Note the device's fault memory as a measurement window opens: `state` then reports any
        fault it remembers since (until the next move)."""
        self._window = self._fault_memory()

    def state(self) -> TableState:
        """Status, then position, against the last commanded target and the station's tolerance;
        then, since a window opened (`window_opens`), the device's memory of a fault in between."""
        status = self.status()
        here = self.angle()
        off = None if self._target is None else wrapped(here - self._target) * ARCSEC_PER_DEG
        trace = None if self._window is None else self._fault_since(self._window, status)
        return TableState(self.device, status.fault, status.moving, status.in_position, here % 360.0, off,
                          self.tolerance_arcsec, status.words, trace, status.needs_homing)

    def stop(self) -> None:
        """Tell the device to stop; a stop that fails is logged as a WARNING and raised."""
        try:
            self._halt()
        except Exception as exc:
            log.warning("%s: STOP FAILED, the table may still be moving: %s", self.device, exc)
            raise

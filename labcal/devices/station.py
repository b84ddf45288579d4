"""The two small interfaces the sequencer drives, and the station that bundles them.

Hardware drivers (`labcal.drivers`) and the simulated rig (`labcal.sim`) both implement
them, so the sequencer cannot tell which it talks to (docs/design.md §4).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import Mount
from labcal.devices.winding import Reach
from labcal.errors import LabcalError

STILL_WITHIN_S = 30.0  # a stopped table decelerating from full speed is still long before this
STILL_POLL_S = 0.05


class CriticalSection(Protocol):
    """A section a stop must not cut in half (the run's Ctrl-C handler defers a stop to its end);
    ``awaiting_reply=True``: the wait for a device's reply, which a stop does cut short
    (`labcal.run.interrupts.Interrupts.critical`)."""

    def __call__(self, *, awaiting_reply: bool = False) -> AbstractContextManager[None]: ...



@dataclass(frozen=True)
class TableState:
    """What a table reports of itself, in the same terms for every table family: the sequencer reads
    it before and after each measurement window, and discards a window it does not vouch for."""

    device: str  # the table, in words ("roll table (Newport SMC100, address 2 on /dev/ttyUSB0)")
    fault: str | None  # what its controller reports wrong, in words; None when healthy
    moving: bool
    in_position: bool
    position_deg: float  # 0..360
    off_arcsec: float | None  # position − the commanded one, folded; None when nothing was commanded
    tolerance_arcsec: float  # the station's in_position_arcsec
    words: str  # the controller's own status, for people
    # a fault the controller remembers since the measurement window opened (`RotaryAxis.window_opens`)
    # though it reports none now: an alarm raised and reset, a stage disabled and enabled again
    trace: str | None = None
    needs_homing: bool = False  # its controller lost its reference (a power cycle): homing restores it

    def problem(self) -> str | None:
        """Why a window measured with the table in this state cannot be kept; None if it can."""
        if self.fault:
            return f"{self.device}: {self.fault}"
        if self.trace:
            return f"{self.device}: {self.trace}"
        if self.moving:
            return f"{self.device}: moving ({self.words})"
        if self.off_arcsec is not None and abs(self.off_arcsec) > self.tolerance_arcsec:
            return (f"{self.device}: at {self.position_deg:.5f}°, {self.off_arcsec:+.1f}″ off its commanded "
                    f"position (tolerance {self.tolerance_arcsec:g}″)")
        return None


class RotaryAxis(Protocol):
    """One index table."""

    name: str
    reach: Reach  # the accumulated rotation from home it may have: its cable wrap and soft limits

    def state(self) -> TableState:
        """Status and position, read now (no motion); with the trace of any fault the controller
        remembers since `window_opens` (until the next move)."""

    def prepare(self) -> None:
        """Make the table ready to move, as a run does before its first move: home it where its
        controller has lost its reference (it moves!), enable it, set its speeds."""

    def window_opens(self) -> None:
        """A measurement window opens: note what the controller keeps of its faults (an alarm
        history, its state), so that `state` after the window sees a fault raised and cleared inside
        it, which a status read before and after cannot."""

    def move_to(self, angle_deg: float, *, travel_deg: float | None = None) -> None:
        """Start a move to an absolute angle; returns at once. ``travel_deg``: the signed turn the
        caller chose for it (`labcal.devices.winding`: which way round its cables allow); None: the
        shortest way round within the reach."""

    def wait_in_position(self, timeout_s: float) -> float:
        """Block until the table is in position and clamped; return the position read back (deg)."""

    def position(self) -> float:
        """Present position in degrees, 0..360."""

    def winding(self) -> float | None:
        """Its accumulated rotation from home, where the device counts turns (None where it does
        not: then the journal's moves say which turn it is on, `labcal.devices.winding.locate`)."""

    def send_stop(self) -> None:
        """Put a stop on its way at once, waiting for no reply (`Station.stop` sends every table's
        before it confirms any)."""

    def stop(self) -> None:
        """Stop at once, confirmed (retried where safe). Must always reach the device."""


@dataclass(frozen=True)
class Scan:
    """N consecutive samples of the three accelerometer channels (V) and the temperature (°C)."""

    volts: NDArray  # (n, 3)
    temp_c: NDArray | None = None  # (n,)


class Voltmeter(Protocol):
    measures_temperature: bool  # whether scans carry temp_c

    def read(self, n_samples: int) -> Scan:
        """Take n consecutive samples of all channels."""


class Clock(Protocol):
    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...


class SystemClock:
    """Wall-clock time, for real hardware."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        time.sleep(max(0.0, seconds))


def _nobody_to_tell(mount: Mount) -> None:
    """On a real station the operator's hands do the remount; no device needs telling."""


def _nothing_to_prepare(key: str) -> None:
    """Real hardware needs no notice of which point is next."""


def _no_exchanges_to_guard(critical: CriticalSection | None) -> None:
    """A simulated station exchanges no bytes that a stop could cut in half."""


@dataclass
class Station:
    """Everything the sequencer drives: two tables, a DMM, a clock, and what a remount changes."""

    pitch: RotaryAxis
    roll: RotaryAxis
    dmm: Voltmeter
    clock: Clock = field(default_factory=SystemClock)
    remounted: Callable[[Mount], None] = _nobody_to_tell
    at_point: Callable[[str], None] = _nothing_to_prepare  # the simulator draws each point's noise from it
    # the run hands its critical section to the devices' links, so that no exchange is cut in half
    guard_exchanges: Callable[[CriticalSection | None], None] = _no_exchanges_to_guard
    description: str = "station"

    def stop(self) -> None:
        """Stop both tables at once: every table's stop is sent first, once and without waiting for
        any reply, and only then is each confirmed (with its retries), so that a controller that does
        not answer never delays the other table's stop. Each is attempted even if the other fails.
        `StopFailed` names every table whose stop was not confirmed."""
        tables = (("pitch", self.pitch), ("roll", self.roll))
        for _, axis in tables:
            try:
                axis.send_stop()
            except Exception:  # noqa: BLE001, S110 - the confirmation below stops it, or says it did not
                pass
        failures: dict[str, Exception] = {}
        for table, axis in tables:
            try:
                axis.stop()
            except Exception as exc:  # noqa: BLE001 - both axes must get their stop
                failures[table] = exc
        failures.update(self._until_still([(table, axis) for table, axis in tables if table not in failures]))
        if failures:
            raise StopFailed(failures)

    def _until_still(self, tables: list[tuple[str, RotaryAxis]]) -> dict[str, Exception]:
        """Wait until each stopped table's status says it is not moving (a stop decelerates): only
        then are the tables still, as the pause prompt says. A table whose status cannot be read, or
        that still moves after `STILL_WITHIN_S`, may be moving."""
        deadline = self.clock.now() + STILL_WITHIN_S
        failures: dict[str, Exception] = {}
        waiting = dict(tables)
        while waiting:
            for table, axis in list(waiting.items()):
                try:
                    state = axis.state()
                except Exception as exc:  # noqa: BLE001 - whatever went wrong, it may be moving
                    failures[table] = exc
                    del waiting[table]
                    continue
                if not state.moving:
                    del waiting[table]
                elif self.clock.now() >= deadline:
                    failures[table] = LabcalError(f"still moving {STILL_WITHIN_S:g} s after its stop "
                                                  f"({state.words})")
                    del waiting[table]
            if waiting:
                self.clock.sleep(STILL_POLL_S)
        return failures


class StopFailed(LabcalError):
    """A table did not take its stop: it may still be moving, and the operator must be told so."""

    def __init__(self, failures: dict[str, Exception]):
        self.tables = tuple(failures)  # "pitch", "roll": the tables that may still be moving
        why = "; ".join(f"{table}: {exc}" for table, exc in failures.items())
        super().__init__(f"the stop did not reach the {may_be_moving(self.tables)} ({why})")


def may_be_moving(tables: tuple[str, ...]) -> str:
    """'pitch table', 'pitch and roll tables': the tables a failed stop leaves possibly moving."""
    return " and ".join(tables) + (" tables" if len(tables) > 1 else " table")


def mean_and_sd(scan: Scan) -> tuple[NDArray, NDArray]:
    """Mean and sample standard deviation per channel."""
    ddof = 1 if len(scan.volts) > 1 else 0
    return scan.volts.mean(axis=0), scan.volts.std(axis=0, ddof=ddof) if ddof else np.zeros(3)

"""Executes a plan on a station: move, wait in position, settle, average, record.

The sequencer never knows whether a real rig or the simulator answers. Axes never move
while a remount prompt is open, and every point is on disk before the next move starts.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from labcal.errors import LabcalError
from labcal.kinematics import Mount
from labcal.operator import Operator
from labcal.plan import Plan
from labcal.readings import ReadingsWriter
from labcal.station import Station, mean_and_sd

LOAD_POSITION = (0.0, 0.0)  # tables level while the operator remounts


class SequencerSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    settle_s: float = Field(default=8.0, ge=0, description="dwell after in-position (≥ 15 τ)")
    samples: int = Field(default=10, ge=1, le=10000, description="DMM samples averaged per point")
    move_timeout_s: float = Field(default=120.0, gt=0)
    position_tolerance_deg: float = Field(default=0.01, gt=0)


@dataclass(frozen=True)
class Step:
    replicate: int
    mount: Mount
    pitch_deg: float
    roll_deg: float


def schedule(plan: Plan) -> Iterator[Step]:
    """Replicates one after another; the mount order alternates so a replicate starts on the
    mount the previous one ended on, which saves a remount per replicate."""
    for rep in range(1, plan.replicates + 1):
        mounts = plan.mount_list if rep % 2 else plan.mount_list[::-1]
        for mount in mounts:
            for pitch, roll in plan.points:
                yield Step(rep, mount, pitch, roll)


class Display:
    """What the sequencer reports as it goes; the console implementation draws a progress bar."""

    def pause(self) -> AbstractContextManager:
        """Context in which a prompt may use the terminal."""
        return nullcontext()

    def point_done(self, step: Step, volts: np.ndarray, station_time_s: float) -> None:
        pass


@dataclass
class RunOutcome:
    points_recorded: int
    station_time_s: float


def _in_position(axis, target: float, timeout: float, tolerance: float) -> float:
    position = axis.wait_in_position(timeout)
    error = (position - target + 180.0) % 360.0 - 180.0
    if abs(error) > tolerance:
        raise LabcalError(
            f"{axis.name} table reads {position:.4f}° after a move to {target:g}° "
            f"(tolerance {tolerance:g}°); check the table and its clamp"
        )
    return position


def move_both(station: Station, pitch: float, roll: float, settings: SequencerSettings) -> None:
    """Start both tables, then wait for both and verify the read-back positions."""
    station.pitch.move_to(pitch)
    station.roll.move_to(roll)
    _in_position(station.pitch, pitch, settings.move_timeout_s, settings.position_tolerance_deg)
    _in_position(station.roll, roll, settings.move_timeout_s, settings.position_tolerance_deg)


def run_plan(
    plan: Plan, station: Station, operator: Operator, writer: ReadingsWriter,
    settings: SequencerSettings, display: Display | None = None,
) -> RunOutcome:
    """Run every point of the plan. On any exception (Ctrl-C included) the tables are stopped
    and the exception propagates; every point recorded so far is already on disk."""
    display = display or Display()
    t0 = station.clock.now()
    steps = list(schedule(plan))
    n_mount_changes = 1 + sum(a.mount != b.mount for a, b in zip(steps, steps[1:], strict=False))
    mounted: Mount | None = None
    change = 0
    try:
        for step in steps:
            if step.mount != mounted:
                change += 1
                move_both(station, *LOAD_POSITION, settings)
                with display.pause():
                    operator.confirm_mount(step.mount, change, n_mount_changes)
                station.remounted(step.mount)
                mounted = step.mount
            move_both(station, step.pitch_deg, step.roll_deg, settings)
            station.clock.sleep(settings.settle_s)
            scan = station.dmm.read(settings.samples)
            mean, sd = mean_and_sd(scan)
            writer.append(
                replicate=step.replicate, y_deg=step.mount.y_deg, u_deg=step.mount.u_deg,
                pitch_deg=step.pitch_deg, roll_deg=step.roll_deg, volts=mean, sd=sd,
                temp_c=None if scan.temp_c is None else float(np.mean(scan.temp_c)),
                n_samples=settings.samples, time_s=station.clock.now() - t0,
            )
            display.point_done(step, mean, station.clock.now() - t0)
    except BaseException as exc:
        try:
            station.stop()
        except Exception as stop_error:  # noqa: BLE001 - report it, but keep the original cause
            exc.add_note(f"and stopping the tables failed too: {stop_error}")
        raise
    return RunOutcome(points_recorded=writer.count, station_time_s=station.clock.now() - t0)

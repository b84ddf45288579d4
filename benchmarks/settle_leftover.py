"""The transient the conventional dead time leaves in a reading, against the simulator's truth.

Dry runs of four-mount-64 on the default simulated rig (steady lab, no drift), conventional
settling with the dead time at σ/√N and the nominal transient alone (``leftover = 1``,
``off_axis_arcsec = 0``: the rule of labcal ≤ 0.9), at a tenth of σ/√N, and at a tenth with the
transient of gravity up to 60″ off the tables' axes (the defaults): a roll at pitch ±90° leaves no
nominal transient, but the device's misalignments (tens of arcseconds) leave a real one.
For every point the simulator itself says, once in position, the settled output
(its own gravity and instrument model, not labcal's) and the sign of the transient still in the
output; a reading's leftover is (reading − settled output) along that sign, averaged over every
channel of every point whose transient at that moment exceeds σ/√N. The instrument is noise-free
(the sequencer is told its usual 20 µV, so it waits exactly as long): the leftover is then the
transient alone, not hidden in noise. Target: below 0.1 σ/√N (σ/√N = 6.3 µV, a reading's noise).

Usage: python benchmarks/settle_leftover.py [--seeds 1 2 3]
"""

from __future__ import annotations

import argparse
import io
import json
import math
import tempfile
from pathlib import Path

import numpy as np
from rich.console import Console

from labcal.config.emulation import RigConfig
from labcal.config.plans import load_plan
from labcal.config.settings import SequencerSettings
from labcal.run.operator import AutoOperator
from labcal.run.runner import calibrate
from labcal.sim.clock import VirtualClock
from labcal.sim.rig import SimRig
from labcal.store.journal import Journal

NOISE_V = 20e-6


class TruthfulRig(SimRig):
    """The simulated rig, noting at each point its settled output and the transient left."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.truth: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def at_point(self, key: str) -> None:
        """In position, before the point's dead time: the settled output, and the transient left."""
        super().at_point(key)
        t = self.clock.now()
        self._advance_filter(t)
        u = self._still_gravity(float(self.pitch.angle_at(t)), float(self.roll.angle_at(t)))
        temp = self.lab_temperature(t)
        settled = self.instrument.static_volts(u, t, temp)
        self.truth[key] = (settled, self.instrument.static_volts(self._g_filtered, t, temp) - settled)


def leftovers(seed: int, leftover: float, off_axis: float) -> tuple[np.ndarray, float]:
    """(signed leftovers in V, summed settle seconds) of one quiet conventional run."""
    base = RigConfig()
    inst = base.instrument.model_copy(update={"noise_v": 0.0, "drift_v_per_h": [0.0, 0.0, 0.0]})
    rig = base.model_copy(update={"lab_temp_swing_c": 0.0, "instrument": inst})
    plan, text = load_plan("four-mount-64")
    sim = TruthfulRig(rig, seed=seed, clock=VirtualClock())
    settle = SequencerSettings().settle.model_copy(update={
        "tau_s": inst.tau_s, "noise_v": NOISE_V, "leftover": leftover, "off_axis_arcsec": off_axis,
        "sensitivity_v_per_g": float(np.max(np.abs(inst.S)))})
    settings = SequencerSettings(settle=settle, speed_dps=rig.speed_dps, accel_dps2=rig.accel_dps2)
    station = json.dumps({"kind": "simulated rig", "seed": seed, "rig": rig.model_dump()}, sort_keys=True)
    with tempfile.TemporaryDirectory() as tmp, Journal(Path(tmp) / "j.sqlite") as journal:
        result = calibrate(plan, text, sim.station(), station, AutoOperator(Console(file=io.StringIO())),
                           settings, Path(tmp), journal)
        points = journal.points(result.run_id)
    out = []
    reading_sd = NOISE_V / math.sqrt(settle.samples)
    for p in points:
        settled, transient = sim.truth[f"{p.seq}:{p.attempt}"]
        reading = np.array([p.vx, p.vy, p.vz])
        out += [(r - s) * math.copysign(1.0, d)
                for r, s, d in zip(reading, settled, transient, strict=True) if abs(d) > reading_sd]
    return np.array(out), sum(p.settle_s or 0.0 for p in points)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = parser.parse_args()
    reading_sd = NOISE_V / math.sqrt(10)
    for leftover, off_axis in ((1.0, 0.0), (0.1, 0.0), (0.1, 60.0)):
        runs = [leftovers(seed, leftover, off_axis) for seed in args.seeds]
        means = [r[0].mean() for r in runs]
        print(f"dead time at {leftover:g} σ/√N, gravity {off_axis:g}″ off axis: mean leftover per run "
              f"{', '.join(f'{m * 1e6:+.2f}' for m in means)} µV = "
              f"{', '.join(f'{m / reading_sd:+.3f}' for m in means)} σ/√N (target < 0.1); "
              f"largest {max(np.max(r[0]) for r in runs) * 1e6:.2f} µV; settle Σ "
              f"{', '.join(f'{r[1]:.1f}' for r in runs)} s")


if __name__ == "__main__":
    main()

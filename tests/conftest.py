"""Shared helpers for the tests."""

from __future__ import annotations

import numpy as np

from labcal.fit import fit_linear
from labcal.kinematics import Misalignment
from labcal.plan import Plan
from labcal.sim.direct import simulate_readings
from labcal.sim.instrument import InstrumentTruth

SOTO_POINTS = [(p, r) for p in (0, 90, 180, 270) for r in (0, 90, 180, 270)]  # Soto Table 2
FOUR_MOUNTS = [(0, 0), (180, 0), (0, 180), (180, 180)]  # Soto Table 3


def soto_plan(mounts: list[tuple[int, int]]) -> Plan:
    return Plan(name="test", mounts=mounts, points=SOTO_POINTS)


def ideal_fit(mounts: list[tuple[int, int]], mis: Misalignment) -> np.ndarray:
    """X fitted to noise-free readings of an ideal instrument (B = 0, S = I) on a misaligned CD."""
    readings = simulate_readings(soto_plan(mounts), InstrumentTruth(), mis)
    return fit_linear(readings).coefficients

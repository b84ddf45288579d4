"""How the tables move and what the instrument's output is left doing when they stop.

Each table runs a trapezoidal velocity profile (triangular when it never reaches full speed); both
start together, so a move lasts as long as the longer one. The instrument's output follows gravity
through a first-order lag of time constant τ. Integrating that lag along the trapezoid in closed
form gives the angle by which the output trails each table when the motion ends:

    accelerating (v = a·t):   L(t) = a·τ·(t − τ·(1 − e^{−t/τ}))
    cruising (v = V):         L → V·τ + (L − V·τ)·e^{−t/τ}
    decelerating (v = V − a·t): L → a·τ² + (L − V·τ − a·τ²)·e^{−t/τ}

After a full-speed move the lag left at the stop is a·τ²·(1 − e^{−V/(aτ)}), not the whole step:
the dead time is sized by it (`labcal.run.settle`), and counted from the end of the motion.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.kinematics import Mount, nominal_gravity


def trapezoid_duration(distance: ArrayLike, speed: float, accel: float) -> NDArray | float:
    """Time to travel |distance| from rest to rest at peak ``speed`` and acceleration ``accel``
    (triangular when the table never reaches full speed). The simulated tables move by it too."""
    d = np.abs(np.asarray(distance, dtype=float))
    t = np.where(d <= speed**2 / accel, 2 * np.sqrt(d / accel), d / speed + speed / accel)
    return t if t.ndim else float(t)


def trapezoid_travel(t: ArrayLike, distance: float, speed: float, accel: float) -> NDArray:
    """Signed travel at times t since the move began (clipped to the move)."""
    d = abs(distance)
    total = trapezoid_duration(d, speed, accel)
    peak = min(speed, math.sqrt(d * accel))
    t_acc = peak / accel
    since = np.clip(np.asarray(t, float), 0.0, total)
    accel_part = 0.5 * accel * np.minimum(since, t_acc) ** 2
    cruise = peak * np.clip(since - t_acc, 0.0, max(0.0, total - 2 * t_acc))
    tail = np.clip(since - (total - t_acc), 0.0, t_acc)
    decel_part = peak * tail - 0.5 * accel * tail**2
    return math.copysign(1.0, distance) * (accel_part + cruise + decel_part)


def shortest_way(a: ArrayLike, b: ArrayLike) -> NDArray:
    """Signed travel (degrees) from angle(s) a to b the shortest way round."""
    return (np.asarray(b, dtype=float) - np.asarray(a, dtype=float) + 180.0) % 360.0 - 180.0


def move_time(a: ArrayLike, b: ArrayLike, speed: float, accel: float, unwrapped: bool = False) -> NDArray:
    """Time to go from attitude(s) a to b (…×2 degrees) with both tables moving together: the
    shortest way round, or straight from a to b when they are ``unwrapped`` (accumulated angles,
    the way round chosen for the tables' cables)."""
    travel = np.asarray(b, dtype=float) - np.asarray(a, dtype=float) if unwrapped else shortest_way(a, b)
    return np.max(trapezoid_duration(travel, speed, accel), axis=-1)


def trapezoid_lag(distance: ArrayLike, speed: float, accel: float, tau: float) -> NDArray:
    """Signed angle (degrees) by which a first-order output of time constant ``tau`` trails a table
    at the end of its trapezoidal move of ``distance`` (the closed form in the module docstring)."""
    d = np.abs(np.asarray(distance, dtype=float))
    peak = np.minimum(speed, np.sqrt(d * accel))
    t_ramp = peak / accel
    t_cruise = np.maximum(d / np.where(peak > 0, peak, 1.0) - t_ramp, 0.0)
    fade_ramp, fade_cruise = np.exp(-t_ramp / tau), np.exp(-t_cruise / tau)
    lag = accel * tau * (t_ramp - tau * (1 - fade_ramp))
    lag = peak * tau + (lag - peak * tau) * fade_cruise
    lag = accel * tau**2 + (lag - peak * tau - accel * tau**2) * fade_ramp
    return np.sign(np.asarray(distance, dtype=float)) * np.where(d > 0, lag, 0.0)


def transient_left(a: tuple[float, float], b: tuple[float, float], mount: Mount, speed: float,
                   accel: float, tau: float, steps_per_tau: int = 50, unwrapped: bool = False) -> float:
    """Largest |output − settled output| over the three sensors, in g, when both tables have
    stopped after the move a → b on ``mount``: nominal gravity along both trapezoids, through the
    first-order lag integrated in steps of τ/50 (exact for an input held over each step; the
    midpoint rule's error is ~1e-4 relative), starting settled. What the dead time is sized by.
    ``unwrapped``: a and b are accumulated angles, the tables went straight from one to the other."""
    travel = np.asarray(b, dtype=float) - np.asarray(a, dtype=float) if unwrapped else shortest_way(a, b)
    motion = float(np.max(trapezoid_duration(travel, speed, accel)))
    y, u = mount.radians
    start, end = np.radians(a), np.radians(b)
    if motion == 0:
        return 0.0
    n = math.ceil(motion * steps_per_tau / tau)
    mids = (np.arange(n) + 0.5) * (motion / n)
    pitch = start[0] + np.radians(trapezoid_travel(mids, float(travel[0]), speed, accel))
    roll = start[1] + np.radians(trapezoid_travel(mids, float(travel[1]), speed, accel))
    fade = math.exp(-motion / n / tau)
    weights = (1 - fade) * fade ** np.arange(n - 1, -1, -1)  # x ← g + (x − g)·fade, step by step
    along = nominal_gravity(pitch, roll, y, u)
    output = nominal_gravity(start[0], start[1], y, u) * fade**n + weights @ along
    return float(np.max(np.abs(output - nominal_gravity(end[0], end[1], y, u))))


def transient_at_stop(a: ArrayLike, b: ArrayLike, mount: Mount, speed: float, accel: float,
                      tau: float) -> NDArray:
    """`transient_left` in closed form for many moves at once (…×2 degrees), to plan with: each
    table's lag at its own stop, faded until the later table stops, then gravity at the target
    against gravity at the target less the lag (linear in the lag: a few % off after fast moves)."""
    travel = shortest_way(a, b)
    ends = trapezoid_duration(travel, speed, accel)
    faded = np.exp(-(np.max(ends, axis=-1, keepdims=True) - ends) / tau)  # until the later stop
    lag = trapezoid_lag(travel, speed, accel, tau) * faded
    target = np.radians(np.asarray(b, dtype=float))
    trailing = target - np.radians(lag)
    y, u = mount.radians
    here = nominal_gravity(target[..., 0], target[..., 1], y, u)
    there = nominal_gravity(trailing[..., 0], trailing[..., 1], y, u)
    return np.max(np.abs(here - there), axis=-1)

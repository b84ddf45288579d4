"""How the tables move and what the instrument's output is left doing when they stop.

Each table runs a trapezoidal velocity profile (triangular when it never reaches full speed); both
start together, so a move lasts as long as the longer one. The instrument's output follows gravity
through a first-order lag of time constant τ. Integrating that lag along the trapezoid in closed
form gives the angle by which the output trails each table when the motion ends:

    accelerating (v = a·t):   L(t) = a·τ·(t − τ·(1 − e^{−t/τ}))
    cruising (v = V):         L → V·τ + (L − V·τ)·e^{−t/τ}
    decelerating (v = V − a·t): L → a·τ² + (L − V·τ − a·τ²)·e^{−t/τ}

After a full-speed move the lag left at the stop is a·τ²·(1 − e^{−V/(aτ)}), not the whole step:
the dead time is sized by it (`labcal.run.settle`), and counted from the end of the motion. What
an earlier move left is still there, faded, when the next one begins (a resumed run's move to the
load position, the mount confirmed at once, then a short move to its first point): `transient_after`
integrates the output along every move since the last window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

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


Move = tuple[tuple[float, float], tuple[float, float], float]  # (from, to) accumulated degrees, start time s


def transient_after(moves: Sequence[Move], mount: Mount, speed: float, accel: float, tau: float,
                    steps_per_tau: int = 50, off_axis_rad: float = 0.0) -> float:
    """Largest |output − settled output| over the three sensors, in g, when both tables have
    stopped after ``moves`` on ``mount``: each (from, to, start time), the tables going straight
    from one accumulated angle to the other, still between moves (the output fading towards the
    gravity there). The output starts settled at the first move's start: what the dead time after
    the last move is sized by, every move since the last measured window counted (a resumed run's
    long move to the load position, a long move's legs), not the last one alone. Nominal gravity
    along the trapezoids, through the first-order lag integrated in steps of τ/50 (exact for an
    input held over each step; the midpoint rule's error is ~1e-4 relative).

    Plus ``off_axis_rad`` times the tables' own lag (rad): gravity off the axis a table turns it
    about by that angle (the device's misalignments, the mount) turns on a cone of that half-angle,
    which the nominal model cannot see — a roll at pitch ±90° leaves it as the only transient."""
    y, u = mount.radians
    output: NDArray | None = None
    angles = np.zeros(2)  # the tables' angles through the same lag, rad
    end = np.zeros(2)
    still_since = 0.0
    for a, b, t_start in moves:
        start, end = np.radians(a), np.radians(b)
        here = nominal_gravity(start[0], start[1], y, u)
        if output is None:
            output, angles = here, start.copy()
        else:  # still at a since the last move ended
            fade_still = math.exp(-max(t_start - still_since, 0.0) / tau)
            output = here + (output - here) * fade_still
            angles = start + (angles - start) * fade_still
        travel = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
        motion = float(np.max(trapezoid_duration(travel, speed, accel)))
        still_since = t_start + motion
        if motion == 0:
            continue
        n = math.ceil(motion * steps_per_tau / tau)
        mids = (np.arange(n) + 0.5) * (motion / n)
        pitch = start[0] + np.radians(trapezoid_travel(mids, float(travel[0]), speed, accel))
        roll = start[1] + np.radians(trapezoid_travel(mids, float(travel[1]), speed, accel))
        fade = math.exp(-motion / n / tau)
        weights = (1 - fade) * fade ** np.arange(n - 1, -1, -1)  # x ← g + (x − g)·fade, step by step
        output = output * fade**n + weights @ nominal_gravity(pitch, roll, y, u)
        angles = angles * fade**n + weights @ np.column_stack([pitch, roll])
    if output is None:
        return 0.0
    off_axis = off_axis_rad * float(np.max(np.abs(angles - end)))
    return float(np.max(np.abs(output - nominal_gravity(end[0], end[1], y, u)))) + off_axis


def transient_left(a: tuple[float, float], b: tuple[float, float], mount: Mount, speed: float,
                   accel: float, tau: float, steps_per_tau: int = 50, unwrapped: bool = False) -> float:
    """`transient_after` one move a → b from rest, settled: the shortest way round, or straight
    from a to b when they are ``unwrapped`` (accumulated angles)."""
    travel = np.asarray(b, dtype=float) - np.asarray(a, dtype=float) if unwrapped else shortest_way(a, b)
    to = (float(a[0] + travel[0]), float(a[1] + travel[1]))
    return transient_after([(a, to, 0.0)], mount, speed, accel, tau, steps_per_tau)


def transient_at_stop(a: ArrayLike, b: ArrayLike, mount: Mount, speed: float, accel: float,
                      tau: float, off_axis_rad: float = 0.0) -> NDArray:
    """`transient_left` in closed form for many moves at once (…×2 degrees), to plan with: each
    table's lag at its own stop, faded until the later table stops, then gravity at the target
    against gravity at the target less the lag (linear in the lag: a few % off after fast moves);
    plus ``off_axis_rad`` times the larger table lag, as in `transient_after`."""
    travel = shortest_way(a, b)
    ends = trapezoid_duration(travel, speed, accel)
    faded = np.exp(-(np.max(ends, axis=-1, keepdims=True) - ends) / tau)  # until the later stop
    lag = trapezoid_lag(travel, speed, accel, tau) * faded
    target = np.radians(np.asarray(b, dtype=float))
    trailing = target - np.radians(lag)
    y, u = mount.radians
    here = nominal_gravity(target[..., 0], target[..., 1], y, u)
    there = nominal_gravity(trailing[..., 0], trailing[..., 1], y, u)
    return np.max(np.abs(here - there), axis=-1) + off_axis_rad * np.max(np.abs(np.radians(lag)), axis=-1)

"""In which order to visit a mount's points: the plan's, the shortest, the paper's sweep, or random.

Both tables move at once, so going from one point to the next takes the longer of the two
moves (each the shortest way round), and then the settling that move leaves (a fast move into a
steep part of gravity leaves more): `shortest` weighs both, as one cost function
(`labcal.run.tour.move_and_settle`), and finds a near-optimal open tour from the load position
(`labcal.run.tour`: nearest neighbour, then 2-opt and Or-opt priced exactly for the asymmetric
cost, with a Held–Karp lower bound to say how near); Tripp & Tcheng recommend sweeping pitch min → max → min
(§4.1); a randomised order per replicate guards against drift aliasing with attitude.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from labcal.run.motion import move_time, trapezoid_duration
from labcal.run.tour import cost_matrix, move_and_settle, shortest_path

__all__ = ["ORDERS", "move_time", "order_points", "trapezoid_duration"]

ORDERS = ("shortest", "plan", "sweep", "random")
SettleCost = Callable[[NDArray, NDArray], NDArray]  # seconds of settling after moves a → b


def _no_settling(a: NDArray, b: NDArray) -> NDArray:
    return np.zeros(np.broadcast_shapes(np.shape(a), np.shape(b))[:-1])


def _shortest(points: NDArray, start: NDArray, speed: float, accel: float,
              settle_s: SettleCost) -> list[int]:
    cost = cost_matrix(points, start, move_and_settle(speed, accel, settle_s))
    return [int(node) - 1 for node in shortest_path(cost)[1:]]


def _sweep(points: NDArray, descending: bool) -> list[int]:
    """Pitch from min to max (or max to min); roll alternating direction at each pitch."""
    pitch = (points[:, 0] + 180.0) % 360.0 - 180.0
    order = []
    for k, p in enumerate(sorted(set(pitch), reverse=descending)):
        idx = np.flatnonzero(pitch == p)
        idx = idx[np.argsort(points[idx, 1] % 360.0)]
        order += (idx[::-1] if k % 2 else idx).tolist()
    return order


def order_points(points: list[tuple[float, float]], how: str, *, replicate: int = 1, seed: int = 0,
                 start: tuple[float, float] = (0.0, 0.0), speed: float = 20.0,
                 accel: float = 40.0, settle_s: SettleCost = _no_settling) -> list[int]:
    """Indices of ``points`` in visiting order; ``settle_s`` prices the settling after each move."""
    pts = np.asarray(points, dtype=float)
    if how == "plan":
        return list(range(len(pts)))
    if how == "sweep":
        return _sweep(pts, descending=replicate % 2 == 0)
    if how == "random":
        return np.random.default_rng([seed, replicate, 0x0DE5]).permutation(len(pts)).tolist()
    if how == "shortest":
        return _shortest(pts, np.asarray(start, float), speed, accel, settle_s)
    raise ValueError(f"unknown order {how!r}; choose from {', '.join(ORDERS)}")

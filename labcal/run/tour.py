"""The shortest tour of a mount's points, and a lower bound that says how short it is.

A tour is an open path: it starts where the tables are (the load position, node 0), visits every
point once and ends anywhere. What a step costs is one function of the attitudes a → b (`MoveCost`,
seconds: both tables' trapezoidal moves at once, then the settling the move leaves); everything
below only sees the matrix it fills, so a move that must go the long way round (cable wrap) changes
that function and nothing else. The cost is asymmetric (the settling after a → b is not that after
b → a), and every exchange below is priced exactly, reversed stretches included.

Construction: nearest neighbour from node 0, then local search to a local optimum of two
neighbourhoods — 2-opt (reverse a stretch) and Or-opt (move a stretch of 1–3 points elsewhere,
either way round). No randomness: the same points give the same tour. On Tripp's 481-point grid
it lies within 0.3 % of the bound below (`benchmarks/rig_hours.py`), in about half a second;
double-bridge kicks (iterated local search) found nothing shorter there at 15× the time.

Bound: Held & Karp's 1-tree relaxation with subgradient ascent (Held & Karp 1970, 1971), on the
symmetric lower envelope min(c_ij, c_ji) (any path costs at least its edges' envelope). The open path
becomes a cycle through a dummy node joined to node 0 (forced) and to every point at cost 0; the
1-tree's special node is the dummy, so it is a minimum spanning tree of node 0 and the points plus
the dummy's two edges. Every node-penalty vector π gives a valid bound; the ascent only tightens it.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from labcal.run.motion import move_time

MoveCost = Callable[[NDArray, NDArray], NDArray]  # seconds from attitude(s) a to b (…×2 degrees)
SEGMENTS = (1, 2, 3)  # Or-opt stretch lengths


def move_and_settle(speed: float, accel: float,
                    settle_s: Callable[[NDArray, NDArray], NDArray] | None = None) -> MoveCost:
    """The cost of a step: the longer of the two tables' trapezoidal moves (each the shortest way
    round), plus the settling after it. The one function a cable-wrap-aware move replaces."""
    def cost(a: NDArray, b: NDArray) -> NDArray:
        t = np.asarray(move_time(a, b, speed, accel), dtype=float)
        return t if settle_s is None else t + np.asarray(settle_s(a, b), dtype=float)
    return cost


def cost_matrix(points: NDArray, start: NDArray, cost: MoveCost) -> NDArray:
    """(n+1)×(n+1) seconds, node 0 the start and node i+1 point i; nothing returns to the start."""
    nodes = np.vstack([np.asarray(start, float)[None, :], np.asarray(points, float)])
    c = np.asarray(cost(nodes[:, None, :], nodes[None, :, :]), dtype=float).copy()
    c[:, 0] = np.inf
    np.fill_diagonal(c, 0.0)
    return c


def path_length(c: NDArray, path: NDArray | list[int]) -> float:
    """Seconds along ``path`` (node indices, starting with 0)."""
    p = np.asarray(path)
    return float(c[p[:-1], p[1:]].sum())


def _nearest_neighbour(c: NDArray) -> NDArray:
    m = len(c)
    path, free = [0], np.ones(m, bool)
    free[0] = False
    for _ in range(m - 1):
        row = np.where(free, c[path[-1]], np.inf)
        nxt = int(np.argmin(row))
        path.append(nxt)
        free[nxt] = False
    return np.array(path)


def _two_opt(c: NDArray, p: NDArray) -> bool:
    """One pass of 2-opt: for each i, reverse the stretch p[i..j] that gains most, if any."""
    m, improved = len(p), False
    cf = cb = np.zeros(0)
    stale = True
    for i in range(1, m - 1):
        if stale:  # the path's running sums, forwards and backwards, after a change
            stale = False
            bwd = c[p[1:], p[:-1]]
            bwd[0] = 0.0  # the start's edge is never reversed (i ≥ 1)
            cf = np.concatenate([[0.0], np.cumsum(c[p[:-1], p[1:]])])
            cb = np.concatenate([[0.0], np.cumsum(bwd)])
        j = np.arange(i + 1, m)
        nxt = np.minimum(j + 1, m - 1)
        last = j == m - 1
        old = c[p[i - 1], p[i]] + np.where(last, 0.0, c[p[j], p[nxt]]) + cf[j] - cf[i]
        new = c[p[i - 1], p[j]] + np.where(last, 0.0, c[p[i], p[nxt]]) + cb[j] - cb[i]
        gain = old - new
        k = int(np.argmax(gain))
        if gain[k] > 1e-9:
            p[i:j[k] + 1] = p[i:j[k] + 1][::-1].copy()
            improved = stale = True
    return improved


def _or_opt(c: NDArray, p: NDArray) -> bool:
    """One pass of Or-opt: move each stretch of 1–3 points to where it gains most, either way round."""
    m, improved = len(p), False
    for length in SEGMENTS:
        i = 1
        while i + length <= m:
            s = p[i:i + length]
            first, lastn = s[0], s[-1]
            inner_f = float(c[s[:-1], s[1:]].sum())
            inner_b = float(c[s[1:], s[:-1]].sum())
            before, after = p[i - 1], (p[i + length] if i + length < m else -1)
            removed = c[before, first] + (c[lastn, after] - c[before, after] if after >= 0 else 0.0)
            rest = np.concatenate([p[:i], p[i + length:]])  # the path without the stretch
            a = rest
            b = np.append(rest[1:], -1)
            has_b = b >= 0
            bb = np.where(has_b, b, 0)
            link = np.where(has_b, c[a, bb], 0.0)
            ins_f = c[a, first] + np.where(has_b, c[lastn, bb], 0.0) - link
            ins_b = c[a, lastn] + np.where(has_b, c[first, bb], 0.0) - link + inner_b - inner_f
            ins = np.minimum(ins_f, ins_b)
            ins[i - 1] = np.inf  # where it already is
            k = int(np.argmin(ins))
            if removed - ins[k] > 1e-9:
                seg = s if ins_f[k] <= ins_b[k] else s[::-1]
                p[:] = np.concatenate([rest[:k + 1], seg, rest[k + 1:]])
                improved = True
            else:
                i += 1
    return improved


def _local_search(c: NDArray, p: NDArray) -> NDArray:
    while _two_opt(c, p) | _or_opt(c, p):
        pass
    return p


def shortest_path(c: NDArray) -> NDArray:
    """A near-optimal open path through every node of ``c`` from node 0 (see the module docstring)."""
    if len(c) <= 2:
        return np.arange(len(c))
    return _local_search(c, _nearest_neighbour(c))


def _mst(w: NDArray) -> tuple[float, NDArray]:
    """Prim's minimum spanning tree of the complete graph ``w``: its weight and each node's degree."""
    m = len(w)
    in_tree = np.zeros(m, bool)
    in_tree[0] = True
    dist, parent = w[0].copy(), np.zeros(m, int)
    degree, total = np.zeros(m, int), 0.0
    dist[0] = np.inf
    for _ in range(m - 1):
        v = int(np.argmin(dist))
        total += float(dist[v])
        degree[v] += 1
        degree[parent[v]] += 1
        in_tree[v] = True
        dist[v] = np.inf
        closer = ~in_tree & (w[v] < dist)
        dist[closer], parent[closer] = w[v][closer], v
    return total, degree


def path_lower_bound(c: NDArray, iterations: int = 300) -> float:
    """A lower bound (seconds) on every open path through ``c`` from node 0: Held–Karp's 1-tree
    bound with subgradient ascent (module docstring). Valid whatever the ascent reaches."""
    m = len(c)
    if m <= 1:
        return 0.0
    s = np.minimum(c, c.T)
    s[0, :] = s[:, 0] = c[0, :]  # from the start only
    np.fill_diagonal(s, np.inf)
    if m == 2:
        return float(c[0, 1])
    pi = np.zeros(m)
    best = -np.inf
    upper = path_length(c, shortest_path(c))
    step_scale = 2.0
    stall = 0
    for _ in range(iterations):
        w = s + pi[:, None] + pi[None, :]
        tree, degree = _mst(w)
        j = 1 + int(np.argmin(pi[1:]))  # the dummy's cheaper edge to a point (its edge to 0 is forced)
        degree = degree.copy()
        degree[0] += 1
        degree[j] += 1
        bound = tree + pi[0] + pi[j] - 2 * pi.sum()
        if bound > best + 1e-12:
            best, stall = bound, 0
        else:
            stall += 1
            if stall >= 10:
                step_scale, stall = step_scale / 2, 0
        g = degree - 2.0
        norm = float(g @ g)
        if norm == 0 or step_scale < 1e-6:  # a tour: the bound is the optimum
            break
        pi += step_scale * max(upper - bound, 1e-9 * upper) / norm * g
    return float(best)

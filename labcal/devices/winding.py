"""Cable wrap: how far each table may turn from home, and which way round each move goes.

A table without slip rings carries its cables through its rotation: they tolerate the table's
accumulated rotation from home (not its angle mod 360) within ±``cable_wrap_deg``, and a table
that always took the shortest way round would wind them up turn after turn (a 64-point run wound
the roll table −2790°). So every table has a *reach*: the accumulated rotation it may have, its
cable wrap and its soft limits together (unbounded with a slip ring and no limits). Each move goes
to the angle's equivalent within the reach nearest to where the table is: the shortest way round
when that stays within the reach, the other way round otherwise.

The whole run's windings are planned before anything moves (`plan_windings`): a plan with an angle
no equivalent of which lies within a table's reach is refused in one line. Planning them ahead also
makes them the same whatever happened before: a resumed run goes to each point at the winding the
uninterrupted run would have had there, so its moves (and the transients they leave) are the same.

Every move is journaled before it starts (event ``move``: each table's accumulated rotation from
and to), so that a resumed run, or a run that stopped its tables mid-move, knows where the cables
are: the table is somewhere on its last journaled move, and the position read back (mod 360)
tells where (`locate`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from labcal.errors import LabcalError

MOVE_EVENT = "move"  # the journal's event kind for a move's windings, journaled before it starts
HALF_TURN = 180.0
ON_PATH_DEG = 0.5  # how far outside its last journaled move a table may read and still be on it


def wrapped(delta_deg: float) -> float:
    """An angle difference folded into [-180, 180)."""
    return (delta_deg + 180.0) % 360.0 - 180.0


@dataclass(frozen=True)
class Reach:
    """The accumulated rotation from home, in degrees, that a table may have: [lo, hi]."""

    lo: float = -math.inf
    hi: float = math.inf

    @classmethod
    def of(cls, cable_wrap_deg: float | None, limits_deg: tuple[float, float] | None = None) -> Reach:
        """A table's reach: ±``cable_wrap_deg`` (None: slip rings, no bound) within its soft limits."""
        lo, hi = limits_deg or (-math.inf, math.inf)
        if cable_wrap_deg is not None:
            lo, hi = max(lo, -cable_wrap_deg), min(hi, cable_wrap_deg)
        return cls(lo, hi)

    @property
    def bounded(self) -> bool:
        return math.isfinite(self.lo) or math.isfinite(self.hi)

    def __str__(self) -> str:
        if -self.lo == self.hi:
            return f"±{self.hi:g}° from home"
        return f"[{self.lo:g}°, {self.hi:g}°] from home"

    def nearest(self, angle_deg: float, near_deg: float) -> float | None:
        """The equivalent of ``angle_deg`` (mod 360) within the reach nearest to ``near_deg``, which
        may lie outside it (a tie, half a turn either way, goes towards home); None when no
        equivalent lies within the reach."""
        k_lo = math.ceil((self.lo - angle_deg) / 360.0 - 1e-9) if math.isfinite(self.lo) else -math.inf
        k_hi = math.floor((self.hi - angle_deg) / 360.0 + 1e-9) if math.isfinite(self.hi) else math.inf
        if k_lo > k_hi:
            return None
        k = round((near_deg - angle_deg) / 360.0)  # the nearest equivalent, were there no bounds
        turns = {int(min(max(k + d, k_lo), k_hi)) for d in (-1, 0, 1)}
        nearest_first = lambda t: (round(abs(t - near_deg), 9), abs(t), t)  # noqa: E731
        return min((angle_deg + 360.0 * n for n in turns), key=nearest_first)

    def contains(self, angle_deg: float) -> bool:
        return self.lo - 1e-9 <= angle_deg <= self.hi + 1e-9


def refuse(table: str, angle_deg: float, reach: Reach) -> LabcalError:
    return LabcalError(f"plan refused before any motion: the {table} table cannot reach {angle_deg:g}° "
                       f"within its cable wrap and limits ({reach}); change the plan, or give the {table} "
                       "table a larger cable_wrap_deg (or slip_ring = true) if its cables allow it")


def plan_windings(targets: Sequence[tuple[float, float]], reaches: tuple[Reach, Reach],
                  start: tuple[float, float] = (0.0, 0.0), names: tuple[str, str] = ("pitch", "roll")
                  ) -> list[tuple[float, float]]:
    """Each target's winding (accumulated rotation from home, per table) for a sequence of moves
    made one after the other from ``start``, each the nearest within the reach; raises the one-line
    refusal for an angle no equivalent of which is within a table's reach."""
    at = list(start)
    out: list[tuple[float, float]] = []
    for target in targets:
        for i in (0, 1):
            found = reaches[i].nearest(target[i], at[i])
            if found is None:
                raise refuse(names[i], target[i], reaches[i])
            at[i] = found
        out.append((at[0], at[1]))
    return out


def locate(read_deg: float, last: tuple[float, float] | None, reach: Reach) -> float:
    """Where a table is in accumulated degrees from home, from its position read back (any
    equivalent) and its last journaled move (from, to): on that move if the reading fits it (a
    stop may have caught it part way), else the equivalent nearest to where it was going; with no
    journaled move, the equivalent nearest home (within the reach if one is)."""
    if last is None:
        found = reach.nearest(read_deg, 0.0)
        return wrapped(read_deg) if found is None else found
    lo, hi = min(last) - ON_PATH_DEG, max(last) + ON_PATH_DEG
    k = math.ceil((lo - read_deg) / 360.0)
    on_path = read_deg + 360.0 * k
    if on_path <= hi:
        return on_path
    return last[1] + wrapped(read_deg - last[1])


class Journaled(Protocol):
    """A journaled event as the journal gives it back (`labcal.store.journal.EventRow`, a layer above)."""

    @property
    def kind(self) -> str: ...

    @property
    def values(self) -> dict[str, Any]: ...


def last_move(events: Sequence[Journaled]) -> tuple[tuple[float, float], tuple[float, float]] | None:
    """The last journaled move's windings, ((pitch from, to), (roll from, to)), or None."""
    for event in reversed(events):
        if event.kind == MOVE_EVENT and event.values:
            data = event.values
            return (float(data["pitch"][0]), float(data["pitch"][1])), (float(data["roll"][0]),
                                                                          float(data["roll"][1]))
    return None


def left_at(events: Sequence[Journaled]) -> tuple[float, float] | None:
    """Where the journal last sent the tables (pitch, roll), accumulated from home; None if nowhere.
    A simulated or emulated rig resumes with its tables there, as a real bench's stayed."""
    last = last_move(events)
    return None if last is None else (last[0][1], last[1][1])

"""Is the instrument mounted the way the plan says, and is the station wired the way its file says?
Checked at the start of a run and after every remount, before any point of a mount is kept.

One reading of gravity at one attitude answers both, if the attitude is chosen so that nothing a
mistake can do leaves the reading alone. Gravity on the first mount is g = [sin p, cos p sin r,
cos p cos r] (Soto §5); at pitch 33°, roll 76° that is [0.545, 0.814, 0.203]:

- the tables exchanged (their addresses or cables swapped: the pitch command turns the roll table)
  give [sin r, cos r sin p, cos r cos p] = [0.970, 0.132, 0.203]. A check where p = r, such as
  (30°, 30°), is the same either way: it proves nothing;
- a table turning the wrong way reverses one component (sin p, or sin r in y), none of which is near
  zero;
- the DMM's channels in another order permute three components of distinct sizes;
- each mount reverses two components (`MOUNTS`).

Every combination of these that is not the plan's own reads at least 0.38 g from it (a grid search
over the attitudes, every mount; the test recomputes the separations): ~1.9 V at 5 V/g, against
microvolts of noise. Two combinations gravity cannot tell apart at any attitude: both tables
reversed turns the instrument 180° about z, which is the fore-and-aft mount (y = 180°); so the
reading says "reads as if on that mount". The readings are turned into g with the calibration so
far when there is one, otherwise with the nominal instrument (B ≈ 0, S ≈ s·I, s > 0).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import MOUNTS, Mount, mount_gravity

CHECK_ATTITUDE = (33.0, 76.0)
SENSORS = "xyz"
TIE = 1e-9  # g: hypotheses this close are the same reading (rounding), the simplest one is named


@dataclass(frozen=True)
class Wiring:
    """How the station might really be wired: the tables exchanged, a table turning the wrong way
    (its sense reversed), and which of the instrument's sensors each DMM channel (x, y, z) reads."""

    exchanged: bool = False
    pitch_reversed: bool = False
    roll_reversed: bool = False
    channels: tuple[int, int, int] = (0, 1, 2)

    @property
    def faults(self) -> list[str]:
        """What is wrong, in words, one phrase each (none: the station is as its file says)."""
        found = []
        if self.exchanged:
            found.append("the tables look exchanged: pitch moves what the plan calls roll (check the "
                         "tables' addresses or cables)")
        for name, reversed_ in (("pitch", self.pitch_reversed), ("roll", self.roll_reversed)):
            if reversed_:
                found.append(f"the {name} table turns the wrong way (its sense is reversed)")
        if self.channels != (0, 1, 2):
            read = ", ".join(SENSORS[c] for c in self.channels)
            found.append(f"the DMM's channels look exchanged: its x, y, z channels read the instrument's "
                         f"{read}")
        return found

    def gravity(self, pitch_deg: float, roll_deg: float, mount: Mount) -> NDArray[np.float64]:
        """The gravity each DMM channel reads when the plan commands (pitch, roll) on ``mount``."""
        pitch, roll = (roll_deg, pitch_deg) if self.exchanged else (pitch_deg, roll_deg)
        pitch, roll = -pitch if self.pitch_reversed else pitch, -roll if self.roll_reversed else roll
        return mount_gravity(pitch, roll, mount)[list(self.channels)]


AS_STATED = Wiring()
WIRINGS = [Wiring(e, p, r, (c[0], c[1], c[2])) for e, p, r in itertools.product((False, True), repeat=3)
           for c in itertools.permutations(range(3))]


def expected_gravity(mount: Mount, wiring: Wiring = AS_STATED) -> NDArray[np.float64]:
    return wiring.gravity(*CHECK_ATTITUDE, mount)


def identify(volts: NDArray, provisional: NDArray | None = None, stated: Mount | None = None
             ) -> tuple[Mount, Wiring]:
    """The mount and wiring whose check-attitude gravity best matches the mean voltages; among those
    that read alike, the one with the fewest faults, on the ``stated`` mount if it is one of them.
    ``provisional`` is an X (4×3) fitted from the points measured so far, if any.

    A package of fewer sensors (NaN in the outputs it lacks) is judged by the signs of the gravity
    components its sensors see (0.2 g at least at the check attitude), its wiring taken as stated:
    an x–y or x–z package tells the four mounts apart, a single x sensor only the x direction, so
    where mounts tie the ``stated`` one is taken (`distinguishes` says whether the check could tell)."""
    volts = np.asarray(volts, float)
    present = ~np.isnan(volts)
    if not present.all():
        if provisional is not None and provisional.shape[1] == present.sum():
            volts = volts[present] - provisional[0]
        else:
            volts = volts[present]
        signs = np.sign(volts)
        mount = min(MOUNTS, key=lambda m: (int(np.sum(signs != np.sign(expected_gravity(m)[present]))),
                                           m != stated))
        return mount, AS_STATED
    if provisional is not None:
        g = np.linalg.solve(provisional[1:].T, volts - provisional[0])
    else:
        g = volts / np.linalg.norm(volts)
    candidates = sorted(((m, w) for w in WIRINGS for m in MOUNTS),
                        key=lambda c: (len(c[1].faults), c[0] != stated))
    distance = [float(np.linalg.norm(g - expected_gravity(m, w))) for m, w in candidates]
    best = min(distance)
    return next(c for c, d in zip(candidates, distance, strict=True) if d <= best + TIE)


def distinguishes(volts: NDArray) -> bool:
    """Whether the outputs present tell the four mounts apart at the check attitude (every package
    but a single sensor's)."""
    present = ~np.isnan(np.asarray(volts, float))
    signs = {tuple(np.sign(expected_gravity(m)[present])) for m in MOUNTS}
    return len(signs) == len(MOUNTS)


def drawing(mount: Mount) -> list[str]:
    """The mount asked for, drawn for the technician: the roll table's plate seen from the side
    (the front of the table to the right), its dowels, the instrument on the plate's top or bottom
    side, and the instrument's x arrow pointing forward or backward. Plain ASCII, 22 columns at
    most, so that any terminal shows it whole; the words beside the prompt say the same."""
    arrow = "x -->" if mount.y_deg % 360 == 0 else "<-- x"
    case = ["    +------------+", f"    |   {arrow}    |", "    +------------+"]
    plate = "====o============o===="
    top = mount.u_deg % 360 == 0
    body = [*case[:2], plate] if top else [plate, *case[1:]]
    return ["front of the table -->", *body, "=  the plate", "o  its dowels"]

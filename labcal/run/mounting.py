"""Is the instrument mounted the way the plan says? Checked before any point of a mount is kept.

At level all four mounts look alike to x (g along z only separates top from bottom), so the
check attitude is pitch 30°, roll 30°, where the four mounts' gravity vectors differ in sign on
at least two axes. The reading is turned into g with the calibration so far when there is one,
otherwise with the nominal instrument (B ≈ 0, S ≈ s·I, s > 0): only signs need to be right.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import MOUNTS, Mount, mount_gravity

CHECK_ATTITUDE = (30.0, 30.0)


def expected_gravity(mount: Mount) -> NDArray:
    return mount_gravity(*CHECK_ATTITUDE, mount)


def identify(volts: NDArray, provisional: NDArray | None = None, expected: Mount | None = None) -> Mount:
    """The mount whose check-attitude gravity best matches the mean voltages. ``provisional`` is
    an X (4×3) fitted from the points measured so far, if any.

    A package of fewer sensors (NaN in the outputs it lacks) is judged by the signs of the gravity
    components its sensors see (0.43 g at least at the check attitude): an x–y or x–z package tells
    the four mounts apart, a single x sensor only the x direction, so where mounts tie the
    ``expected`` one is taken (`distinguishes` says whether the check could tell)."""
    volts = np.asarray(volts, float)
    present = ~np.isnan(volts)
    if not present.all():
        if provisional is not None and provisional.shape[1] == present.sum():
            volts = volts[present] - provisional[0]
        else:
            volts = volts[present]
        signs = np.sign(volts)
        return min(MOUNTS, key=lambda m: (int(np.sum(signs != np.sign(expected_gravity(m)[present]))),
                                          m != expected))
    if provisional is not None:
        g = np.linalg.solve(provisional[1:].T, volts - provisional[0])
    else:
        g = volts / np.linalg.norm(volts)
    return min(MOUNTS, key=lambda m: float(np.linalg.norm(g - expected_gravity(m))))


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

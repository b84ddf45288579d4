"""Calibration points as arrays: what every fit takes (`labcal.config.readings_csv` reads and
writes them as the readings CSV of docs/design.md §5)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.replication import Cells, first_rows, point_groups


def angle_key(degrees: NDArray[np.float64]) -> NDArray[np.float64]:
    """What identifies an angle of a calibration point: degrees modulo 360, to 1e-9°."""
    key: NDArray[np.float64] = np.round(degrees % 360.0, 9) % 360.0
    return key


@dataclass(frozen=True)
class PointIndex:
    """The calibration points of a set of readings (mount and table angles modulo 360°)."""

    groups: NDArray[np.intp]  # (n,) point of every reading, numbered in the keys' order
    counts: NDArray[np.float64]  # (G,) readings of each point
    first: NDArray[np.intp]  # (G,) the first reading of each point

    def __len__(self) -> int:
        return len(self.counts)

    def means(self, values: NDArray[np.float64]) -> NDArray[np.float64]:
        """Mean of each column of ``values`` (n×m) over each point's readings (G×m)."""
        sums = np.column_stack([np.bincount(self.groups, weights=c, minlength=len(self)) for c in values.T])
        return sums / self.counts[:, None]


@dataclass(frozen=True)
class Readings:
    """Calibration points as arrays; angles in degrees as they arrive from files."""

    replicate: NDArray[np.int_]  # (n,)
    y_deg: NDArray[np.float64]
    u_deg: NDArray[np.float64]
    pitch_deg: NDArray[np.float64]
    roll_deg: NDArray[np.float64]
    volts: NDArray[np.float64]  # (n, 3): vx, vy, vz
    temp_c: NDArray[np.float64] | None = None
    units: str = "V"  # the outputs' unit (V, mV, counts, m/s2): B is in it, S in it per g
    # Each point's window as the sequencer averaged it: the samples' standard deviation per channel
    # (ddof 1; n×3) and their number (n,). None where the readings do not say (a readings CSV without
    # the audit columns, a simulation of window means): the instrument's repeatability is then unknown.
    window_sd: NDArray[np.float64] | None = None
    window_n: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.replicate)

    @cached_property
    def points(self) -> PointIndex:
        """Computed once: every fit, check and test of these readings groups them the same way (a
        changed set of readings is a new Readings, e.g. dataclasses.replace, never arrays changed in
        place, so the cache cannot go stale)."""
        groups, n_points = point_groups([self.y_deg, self.u_deg, self.pitch_deg, self.roll_deg], angle_key)
        return PointIndex(groups, np.bincount(groups, minlength=n_points).astype(float),
                          first_rows(groups, n_points))

    @cached_property
    def point_means(self) -> NDArray[np.float64]:
        """The mean volts of each point (G×3), computed once for the fits and checks that start there."""
        return self.points.means(self.volts)

    @cached_property
    def cells(self) -> Cells:
        """What the replicated analyses of every model take from the readings, computed once."""
        return Cells.of(self.volts, self.points.groups, self.replicate, len(self.points), self.point_means)

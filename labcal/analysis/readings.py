"""Calibration points as arrays: what every fit takes (`labcal.config.readings_csv` reads and
writes them as the readings CSV of DESIGN.md §5)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


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

    def __len__(self) -> int:
        return len(self.replicate)

"""Calibration points as arrays: what every fit takes (`labcal.config.readings_csv` reads and
writes them as the readings CSV of DESIGN.md §5)."""

from __future__ import annotations

from dataclasses import dataclass

from numpy.typing import NDArray


@dataclass(frozen=True)
class Readings:
    """Calibration points as arrays; angles in degrees as they arrive from files."""

    replicate: NDArray  # (n,) int
    y_deg: NDArray
    u_deg: NDArray
    pitch_deg: NDArray
    roll_deg: NDArray
    volts: NDArray  # (n, 3): vx, vy, vz
    temp_c: NDArray | None = None

    def __len__(self) -> int:
        return len(self.replicate)

"""The linear instrument model V = B + gᵀS (Soto eqs. 4, 13–21) fitted on the nominal gravity."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from labcal.kinematics import gravity
from labcal.readings import Readings
from labcal.regression import LeastSquares, least_squares

SENSORS = ("x", "y", "z")
ROW_NAMES = ("B", "S_x", "S_y", "S_z")  # rows of X: bias, then the g_x, g_y, g_z sensitivities


def linear_design(readings: Readings) -> NDArray:
    """[1 gᵀ] with g the nominal gravity of each point, mount included (Soto eq. 14)."""
    g = gravity(*readings.angles_rad)
    return np.column_stack([np.ones(len(readings)), g])


@dataclass(frozen=True)
class LinearFit:
    """X = [Bᵀ; S] (4×3) with its statistics; column j is sensor j."""

    ls: LeastSquares

    @property
    def coefficients(self) -> NDArray:
        return self.ls.coef

    @property
    def bias(self) -> NDArray:
        return self.ls.coef[0]

    @property
    def sensitivity(self) -> NDArray:
        return self.ls.coef[1:]

    def to_json(self) -> dict:
        """The linear fit JSON contract of DESIGN.md §5, plus per-sensor statistics."""
        return {
            "model": "linear",
            "coefficients": self.ls.coef.tolist(),
            "standard_errors": self.ls.stderr.tolist(),
            "residual_standard_error": self.ls.residual_se.tolist(),
            "degrees_of_freedom": self.ls.dof,
            "n_points": self.ls.n_obs,
            "layout": {
                "rows": ["B", "S row g_x", "S row g_y", "S row g_z"],
                "columns": ["sensor x", "sensor y", "sensor z"],
                "units": "V (bias), V/g (sensitivity)",
            },
        }


def fit_linear(readings: Readings) -> LinearFit:
    return LinearFit(least_squares(linear_design(readings), readings.volts))

"""The simulated three-axis accelerometer instrument: true B and S, and its imperfections.

Static model V = B + gᵀS (Soto eq. 4), or equivalently per sensor v = b + S·(u·g) with the
coning unit vectors of DESIGN.md §3 (Tripp eqs. 2, 4, 5). On top: a first-order low-pass
output, white noise, slow offset drift and temperature coefficients.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, field_validator


def coning_axes(omega: NDArray, azimuth: NDArray) -> NDArray:
    """Unit sensitive axes u_x, u_y, u_z as columns (3×3) from coning angles Ω and azimuths A (rad)."""
    (ox, oy, oz), (ax, ay, az) = np.asarray(omega, float), np.asarray(azimuth, float)
    ux = [np.cos(ox), -np.sin(ox) * np.cos(ax), -np.sin(ox) * np.sin(ax)]
    uy = [-np.sin(oy) * np.sin(ay), np.cos(oy), np.sin(oy) * np.cos(ay)]
    uz = [-np.sin(oz) * np.cos(az), np.sin(oz) * np.sin(az), np.cos(oz)]
    return np.column_stack([ux, uy, uz])


class InstrumentTruth(BaseModel):
    """True coefficients and imperfections. B in V; S (3×3) in V/g, column j = sensor j."""

    model_config = ConfigDict(extra="forbid")

    B: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    S: list[list[float]] = Field(default=[[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    noise_v: float = Field(default=0.0, ge=0, description="white noise per sample, V rms")
    tau_s: float = Field(default=0.5, gt=0, description="first-order output time constant, s")
    drift_v_per_h: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    tc_bias_v_per_c: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    tc_scale_per_c: list[float] = Field(default=[0.0, 0.0, 0.0], min_length=3, max_length=3)
    t_ref_c: float = 20.0

    @field_validator("S")
    @classmethod
    def _square(cls, s: list[list[float]]) -> list[list[float]]:
        if np.shape(s) != (3, 3):
            raise ValueError("S must be 3 rows of 3 numbers")
        if abs(np.linalg.det(np.array(s))) < 1e-12:
            raise ValueError("S is singular: the three sensors must not be coplanar")
        return s

    @classmethod
    def from_coning(cls, b: list[float], sensitivity: list[float], omega_deg: list[float],
                    azimuth_deg: list[float], **rest) -> InstrumentTruth:
        """Per-sensor offset b, sensitivity S, coning angle Ω and azimuth A (Tripp eq. 2)."""
        axes = coning_axes(np.radians(omega_deg), np.radians(azimuth_deg))
        return cls(B=list(b), S=(axes * np.asarray(sensitivity)[None, :]).tolist(), **rest)

    @property
    def X(self) -> NDArray:
        """The true coefficients in Soto's layout [Bᵀ; S] (4×3)."""
        return np.vstack([self.B, self.S])

    def static_volts(self, g: NDArray, elapsed_s: float = 0.0, temp_c: float | None = None) -> NDArray:
        """Noise-free settled output for gravity g (..., 3) after ``elapsed_s`` at ``temp_c``."""
        dt = 0.0 if temp_c is None else temp_c - self.t_ref_c
        bias = np.asarray(self.B) + np.asarray(self.drift_v_per_h) * elapsed_s / 3600 \
            + np.asarray(self.tc_bias_v_per_c) * dt
        sens = np.asarray(self.S) * (1 + np.asarray(self.tc_scale_per_c) * dt)[None, :]
        return bias + np.asarray(g) @ sens


def default_instrument() -> InstrumentTruth:
    """A plausible servo-accelerometer package (~5 V/g) for dry runs: small coning, µV noise."""
    return InstrumentTruth.from_coning(
        b=[0.0123, -0.0081, 0.0047],
        sensitivity=[4.9871, 5.0124, 4.9958],
        omega_deg=[0.21, 0.14, 0.09],
        azimuth_deg=[35.0, -120.0, 200.0],
        noise_v=20e-6,
        tau_s=0.5,
        drift_v_per_h=[2e-6, -1e-6, 1.5e-6],
        tc_bias_v_per_c=[5e-6, -4e-6, 3e-6],
        tc_scale_per_c=[15e-6, 12e-6, -10e-6],
    )

"""Calibration plans: which mounts, which (pitch, roll) points, how many replicates.

The validated model of an experimental design; `labcal.config.plans` reads and writes plan files.
Every angle is validated before anything moves.
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from labcal.analysis.kinematics import Mount, gravity

INDEX_STEP_DEG = 1.0  # index tables stop on a 1° grid
N_COEFFICIENTS = 4  # per sensor: bias and three sensitivities


def on_grid(angle: float, step: float) -> bool:
    """Whether an angle is one the tables can stop at (step 0: any angle)."""
    return not step or abs(angle / step - round(angle / step)) <= 1e-9


MIN_STEP_DEG = 1e-6  # finer than any rotary table's resolution (0.36 arcsec = 1e-4°)


class Plan(BaseModel):
    """A validated articulation plan. Angles in degrees: table angles in -180..360 on the 1° grid."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(min_length=1)
    description: str = ""
    replicates: int = Field(default=1, ge=1, le=100)
    angle_step_deg: float = Field(default=INDEX_STEP_DEG, ge=0, le=90, allow_inf_nan=False,
                                  description="table grid, 0 if continuous")
    mounts: list[tuple[float, float]] = Field(min_length=1, description="[y_deg, u_deg] per mount")
    points: list[tuple[float, float]] = Field(min_length=1, description="[pitch_deg, roll_deg] per point")

    @field_validator("mounts")
    @classmethod
    def _mount_angles(cls, mounts: list[tuple[float, float]]) -> list[tuple[float, float]]:
        for i, (y, u) in enumerate(mounts):
            if y not in (0, 180) or u not in (0, 180):
                raise ValueError(f"mount {i + 1} is [{y:g}, {u:g}]; y_deg and u_deg must each be 0 or 180")
        if len(set(mounts)) != len(mounts):
            raise ValueError("a mount is listed twice; use `replicates` to repeat the plan")
        return mounts

    @field_validator("angle_step_deg")
    @classmethod
    def _real_grid(cls, step: float) -> float:
        if 0 < step < MIN_STEP_DEG:  # a subnormal step would make every angle "off the grid" by overflow
            raise ValueError(f"{step:g}° is finer than any table's grid; use 0 (continuous) or at least "
                             f"{MIN_STEP_DEG:g}°")
        return step

    @model_validator(mode="after")
    def _point_angles(self) -> Plan:
        step = self.angle_step_deg
        for i, point in enumerate(self.points):
            for axis, angle in zip(("pitch", "roll"), point, strict=True):
                if not -180 <= angle <= 360:
                    raise ValueError(f"point {i + 1}: {axis} {angle:g}° is outside -180..360")
                if not on_grid(angle, step):
                    raise ValueError(
                        f"point {i + 1}: {axis} {angle:g}° is not on the tables' {step:g}° grid "
                        "(set angle_step_deg = 0 for continuously positioned tables)"
                    )
        return self

    @model_validator(mode="after")
    def _determines_coefficients(self) -> Plan:
        if len(self.mounts) * len(self.points) < N_COEFFICIENTS:
            raise ValueError(
                f"{len(self.mounts) * len(self.points)} points per replicate cannot determine "
                f"{N_COEFFICIENTS} coefficients per sensor"
            )
        g = self.nominal_gravity()
        design = np.column_stack([np.ones(len(g)), g])
        if np.linalg.matrix_rank(design, tol=1e-9) < N_COEFFICIENTS:
            raise ValueError(
                "the points do not determine bias and sensitivities (the design is singular); "
                "spread them over more pitch and roll angles"
            )
        return self

    @property
    def mount_list(self) -> list[Mount]:
        return [Mount(y, u) for y, u in self.mounts]

    @property
    def n_points(self) -> int:
        """Points in the whole run, every replicate and mount included."""
        return self.replicates * len(self.mounts) * len(self.points)

    def nominal_gravity(self) -> np.ndarray:
        """Nominal g of one replicate, mount by mount, (len(mounts)·len(points), 3)."""
        p, r = np.radians(np.array(self.points)).T
        return np.concatenate(
            [gravity(p, r, *np.radians([y, u])) for y, u in self.mounts], axis=0
        )

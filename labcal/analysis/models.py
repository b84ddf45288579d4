"""Instrument models as regressor sets over the one least-squares core (docs/design.md §3).

The base model is Soto's [1 gᵀ]; extensions are extra regressors: temperature-corrected
offset and sensitivity, and the 2α / 2R harmonics Tripp & Tcheng see in their residuals.
The coning model (b, S, Ω, A) is not a regressor set but a change of variables of the
base fit (`labcal.analysis.coning`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labcal.analysis.kinematics import Misalignment, gravity, nominal_gravity
from labcal.errors import LabcalError

BASE_NAMES = ("B", "S_x", "S_y", "S_z")


@dataclass(frozen=True)
class Points:
    """Where the instrument was (or will be): table angles and mount in degrees, temperature in °C."""

    pitch_deg: NDArray[np.float64]
    roll_deg: NDArray[np.float64]
    y_deg: NDArray[np.float64]
    u_deg: NDArray[np.float64]
    temp_c: NDArray[np.float64] | None = None

    @classmethod
    def at(cls, pitch_deg: ArrayLike, roll_deg: ArrayLike, y_deg: ArrayLike = 0.0, u_deg: ArrayLike = 0.0,
           temp_c: ArrayLike | None = None) -> Points:
        p, r, y, u = np.broadcast_arrays(*(np.atleast_1d(np.asarray(a, float))
                                           for a in (pitch_deg, roll_deg, y_deg, u_deg)))
        t = None if temp_c is None else np.broadcast_to(np.asarray(temp_c, float), p.shape)
        return cls(p, r, y, u, t)

    def nominal_gravity(self) -> NDArray[np.float64]:
        return nominal_gravity(np.radians(self.pitch_deg), np.radians(self.roll_deg),
                               np.radians(self.y_deg), np.radians(self.u_deg))

    def gravity(self, device: Misalignment | None = None) -> NDArray[np.float64]:
        """The gravity the instrument saw: nominal, or with the calibration device's known
        misalignments ``device`` (Soto eq. 11, row 3 of KM)."""
        if device is None:
            return self.nominal_gravity()
        return gravity(np.radians(self.pitch_deg), np.radians(self.roll_deg), np.radians(self.y_deg),
                       np.radians(self.u_deg), device)


def _temperature(points: Points, t_ref: float, g: NDArray[np.float64]
                 ) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    if points.temp_c is None:
        raise LabcalError("the temperature extension needs a temp_c column in the readings")
    dt = (points.temp_c - t_ref)[:, None]
    return ("dB/dT", "dS_x/dT", "dS_y/dT", "dS_z/dT"), np.hstack([dt, dt * g])


def _harmonics(points: Points, t_ref: float, g: NDArray[np.float64]
               ) -> tuple[tuple[str, ...], NDArray[np.float64]]:
    p, r = np.radians(points.pitch_deg), np.radians(points.roll_deg)
    cols = np.column_stack([np.sin(2 * p), np.cos(2 * p), np.sin(2 * r), np.cos(2 * r)])
    return ("sin 2α", "cos 2α", "sin 2R", "cos 2R"), cols


# Each extension's regressors from the points, the reference temperature and the base model's gravity
EXTENSIONS: dict[str, Callable[[Points, float, NDArray[np.float64]],
                               tuple[tuple[str, ...], NDArray[np.float64]]]] = {
    "temperature": _temperature,
    "harmonics": _harmonics,
}


@dataclass(frozen=True)
class Model:
    """A regressor set: the base [1 gᵀ] plus named extensions; ``t_ref`` centres temperature terms."""

    extensions: tuple[str, ...] = ()
    t_ref: float = 20.0
    dropped: tuple[str, ...] = ()  # extension terms the plan cannot estimate (aliased), left out
    # The calibration device's misalignments a…k where they are known, not identified by the plan (a
    # plan's device correction): the regressors are the gravity they give, so the fit is
    # Soto's linear one with the device model's misalignments held at these values. None: nominal g.
    device: Misalignment | None = None

    def __post_init__(self) -> None:
        unknown = [e for e in self.extensions if e not in EXTENSIONS]
        if unknown:
            raise LabcalError(f"unknown model extension {unknown[0]!r}; choose from {', '.join(EXTENSIONS)}")

    @property
    def per_point(self) -> bool:
        """Every regressor is a function of the calibration point (mount, pitch, roll) alone."""
        return "temperature" not in self.extensions

    def design(self, points: Points) -> tuple[tuple[str, ...], NDArray[np.float64]]:
        """Regressor names and the design matrix F (K×L)."""
        g = points.gravity(self.device)
        names, cols = list(BASE_NAMES), [np.ones((len(g), 1)), g]
        for ext in self.extensions:
            ext_names, ext_cols = EXTENSIONS[ext](points, self.t_ref, g)
            keep = [i for i, n in enumerate(ext_names) if n not in self.dropped]
            names += [ext_names[i] for i in keep]
            cols.append(ext_cols[:, keep])
        return tuple(names), np.hstack(cols)

"""Kinematics of the two-axis calibration device (Soto 2020, §4 and eq. 11).

Angles are radians here; degrees live only at the edges (CLI, files, reports).
Every function is vectorised over points: angles broadcast against each other.
Results are typed float64; the complex-step derivatives of `labcal.analysis.design.audit` pass
complex angles and get complex arrays of the same shapes (numpy's types cannot follow the dtype
of an ArrayLike argument).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

ARCSEC = np.pi / (180 * 3600)
MISALIGNMENT_NAMES = ("a", "b", "d", "e", "f", "k")


def rx(t: ArrayLike) -> NDArray[np.float64]:
    """Textbook rotation about x, stacked over the shape of ``t`` (..., 3, 3)."""
    c, s = np.cos(t), np.sin(t)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([o, z, z, z, c, -s, z, s, c], axis=-1).reshape(*np.shape(c), 3, 3)


def ry(t: ArrayLike) -> NDArray[np.float64]:
    """Textbook rotation about y."""
    c, s = np.cos(t), np.sin(t)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([c, z, s, z, o, z, -s, z, c], axis=-1).reshape(*np.shape(c), 3, 3)


def rz(t: ArrayLike) -> NDArray[np.float64]:
    """Textbook rotation about z."""
    c, s = np.cos(t), np.sin(t)
    o, z = np.ones_like(c), np.zeros_like(c)
    return np.stack([c, -s, z, s, c, z, z, z, o], axis=-1).reshape(*np.shape(c), 3, 3)


def prot(x: ArrayLike) -> NDArray[np.float64]:
    """Pitch rotation, aeronautical sign: Ry(-x). Angles may be complex (complex-step derivatives)."""
    return ry(-np.asarray(x))


def rrot(x: ArrayLike) -> NDArray[np.float64]:
    """Roll rotation: Rx(x)."""
    return rx(np.asarray(x))


def yrot(x: ArrayLike) -> NDArray[np.float64]:
    """Yaw rotation, aeronautical sign: Rz(-x)."""
    return rz(-np.asarray(x))


@dataclass(frozen=True)
class Misalignment:
    """The six grouped CD misalignments of Soto Table 1, in radians.

    a, b: pitch and roll of the device as a rigid body; d: yaw between the tables;
    e, f: pitch and roll of the x–y plate; k: yaw of the x–z dowels. Each may be a scalar
    or an array over points (index and wobble errors vary from point to point).
    """

    a: ArrayLike = 0.0
    b: ArrayLike = 0.0
    d: ArrayLike = 0.0
    e: ArrayLike = 0.0
    f: ArrayLike = 0.0
    k: ArrayLike = 0.0

    @classmethod
    def from_degrees(cls, **angles_deg: float) -> Misalignment:
        return cls(**{name: np.radians(value) for name, value in angles_deg.items()})

    def __add__(self, other: Misalignment) -> Misalignment:
        return Misalignment(
            **{f.name: np.add(getattr(self, f.name), getattr(other, f.name)) for f in fields(self)}
        )

    def degrees(self) -> dict[str, float]:
        return {name: float(np.degrees(getattr(self, name))) for name in MISALIGNMENT_NAMES}


NO_MISALIGNMENT = Misalignment()


def device_matrix(
    pitch: ArrayLike, roll: ArrayLike, y: ArrayLike, u: ArrayLike, mis: Misalignment = NO_MISALIGNMENT
) -> NDArray[np.float64]:
    """KM of Soto eq. 11: columns are the instrument's x, y, z axes in the gravity frame.

    KM = rrot[b]·prot[p]·prot[a]·yrot[d]·rrot[r]·rrot[f]·prot[e]·yrot[k]·yrot[y]·rrot[u]
    """
    chain = device_chain(pitch, roll, y, u, mis)
    km = chain[0]
    for m in chain[1:]:
        km = km @ m
    return km


def device_chain(
    pitch: ArrayLike, roll: ArrayLike, y: ArrayLike, u: ArrayLike, mis: Misalignment = NO_MISALIGNMENT
) -> tuple[NDArray[np.float64], ...]:
    """The ten factors of KM (Soto eq. 11), left to right."""
    return (
        rrot(mis.b), prot(pitch), prot(mis.a), yrot(mis.d), rrot(roll),
        rrot(mis.f), prot(mis.e), yrot(mis.k), yrot(y), rrot(u),
    )


# Where each misalignment sits in `device_chain` and the generator G of its factor: the derivative of
# a factor R(x) with respect to x is R(x)·G (rrot = Rx(x): +Kx; prot = Ry(−x): −Ky; yrot = Rz(−x): −Kz).
_KX = np.array([[0.0, 0, 0], [0, 0, -1], [0, 1, 0]])
_KY = np.array([[0.0, 0, 1], [0, 0, 0], [-1, 0, 0]])
_KZ = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 0]])
_FACTOR = {"a": (2, -_KY), "b": (0, _KX), "d": (3, -_KZ), "e": (6, -_KY), "f": (5, _KX), "k": (7, -_KZ)}


def gravity_jacobian(
    pitch: ArrayLike, roll: ArrayLike, y: ArrayLike, u: ArrayLike, mis: Misalignment = NO_MISALIGNMENT
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True gravity (..., 3) and its analytic derivatives with respect to a, b, d, e, f, k
    (..., 6, 3), in `MISALIGNMENT_NAMES` order: what the device model's Gauss–Newton needs.

    g = e₃ᵀ·F₀·…·F₉; ∂g/∂x for the factor Fq(x) is e₃ᵀ·F₀…Fq·G·Fq₊₁…F₉. Only row 3 of KM is
    carried on the left, so the prefixes are vectors and only the suffixes are matrices.
    """
    chain = device_chain(pitch, roll, y, u, mis)
    rows = [chain[0][..., 2, :]]  # e₃ᵀ·F₀…Fq
    for m in chain[1:]:
        rows.append(np.einsum("...i,...ij->...j", rows[-1], m))
    suffix: list[NDArray[np.float64]] = [np.eye(3)] * (len(chain) + 1)  # suffix[q] = Fq…F₉
    for q in range(len(chain) - 1, -1, -1):
        suffix[q] = chain[q] @ suffix[q + 1]
    derivatives = [np.einsum("...i,...ij->...j", rows[q] @ generator, suffix[q + 1])
                   for q, generator in (_FACTOR[name] for name in MISALIGNMENT_NAMES)]
    shape = np.broadcast_shapes(rows[-1].shape, *(d.shape for d in derivatives))
    dg = np.stack([np.broadcast_to(d, shape) for d in derivatives], axis=-2)
    return np.broadcast_to(rows[-1], shape), dg


def gravity(
    pitch: ArrayLike, roll: ArrayLike, y: ArrayLike, u: ArrayLike, mis: Misalignment = NO_MISALIGNMENT
) -> NDArray[np.float64]:
    """Gravity (in g) seen by the instrument's x, y, z sensors: row 3 of KM, shape (..., 3).

    With ``mis`` zero this is the *nominal* gravity the fit uses; with the device's
    misalignments it is the *true* gravity that drives the instrument.
    """
    return device_matrix(pitch, roll, y, u, mis)[..., 2, :]


def nominal_gravity(pitch: ArrayLike, roll: ArrayLike, y: ArrayLike, u: ArrayLike) -> NDArray[np.float64]:
    """`gravity` with every misalignment zero, in closed form: row 3 of prot[p]·rrot[r] is
    [sin p, cos p sin r, cos p cos r] (§2), then turned by yrot[y]·rrot[u]. The fit asks it for
    every reading; the ten stacked 3×3 products of the general chain cost a million-row file
    seconds and gigabytes."""
    p, r, y, u = (np.asarray(a, dtype=float) for a in (pitch, roll, y, u))
    cp = np.cos(p)
    a0, a1, a2 = np.sin(p), cp * np.sin(r), cp * np.cos(r)
    cy, sy, cu, su = np.cos(y), np.sin(y), np.cos(u), np.sin(u)
    b1 = a0 * sy + a1 * cy
    return np.stack(np.broadcast_arrays(a0 * cy - a1 * sy, b1 * cu + a2 * su, a2 * cu - b1 * su), axis=-1)


@dataclass(frozen=True)
class Mount:
    """One of the four mounting orientations (Soto Table 3), in degrees."""

    y_deg: float
    u_deg: float

    @property
    def radians(self) -> tuple[float, float]:
        return float(np.radians(self.y_deg)), float(np.radians(self.u_deg))

    def describe(self) -> str:
        """The orientation in the words a technician uses at the bench."""
        side = "top" if self.u_deg % 360 == 0 else "bottom"
        direction = "forward" if self.y_deg % 360 == 0 else "backward"
        return f"{side} side of the plate, x sensor pointing {direction}"

    def __str__(self) -> str:
        return f"y={self.y_deg:g}°, u={self.u_deg:g}°"


def mount_gravity(pitch_deg: float, roll_deg: float, mount: Mount) -> NDArray[np.float64]:
    """Nominal gravity at table angles in degrees on one mount: what the run machinery expects at a
    point (degrees at the edge, radians inside)."""
    y, u = mount.radians
    return nominal_gravity(math.radians(pitch_deg), math.radians(roll_deg), y, u)


MOUNTS = (Mount(0, 0), Mount(180, 0), Mount(0, 180), Mount(180, 180))


@dataclass(frozen=True)
class IndexWobble:
    """Per-point index and wobble errors of the two tables (Soto Table 1: a2, d1, f1, f3, e1, k1).

    Each error is a fixed function of its table's angle — a real table errs the same way
    every time it returns to an angle — modelled as harmonics 1–3 of that angle with
    random phases and weights summing to one, so its magnitude never exceeds the stated
    amplitude and it averages to zero over a revolution and over any four points 90° apart.
    """

    index_arcsec: float = 0.0
    wobble_arcsec: float = 0.0
    seed: int = 0

    @cached_property
    def _terms(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Weights and phases, drawn once per table (the simulator asks at every filter step)."""
        rng = np.random.default_rng([self.seed, 0x1DE4])
        weights = rng.dirichlet(np.ones(3), size=6)  # a2 d1 f1 | f3 e1 k1
        phases = rng.uniform(0, 2 * np.pi, size=(6, 3))
        return weights, phases

    def misalignment(self, pitch: ArrayLike, roll: ArrayLike) -> Misalignment:
        """The point-dependent part of the misalignments at these table angles (radians)."""
        if self.index_arcsec == 0 and self.wobble_arcsec == 0:
            return NO_MISALIGNMENT
        weights, phases = self._terms
        h = np.arange(1, 4)
        amp = np.array([self.index_arcsec, self.wobble_arcsec, self.wobble_arcsec,
                        self.index_arcsec, self.wobble_arcsec, self.wobble_arcsec]) * ARCSEC

        def err(i: int, angle: ArrayLike) -> NDArray[np.float64]:
            angle = np.asarray(angle, dtype=float)[..., None]
            e: NDArray[np.float64] = amp[i] * np.sum(weights[i] * np.sin(h * angle + phases[i]), axis=-1)
            return e

        return Misalignment(
            a=err(0, pitch), d=err(1, pitch), f=err(2, pitch) + err(3, roll),
            e=err(4, roll), k=err(5, roll),
        )

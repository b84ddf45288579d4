"""The device model: the instrument and the calibration device's six misalignments in one
regression (Soto's promised Part 2; docs/design.md §3), and what a plan can identify of it.

V = B + g_true(p, r, y, u; a, b, d, e, f, k)ᵀ S with g_true from the kinematics of Soto eq. 11
(`labcal.analysis.kinematics`). Parameters θ = [a, b, d, e, f, k (rad); B (3); S (9, in the
rows of Soto's X = [Bᵀ; S] below B)], so that θ[6:] is X.ravel() in the linear fit's layout.

Identifiability is a property of the geometry, not of the data: it is computed here for an
ideal instrument (B = 0, S = I, no misalignment) at the plan's points, from the singular
values and null space of the column-scaled Jacobian. A null direction is a combination of
parameters that moves no reading; the misalignment in it is *confounded* with the coefficients
in it, and adding a mount that breaks the combination is the remedy, found by trying each.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.kinematics import (
    ARCSEC,
    MISALIGNMENT_NAMES,
    MOUNTS,
    NO_MISALIGNMENT,
    Misalignment,
    Mount,
    gravity,
    gravity_jacobian,
)
from labcal.analysis.replication import first_rows, point_groups

SENSORS = ("x", "y", "z")
N_MIS = len(MISALIGNMENT_NAMES)
# X[1 + l, j] is sensor j's sensitivity to g_l, written S_jl ("S_xy": sensor x, gravity y).
PARAMETER_NAMES = (*MISALIGNMENT_NAMES, *(f"B_{s}" for s in SENSORS),
                   *(f"S_{SENSORS[j]}{SENSORS[g]}" for g in range(3) for j in range(3)))
N_PARAMETERS = len(PARAMETER_NAMES)
NULL_TOLERANCE = 1e-9  # singular value of the column-scaled Jacobian, relative to the largest, that is 0
USELESS_U_ARCSEC_PER_UG = 10.0  # a misalignment this uncertain per µg of reading noise is not worth fitting
MICRO_G = 1e-6


@dataclass(frozen=True)
class Geometry:
    """Where readings were taken, in radians: table angles and mount per reading."""

    pitch: NDArray[np.float64]
    roll: NDArray[np.float64]
    y: NDArray[np.float64]
    u: NDArray[np.float64]

    @classmethod
    def from_degrees(cls, pitch_deg: Any, roll_deg: Any, y_deg: Any, u_deg: Any) -> Geometry:
        p, r, y, u = np.broadcast_arrays(*(np.radians(np.asarray(a, float)) for a in
                                           (pitch_deg, roll_deg, y_deg, u_deg)))
        return cls(p, r, y, u)

    @classmethod
    def of_plan(cls, points: list[tuple[float, float]], mounts: list[tuple[float, float]]) -> Geometry:
        """Every point on every mount, once."""
        rows = np.array([(p, r, y, u) for y, u in mounts for p, r in points], dtype=float)
        return cls.from_degrees(*rows.T)

    def distinct(self) -> Geometry:
        """One reading per distinct point (replicates add no geometry)."""
        keys = np.round(np.column_stack([self.pitch, self.roll, self.y, self.u]) % (2 * np.pi), 12)
        first = np.sort(first_rows(*point_groups(keys)))  # in reading order
        return Geometry(self.pitch[first], self.roll[first], self.y[first], self.u[first])

    def with_mount(self, mount: Mount) -> Geometry:
        """These points plus the same table angles on another mount."""
        y, u = mount.radians
        pr: NDArray[np.float64] = np.unique(np.round(np.column_stack([self.pitch, self.roll]), 12), axis=0)
        extra = Geometry(pr[:, 0], pr[:, 1], np.full(len(pr), y), np.full(len(pr), u))
        return Geometry(*(np.concatenate([getattr(self, f), getattr(extra, f)])
                          for f in ("pitch", "roll", "y", "u")))

    @property
    def mounts(self) -> set[tuple[float, float]]:
        return {(round(float(np.degrees(y))) % 360, round(float(np.degrees(u))) % 360)
                for y, u in np.column_stack([self.y, self.u])}


def split(theta: NDArray[np.float64]) -> tuple[Misalignment, NDArray[np.float64]]:
    """θ → the misalignments and X (4×3)."""
    return Misalignment(*theta[:N_MIS]), theta[N_MIS:].reshape(4, 3)


def predict(theta: NDArray[np.float64], where: Geometry) -> NDArray[np.float64]:
    """Noise-free readings (K×3) of the device model."""
    mis, X = split(theta)
    volts: NDArray[np.float64] = X[0] + gravity(where.pitch, where.roll, where.y, where.u, mis) @ X[1:]
    return volts


def jacobian(theta: NDArray[np.float64], where: Geometry, offsets: Misalignment = NO_MISALIGNMENT
             ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Readings (K×3) and their analytic derivatives (K×3×18) with respect to θ; ``offsets`` adds
    per-point misalignments (the tables' index errors, `labcal.analysis.index_errors`)."""
    mis, X = split(theta)
    g, dg = gravity_jacobian(where.pitch, where.roll, where.y, where.u, mis + offsets)
    n = len(g)
    jac = np.empty((n, 3, N_PARAMETERS))
    jac[:, :, :N_MIS] = np.swapaxes(dg @ X[1:], 1, 2)  # ∂V_j/∂m = (∂g/∂m)·S[:, j]
    jac[:, :, N_MIS:N_MIS + 3] = np.eye(3)
    # ∂V_j/∂X[1+l, k] = g_l δ_jk
    jac[:, :, N_MIS + 3:] = np.einsum("il,jk->ijlk", g, np.eye(3)).reshape(n, 3, 9)
    return X[0] + g @ X[1:], jac


# θ of a perfect instrument on a perfect device
IDEAL = np.concatenate([np.zeros(N_MIS + 3), np.eye(3).ravel()])


@dataclass(frozen=True)
class Confounding:
    """One direction the readings cannot see: a misalignment with a combination of coefficients."""

    misalignments: tuple[str, ...]
    combination: dict[str, float]  # coefficient name → weight (largest magnitude 1)
    remedy: Mount | None  # a mount whose addition separates them, if one does

    @property
    def terms(self) -> str:
        parts = []
        for i, (name, w) in enumerate(self.combination.items()):
            sign = "−" if w < 0 else ("+" if i else "")
            magnitude = "" if np.isclose(abs(w), 1.0, atol=1e-6) else f"{abs(w):.3g}·"
            parts.append(f"{sign} {magnitude}{name}".strip() if i else f"{sign}{magnitude}{name}")
        return " ".join(parts)

    def describe(self) -> str:
        """In a metrologist's words, with the mount to add."""
        what = " and ".join(self.misalignments)
        verb = "is" if len(self.misalignments) == 1 else "are"
        text = f"{what} {verb} confounded with {self.terms}" if self.combination else \
            f"{what} {verb} not seen by these readings"
        if self.remedy is None:
            return text + ": spread the points over more pitch and roll angles"
        y, u = int(self.remedy.y_deg), int(self.remedy.u_deg)
        return text + f": add a mount on the {self.remedy.describe()} (y = {y}°, u = {u}°)"

    def to_json(self) -> dict[str, Any]:
        return {"misalignments": list(self.misalignments), "coefficients": self.combination,
                "description": self.describe(),
                "add_mount": None if self.remedy is None else [self.remedy.y_deg, self.remedy.u_deg]}


@dataclass(frozen=True)
class Identifiability:
    """What a set of points can tell about θ, for an ideal instrument."""

    rank: int
    condition: float  # of the Jacobian in radians and V/g at an ideal instrument; inf when rank < 18
    u_per_ug: dict[str, float]  # standard uncertainty (arcsec) of each misalignment per µg of reading noise
    confounded: tuple[Confounding, ...]

    @property
    def complete(self) -> bool:
        return self.rank == N_PARAMETERS

    @property
    def useless(self) -> tuple[str, ...]:
        """Misalignments identified in principle but too uncertain to be worth estimating."""
        return tuple(n for n, u in self.u_per_ug.items() if np.isfinite(u) and u > USELESS_U_ARCSEC_PER_UG)

    @property
    def estimable(self) -> bool:
        """Whether the device model is worth fitting on these points."""
        return self.complete and not self.useless

    def problem(self) -> str | None:
        """One line saying what these points cannot see, or None when they see all six."""
        if not self.complete:
            return "; ".join(c.describe() for c in self.confounded)
        if self.useless:
            worst = max(self.u_per_ug.values())
            verb = "is" if len(self.useless) == 1 else "are"
            return (f"{', '.join(self.useless)} {verb} so ill-conditioned "
                    f"(up to {worst:.3g}″ per µg of noise, condition {self.condition:.3g}) that the estimate "
                    "would be useless: spread the pitch angles (not only 0° and 180°)")
        return None

    def to_json(self) -> dict[str, Any]:
        return {"rank": self.rank, "parameters": N_PARAMETERS,
                "condition": self.condition if np.isfinite(self.condition) else None,
                "u_arcsec_per_ug_noise": {n: (u if np.isfinite(u) else None)
                                          for n, u in self.u_per_ug.items()},
                "confounded": [c.describe() for c in self.confounded],
                "confounded_directions": [c.to_json() for c in self.confounded],
                "ill_conditioned": list(self.useless)}


def _scaled_jacobian(where: Geometry) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The Jacobian (3K×18) at an ideal instrument and its column norms; a column of rounding noise
    keeps scale 1 so that it stays near zero, a null direction."""
    _, jac = jacobian(IDEAL, where)
    jac = jac.reshape(-1, N_PARAMETERS)
    scale = np.linalg.norm(jac, axis=0)
    scale[scale <= 1e-12 * scale.max()] = 1.0
    return jac, scale


def _null_space(where: Geometry) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Singular values of the column-scaled Jacobian at an ideal instrument, and its null space in
    θ's own units (18×q)."""
    jac, scale = _scaled_jacobian(where)
    r = np.linalg.qr(jac / scale, mode="r")  # same singular values and right vectors, at most 18×18
    _, sv, vt = np.linalg.svd(r)  # r is 18×18, or shorter when there are fewer than 18 readings
    sv = np.concatenate([sv, np.zeros(N_PARAMETERS - len(sv))])
    null = sv <= NULL_TOLERANCE * sv[0]
    return sv, vt[null].T / scale[:, None]


def _named_directions(null: NDArray[np.float64]) -> list[tuple[tuple[str, ...], dict[str, float], int]]:
    """The null space in a basis with one pivot misalignment per direction (Gauss–Jordan on the
    misalignment rows), each named: (misalignments, coefficient combination, pivot index)."""
    basis = null.copy()
    pivots: list[int] = []
    for col in range(basis.shape[1]):
        rows = [i for i in range(N_MIS) if i not in pivots]
        if not rows:
            break
        i = max(rows, key=lambda r: abs(basis[r, col]))
        if abs(basis[i, col]) < 1e-9:
            continue
        basis[:, col] /= basis[i, col]
        for other in range(basis.shape[1]):
            if other != col:
                basis[:, other] -= basis[i, other] * basis[:, col]
        pivots.append(i)
    named = []
    for col, pivot in zip(range(basis.shape[1]), pivots, strict=False):
        v = basis[:, col]
        mis = tuple(MISALIGNMENT_NAMES[i] for i in range(N_MIS) if abs(v[i]) > 1e-6)
        coef = v[N_MIS:]  # per radian of the pivot misalignment, for S = I: of order one when present
        big = np.max(np.abs(coef))
        order = [i for i in np.argsort(-coef, kind="stable") if abs(coef[i]) > 1e-6]
        combination = {PARAMETER_NAMES[N_MIS + i]: float(coef[i] / big) for i in order}
        named.append((mis, combination, pivot))
    return named


def identifiability(where: Geometry) -> Identifiability:
    """Rank, condition, u per unit noise and the confounded directions of these points."""
    where = where.distinct()
    sv, null = _null_space(where)
    rank = int(np.sum(sv > NULL_TOLERANCE * sv[0]))
    jac, scale = _scaled_jacobian(where)
    natural = np.linalg.svd(np.linalg.qr(jac, mode="r"), compute_uv=False)
    condition = float(natural[0] / natural[-1]) if rank == N_PARAMETERS else float("inf")
    r: NDArray[np.float64] = np.linalg.qr(jac / scale, mode="r")  # type: ignore[assignment]
    cov = np.linalg.pinv(r.T @ r, rcond=NULL_TOLERANCE**2) / np.outer(scale, scale)
    u_per_ug = {}
    for i, name in enumerate(MISALIGNMENT_NAMES):
        seen = null.shape[1] == 0 or np.max(np.abs(null[i])) < 1e-6 * max(1.0, np.max(np.abs(null)))
        seen = seen and cov[i, i] > 0
        u_per_ug[name] = float(np.sqrt(cov[i, i]) * MICRO_G / ARCSEC) if seen else float("inf")
    confounded = []
    for mis, combination, pivot in sorted(_named_directions(null), key=lambda d: d[2]):
        confounded.append(Confounding(mis, combination, _remedy(where, pivot)))
    return Identifiability(rank, condition, u_per_ug, tuple(confounded))


def _remedy(where: Geometry, pivot: int) -> Mount | None:
    """The first of the four mounts, not yet used, whose addition makes this misalignment visible."""
    used = where.mounts
    for mount in MOUNTS:
        if (mount.y_deg % 360, mount.u_deg % 360) in used:
            continue
        _, null = _null_space(where.with_mount(mount))
        if null.shape[1] == 0 or np.max(np.abs(null[pivot])) < 1e-6 * np.max(np.abs(null)):
            return mount
    return None

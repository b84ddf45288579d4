"""The GUM uncertainty budget of the coefficients and of inferred pitch and roll (JCGM 100).

Every source is a set of independent *elementary inputs* (one per sensor for the DMM's gain error,
one per distinct table angle for an index error, one per mounting for mount repeatability, ...)
with one distribution, one standard uncertainty in its own unit and one number of degrees of
freedom, and two Jacobians: ``jac_x`` (12 × m), how each input moves the twelve coefficients
vec(X) (row-major, X[i, j] at 3i + j), and ``jac_v`` (3 × m), how it moves one new reading of the
instrument in use. What happens at the bench reaches the coefficients through the same least
squares the fit uses: a table that errs by δ at a point makes the instrument see gravity g + δg,
the fit still regresses on the nominal g, so X moves by P·(δg S) with P = (FᵀF)⁻¹Fᵀ. Errors that
repeat wherever a table returns to an angle are one input per angle, not one per reading — which
is why a four-mount plan cancels most of them and the budget shows it, instead of averaging them
away as if they were noise.

A user infers attitude z = (pitch, roll) from a new reading with the calibrated X by weighted least
squares on the sphere (`labcal.analysis.attitude.sphere_least_squares`). Linearised at z, a change
δv of the effective output moves the estimate by A·δv with A = (F W Fᵀ)⁻¹ F W (F = ∂f/∂z, W the
estimator's weights): a coefficient error δX acts as δv = −f(z)·δX, a reading error as itself.
Each source's contribution is then u_i(z) = √(Σ_m (A δv_m u_m)²); the Type A sources alone give
back exactly the estimator's own covariance, so the budget collapses to today's Type A values when
every Type B input is zero. Degrees of freedom combine by Welch–Satterthwaite (GUM G.4.1) and
k = t₀.₉₇₅(ν_eff).

Local gravity: the outputs are fitted against gravity normalised to 1 g, and in use the sphere
estimator takes |g| as unknown within ±LOCAL_GRAVITY_TOLERANCE of the calibration's (a prior), so a
different local gravity leaves the direction alone; the prior itself is a source, propagated through
the estimator (`labcal.analysis.attitude.sphere_sensitivity`), not through the outputs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.attitude import (
    LOCAL_GRAVITY_TOLERANCE,
    LOCAL_GRAVITY_U,
    N_ERRORS,
    CovariancePart,
    _gravity_and_derivatives,
    combined_uncertainty,
    coverage_factor,
    sphere_sensitivity,
)
from labcal.analysis.device_fit import DeviceFit, angle_error_shapes
from labcal.analysis.device_model import N_MIS
from labcal.analysis.distributions import welch_satterthwaite
from labcal.analysis.fit import Fit, readings_points
from labcal.analysis.kinematics import ARCSEC, Misalignment, gravity
from labcal.analysis.models import Points
from labcal.analysis.readings import Readings
from labcal.analysis.repeatability import Repeatability, repeatability

Distribution = Literal["normal", "rectangular", "t"]
SQRT3 = float(np.sqrt(3.0))
COVERAGE = 0.95
COMPLEX_STEP = 1e-30

LOCAL_GRAVITY = "local gravity"  # the budget row of the estimator's prior on |g|


@dataclass(frozen=True)
class TypeBInputs:
    """The bench's Type B inputs, in SI units; half-widths of rectangular distributions unless said.
    Zero means "not a source here"."""

    dmm_reading: float = 0.0  # relative, of reading (34970A 1 year, 10 V: 3.5e-5)
    dmm_range_v: float = 0.0  # volts: % of range × range (34970A 1 year, 10 V range: 5e-6 × 10 V)
    dmm_noise_v: float = 0.0  # rms of one averaged reading; shown, already in the fit's Type A
    dmm_conditions: str = ""  # the range and integration time the accuracy applies to, as stated
    # The unit the readings are in (V, mV, counts, m/s2): the residual variance and the reader's
    # absolute terms (dmm_range_v, dmm_noise_v, given in that unit) are stated in it.
    output_unit: str = "V"
    # Inputs whose error is one and the same in the three channels ("dmm_reading", "dmm_range"): a
    # scanning DMM reads them through one ADC. A common gain scales X as a whole and largely cancels
    # in the attitude (a direction); declared independent it would be counted three times over.
    common: tuple[str, ...] = ()
    pitch_index: float = 0.0  # rad
    pitch_wobble: float = 0.0
    roll_index: float = 0.0
    roll_wobble: float = 0.0
    mount_repeatability: float = 0.0  # rad, each of the plate's pitch, roll and yaw per mounting
    # σ (rad, normal) of the same, estimated from the replicates' scatter of the mount groups
    # (`labcal.analysis.remounting`); None: no mount was seated twice, the station file's value is used
    mount_repeatability_sd: float | None = None
    mount_repeatability_dof: int | None = None
    temperature_half_range_k: float = 0.0  # half the temperature range observed during the run
    bias_tempco_v_per_k: float = 0.0
    sensitivity_tempco_per_k: float = 0.0
    # Standard uncertainties (rad, normal) of the device misalignments a…k where a device model
    # estimated them (`fit --model device`); empty: the row is absent.
    device_misalignment: dict[str, float] = field(default_factory=dict)
    # Where they are not this run's estimates but a plan's device correction: the estimate
    # they come from, in words (""; the device model of this run estimated them).
    device_misalignment_source: str = ""


@dataclass(frozen=True)
class Component:
    jac_x: NDArray[np.float64]  # (12, m)
    jac_v: NDArray[np.float64]  # (3, m)
    u: float  # standard uncertainty of each elementary input, in its unit
    dof: float  # np.inf for Type B
    distribution: Distribution
    # Components naming the same estimate share one variance estimate (a sensor's residual variance
    # sets both its coefficients' covariance and one new reading's variance): one term in
    # Welch–Satterthwaite, and one χ² draw in the Monte Carlo.
    estimate: str = ""


@dataclass(frozen=True)
class Source:
    name: str
    type: Literal["A", "B"]
    distribution: str
    u: float  # standard uncertainty in its own unit, as stated (the largest where there are several)
    unit: str
    components: tuple[Component, ...]
    added: bool = True  # False: shown for completeness, already inside another row
    note: str = ""

    @property
    def dof(self) -> float:
        return min((c.dof for c in self.components), default=np.inf)


# --- the calibration's geometry -----------------------------------------------------------------
@dataclass(frozen=True)
class Calibration:
    """What the budget needs of a fit: X, the per-sensor Type A covariance of (B, S) and its dof, one
    new reading's Type A variance, and the projection P = first four rows of (FᵀF)⁻¹Fᵀ."""

    X: NDArray[np.float64]  # (4, 3)
    covariance: NDArray[np.float64]  # (3, 4, 4)
    reading_var: NDArray[np.float64]  # (3,)
    dof: NDArray[np.float64]  # (3,)
    projection: NDArray[np.float64]  # (4, K)
    points: Points
    installation: NDArray[np.int_]  # (K,) one id per mounting (replicate × mount)
    # The per-sensor covariance the attitude estimator weights by, where it is not ``covariance``: a
    # device-model certificate states the marginal covariance of (B, S), and `labcal attitude`
    # weights by what the certificate states.
    estimator_covariance: NDArray[np.float64] | None = None
    # ∂vec(X)/∂V (12 × K × 3) where the fit is not linear in the readings' regressors: the device model
    # re-estimates the misalignments with X, so a bench error reaches X through its own projection
    # (None: the linear fit's, P per sensor).
    reading_projection: NDArray[np.float64] | None = None
    # The instrument's own repeatability (the pooled scatter inside the calibration's windows) and the
    # samples a reading in use averages: the new-reading row. None: the readings do not carry their
    # windows' scatter, and one new reading's variance is ``reading_var`` (the fit's residual).
    repeatability: Repeatability | None = None
    in_use_samples: int | None = None
    noise_type_a: bool = False  # the coefficients' Type A is the windows' noise (`with_noise_covariance`)

    @property
    def in_use_samples_or_calibration(self) -> int | None:
        """The samples a reading in use averages: as stated, else the calibration's window length."""
        if self.repeatability is None:
            return None
        return self.in_use_samples or self.repeatability.window_samples


def calibration_of(fit: Fit, readings: Readings, in_use_samples: int | None = None, noise: bool = True
                   ) -> Calibration:
    """The budget's view of a fit of these readings; ``in_use_samples``: the samples a reading in use
    averages (None: as many as the calibration's windows); ``noise``: the coefficients' Type A from
    the windows' scatter where the readings carry it (`with_noise_covariance`), else the fit's."""
    points = readings_points(readings)
    _, design = fit.model.design(points)
    keys = np.column_stack([readings.replicate, np.mod(readings.y_deg, 360.0), np.mod(readings.u_deg, 360.0)])
    _, installation = np.unique(np.round(keys, 6), axis=0, return_inverse=True)
    cal = Calibration(
        X=fit.coefficients, covariance=np.stack([fit.covariance(j)[:4, :4] for j in range(3)]),
        reading_var=fit.new_measurement_variance(), dof=fit.variance_dof.astype(float),
        projection=(fit.ls.cov_unscaled @ design.T)[:4], points=points,
        installation=np.asarray(installation, dtype=int).ravel(), repeatability=repeatability(readings),
        in_use_samples=in_use_samples)
    return with_noise_covariance(cal, readings) if noise else cal


def calibration_of_device(device: DeviceFit, readings: Readings, in_use_samples: int | None = None
                          ) -> Calibration:
    """The budget's view of a device-model fit: X and one new reading's variance are the device
    model's; the Type A covariance is the device model's noise share conditional on a…k (what the
    readings' noise does to X with the misalignments held at their estimates); the misalignments' own
    noise share is the budget's device-misalignment row. Bench errors (the tables' index and wobble,
    a remount) reach X through the device model's own projection, which re-estimates a…k with X: the
    tables' angle errors enter once, as the table rows, not also through the misalignments' u."""
    cov = device.noise_covariance
    m = slice(0, N_MIS)
    rest = slice(N_MIS, None)
    conditional = cov[rest, rest] - cov[rest, m] @ np.linalg.pinv(cov[m, m]) @ cov[m, rest]
    per_sensor = np.stack([conditional[np.ix_(idx, idx)] for idx in (np.arange(4) * 3 + j for j in range(3))])
    return with_noise_covariance(replace(
        calibration_of(device.linear, readings, in_use_samples, noise=False), X=device.coefficients,
        covariance=per_sensor, reading_var=device.reading_sd() ** 2, dof=np.full(3, float(device.dof)),
        estimator_covariance=np.stack([device.sensor_covariance(j) for j in range(3)]),
        reading_projection=device.reading_projection(readings)[N_MIS:]), readings)


def with_noise_covariance(cal: Calibration, readings: Readings) -> Calibration:
    """The coefficients' Type A from the instrument's noise alone, where the readings carry their
    windows' scatter: each point's mean scatters by s_j²/n_k (s_j the pooled within-window scatter,
    `labcal.analysis.repeatability`), carried to X by the fit's own gain ∂X/∂V, with the pooled
    scatter's degrees of freedom. The residual variance the fit scales (FᵀF)⁻¹ by also holds the
    bench's errors — the tables' per-angle errors, the plate's seating — which the budget's Type B
    rows already carry to X through the same gain (a four-mount plan cancels most of them there);
    scaled by it, those errors were counted twice. The attitude estimator keeps its weights (the
    certificate's fit covariance), so that `labcal attitude` and the budget use one estimator."""
    if cal.repeatability is None or readings.window_n is None:
        return cal
    return windows_noise_covariance(cal, cal.repeatability, np.asarray(readings.window_n, dtype=float))


def windows_noise_covariance(cal: Calibration, rep: Repeatability, window_n: NDArray[np.float64]
                             ) -> Calibration:
    """`with_noise_covariance`'s rule for windows of ``window_n`` samples (K,) scattering as ``rep``
    says: also what a plan's prediction of its certificate uses (`labcal.analysis.optimize`), so that
    the two cannot differ."""
    var_mean = rep.sample_sd[None, :] ** 2 / window_n[:, None]  # (K, 3)
    if cal.reading_projection is not None:
        gain = cal.reading_projection  # (12, K, 3)
    else:  # the linear fit: sensor j's coefficients move with sensor j's readings only
        gain = np.zeros((12, cal.projection.shape[1], 3))
        for j in range(3):
            gain[np.arange(4) * 3 + j, :, j] = cal.projection
    cov = np.einsum("akc,bkc,kc->ab", gain, gain, var_mean)
    per_sensor = np.stack([cov[np.ix_(idx, idx)] for idx in (np.arange(4) * 3 + j for j in range(3))])
    return replace(cal, covariance=per_sensor, dof=np.full(3, rep.dof), noise_type_a=True, repeatability=rep,
                   estimator_covariance=cal.covariance if cal.estimator_covariance is None
                   else cal.estimator_covariance)


def _gravity_derivative(points: Points, name: str) -> NDArray[np.float64]:
    """∂g/∂(misalignment ``name``) at every calibration point (K×3), by complex step: exact."""
    p, r, y, u = (np.radians(a) for a in (points.pitch_deg, points.roll_deg, points.y_deg, points.u_deg))
    g = gravity(p, r, y, u, Misalignment(**{name: 1j * COMPLEX_STEP}))
    return np.asarray(np.imag(g) / COMPLEX_STEP, dtype=float)


def _membership(groups: NDArray[np.int_]) -> NDArray[np.float64]:
    """One column per group (one table angle, one mounting, or all points): 1 at its points."""
    member = np.zeros((len(groups), int(groups.max()) + 1))
    member[np.arange(len(groups)), groups] = 1.0
    return member


def _grouped(cal: Calibration, names: tuple[str, ...], basis: NDArray[np.float64], linear: bool = False
             ) -> NDArray[np.float64]:
    """∂vec(X)/∂e for one input per (basis column, misalignment name): an input moves the misalignment
    at every point by its column's value there (1 in its group, or a harmonic of the table angle),
    through the fit's projection (with ``linear``, the linear fit's: an error in a correction applied
    to the readings)."""
    blocks = []
    for name in names:
        dv = _gravity_derivative(cal.points, name) @ cal.X[1:]  # (K, 3): δV per unit input at each point
        if cal.reading_projection is not None and not linear:
            blocks.append(np.einsum("ikc,kc,km->im", cal.reading_projection, dv, basis))
        else:
            blocks.append(np.einsum("ik,kj,km->ijm", cal.projection, dv, basis).reshape(12, basis.shape[1]))
    return np.concatenate(blocks, axis=1)


def _factor(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """L with L Lᵀ = cov for a covariance that may be singular (noise-free data give zeros)."""
    w, v = np.linalg.eigh(cov)
    return np.asarray(v * np.sqrt(np.clip(w, 0.0, None)), dtype=float)


def _b(jac_x: NDArray[np.float64], u: float, distribution: Distribution = "rectangular") -> Component:
    return Component(jac_x, np.zeros((3, jac_x.shape[1])), u, np.inf, distribution)


Shapes = tuple[tuple[NDArray[np.float64], float], ...]  # a table error's bases over its angles


def _table_inputs(cal: Calibration, b: TypeBInputs) -> tuple[tuple[str, tuple[str, ...], Shapes, float], ...]:
    """Each table error: its row's label, the misalignments it moves, its shapes over the table's
    angles (`angle_error_shapes`) and its stated half-width."""
    pitch_shapes = angle_error_shapes(np.radians(cal.points.pitch_deg))
    roll_shapes = angle_error_shapes(np.radians(cal.points.roll_deg))
    return (("pitch table index accuracy", ("a",), pitch_shapes, b.pitch_index),
            ("pitch table wobble", ("d", "f"), pitch_shapes, b.pitch_wobble),
            ("roll table index accuracy", ("f",), roll_shapes, b.roll_index),
            ("roll table wobble", ("e", "k"), roll_shapes, b.roll_wobble))


def _reading_shift(cal: Calibration, name: str) -> NDArray[np.float64]:
    """How every reading moves (K × 3) per radian of misalignment ``name`` at its point."""
    return np.asarray(_gravity_derivative(cal.points, name) @ cal.X[1:], dtype=float)


def bench_in_readings(cal: Calibration, b: TypeBInputs) -> dict[str, NDArray[np.float64]]:
    """The bench's stated errors that differ from point to point, as they enter the readings, by group
    ("tables": index and wobble in both shapes; "seating": the plate at each mounting), each K × 3 × m,
    one column per elementary input times its u, as their budget rows carry them (a reading moves by
    ∂g/∂misalignment · S). What is common to every point (the DMM's gain and offset, temperature at
    one setting) the fit absorbs; it leaves no residual to judge."""
    k = len(cal.installation)
    tables = []
    for _, names, ((rough, _), (smooth, share)), half in _table_inputs(cal, b):
        for basis, u in ((rough, half / SQRT3), (smooth, half / SQRT3 * np.sqrt(share))):
            if u > 0:
                tables += [_reading_shift(cal, name)[:, :, None] * basis[:, None, :] * u for name in names]
    seat = b.mount_repeatability / SQRT3 if b.mount_repeatability_sd is None else b.mount_repeatability_sd
    seating = []
    if seat > 0:
        member = _membership(cal.installation)
        seating = [_reading_shift(cal, name)[:, :, None] * member[:, None, :] * seat
                   for name in ("e", "f", "k")]
    return {name: np.concatenate(columns, axis=2) if columns else np.zeros((k, 3, 0))
            for name, columns in (("tables", tables), ("seating", seating))}


def sources(cal: Calibration, b: TypeBInputs) -> list[Source]:
    """Every row of the budget, in the order the certificate lists them."""
    X = cal.X
    rows: list[Source] = []
    # Type A: the fit's coefficient covariance (residual SE or lack-of-fit mean square, as the fit
    # chose), one component per sensor because each sensor has its own degrees of freedom.
    from_noise = cal.noise_type_a
    fit_parts = []
    for j in range(3):
        jac = np.zeros((4, 3, 4))
        jac[:, j, :] = _factor(cal.covariance[j])
        fit_parts.append(Component(jac.reshape(12, 4), np.zeros((3, 4)), 1.0, float(cal.dof[j]), "t",
                                   f"{'within-window' if from_noise else 'residual'} variance {'xyz'[j]}"))
    u_bias = float(np.sqrt(cal.covariance[:, 0, 0].max()))
    rows.append(Source("calibration fit (coefficients)", "A", "t", u_bias, "V (u of B, largest)",
                       tuple(fit_parts),
                       note="the instrument's noise (the pooled scatter inside the windows) through the "
                            "fit; the bench's errors are the Type B rows below" if from_noise else
                            "residual standard error, or the lack-of-fit mean square where replication "
                            "shows bias (Tripp & Tcheng §8)"))
    rows.append(new_reading(cal, b.output_unit))
    # The DMM: gain (% of reading) and offset (% of range), systematic over the run; per channel
    # independent, or one error common to the three channels where the station declares it so.
    offset = np.zeros((4, 3))
    offset[0] = 1.0
    for name, label, half, unit, effect in (("dmm_reading", "DMM accuracy, % of reading", b.dmm_reading,
                                             "relative", X),
                                            ("dmm_range", "DMM accuracy, % of range", b.dmm_range_v,
                                             b.output_unit,
                                             offset)):
        common = name in b.common
        jac = np.zeros((4, 3, 1 if common else 3))
        for j in range(3):  # channel j's error moves column j of X by effect[:, j] per unit
            jac[:, j, 0 if common else j] = effect[:, j]
        how = ("one error common to the three channels (one ADC scans them)" if common
               else "independent between the channels")
        rows.append(Source(label, "B", "rectangular", half / SQRT3, unit,
                           (_b(jac.reshape(12, -1), half / SQRT3),),
                           note="; ".join(n for n in (how, b.dmm_conditions) if n)))
    if b.dmm_noise_v > 0:  # its effect is in the residuals, hence in the fit's Type A already
        noise = np.zeros((4, 3, len(cal.installation), 3))
        for j in range(3):
            noise[:, j, :, j] = cal.projection
        rows.append(Source("DMM noise", "B", "normal", b.dmm_noise_v, b.output_unit,
                           (_b(noise.reshape(12, -1), b.dmm_noise_v, "normal"),), added=False,
                           note="included in the fit's Type A (the residuals contain it); not added again"))
    for label, names, shapes, half in _table_inputs(cal, b):
        (rough, _), (smooth, share) = shapes
        rows.append(Source(label, "B", "rectangular", half / SQRT3 / ARCSEC, "arcsec",
                           (_b(_grouped(cal, names, rough), half / SQRT3),
                            _b(_grouped(cal, names, smooth), half / SQRT3 * np.sqrt(share), "normal")),
                           note="a function of the table angle, repeated wherever the table returns to "
                                "it: one error per angle, and harmonics 1–3 of the angle, each with the "
                                "stated u (a rough and a smooth table)"))
    mounting = _grouped(cal, ("e", "f", "k"), _membership(cal.installation))
    if b.mount_repeatability_sd is None:
        rows.append(Source("mount repeatability", "B", "rectangular", b.mount_repeatability / SQRT3 / ARCSEC,
                           "arcsec", (_b(mounting, b.mount_repeatability / SQRT3),),
                           note="pitch, roll and yaw of the plate, one error per mounting; from the station "
                                "file (no mount was seated twice)"))
    else:
        sd, dof = b.mount_repeatability_sd, float(b.mount_repeatability_dof or np.inf)
        rows.append(Source("mount repeatability", "A", "normal", sd / ARCSEC, "arcsec",
                           (Component(mounting, np.zeros((3, mounting.shape[1])), sd, dof, "normal"),),
                           note="pitch, roll and yaw of the plate, one error per mounting; from the "
                                "replicates' scatter of the mount groups (Tripp & Tcheng, marginal drift "
                                "component), not the station file"))
    temp = np.zeros((4, 3, 1))
    temp[0, :, 0] = b.bias_tempco_v_per_k
    temp[1:, :, 0] = b.sensitivity_tempco_per_k * X[1:]
    rows.append(Source("temperature", "B", "rectangular", b.temperature_half_range_k / SQRT3, "K",
                       (_b(temp.reshape(12, 1), b.temperature_half_range_k / SQRT3),),
                       note="temperature coefficients × half the range observed during the run"))
    if b.device_misalignment:
        everything = np.zeros(len(cal.installation), dtype=int)
        # this run's device model, its coefficients' Type A from the windows' noise through its whole
        # gain: the noise the misalignments' estimates carry into X is in that row already
        inside = cal.noise_type_a and cal.reading_projection is not None and not b.device_misalignment_source
        rows.append(Source("device misalignment estimates", "B", "normal",
                           max(b.device_misalignment.values()) / ARCSEC, "arcsec", tuple(
                               _b(_grouped(cal, (name,), _membership(everything), linear=True), u, "normal")
                               for name, u in b.device_misalignment.items()), added=not inside,
                           note="the device model's estimates of a…k, re-estimated with the coefficients: "
                                "their noise is in the coefficients' Type A (through the model's gain); "
                                "shown, not added again" if inside else
                                ("not measured in this run: corrected for from "
                                 f"{b.device_misalignment_source} (the plan's device correction); each "
                                 "one's standard uncertainty as the plan carries it, through the fit's "
                                 "projection (their correlations are not carried)")
                           if b.device_misalignment_source else
                                "the device model's estimates of a…k, applied as corrections: each one's "
                                "standard uncertainty from the joint fit, through the fit's projection "
                                "(their correlations are not carried)"))
    rows.append(Source(LOCAL_GRAVITY, "B", "rectangular", LOCAL_GRAVITY_U, "g", (), added=True,
                       note=f"where the instrument is used |g| may differ from the calibration's by up "
                            f"to ±{LOCAL_GRAVITY_TOLERANCE:g} (latitude, height): the sphere estimator takes "
                            "|g| as unknown within that (a prior), so it follows the direction; its share "
                            "is what the prior leaves in pitch and roll"))
    return rows


def new_reading(cal: Calibration, unit: str) -> Source:
    """One new reading of the instrument in use: its own repeatability at the averaging used in
    service, s/√N with s the pooled within-window scatter of the calibration's samples and ν its
    degrees of freedom (GUM 4.2.3–4.2.4; `labcal.analysis.repeatability`), not the calibration's
    residual, which also holds the tables' per-angle errors: those exist only at the bench and reach
    every later reading through the coefficients, as the table rows. Readings that do not carry
    their windows' scatter fall back to the residual variance, as a certificate always stated it."""
    rep, samples = cal.repeatability, cal.in_use_samples_or_calibration
    if rep is None or samples is None:
        return Source("one new reading (instrument repeatability)", "A", "t",
                      float(np.sqrt(cal.reading_var.max())), unit, tuple(
                          Component(np.zeros((12, 1)), np.eye(3)[:, [j]] * np.sqrt(cal.reading_var[j]), 1.0,
                                    float(cal.dof[j]), "t", f"residual variance {'xyz'[j]}")
                          for j in range(3)),
                      note="the fit's residual standard error: the readings do not carry the scatter "
                           "inside their windows, so the instrument's own repeatability is not known "
                           "apart from the bench's errors")
    sd = np.sqrt(rep.reading_variance(samples))
    stated = "as stated for this certificate" if cal.in_use_samples else "as in the calibration's windows"
    return Source("one new reading (instrument repeatability)", "A", "t", float(sd.max()), unit, tuple(
        Component(np.zeros((12, 1)), np.eye(3)[:, [j]] * sd[j], 1.0, rep.dof, "t",
                  f"within-window variance {'xyz'[j]}") for j in range(3)),
        note=f"a reading in use averages {samples} samples ({stated}): s/√{samples}, s the pooled scatter "
             f"of the samples inside the calibration's {rep.windows} windows (largest channel "
             f"{rep.sample_sd.max():.3g} {unit} per sample, ν = {rep.dof:.0f}); the tables' errors "
             "enter through the coefficients only (their rows)")


# --- propagation to pitch and roll --------------------------------------------------------------
def regressors(pitch: NDArray[np.float64], roll: NDArray[np.float64]) -> NDArray[np.float64]:
    """f(z) = [1, g(z)] of the instrument in use, top-forward mount (n×4)."""
    g, _, _ = _gravity_and_derivatives(pitch, roll)
    return np.concatenate([np.ones((len(g), 1)), g], axis=1)


def estimator_weights(cal: Calibration, f: NDArray[np.float64]) -> NDArray[np.float64]:
    """W of the sphere estimator: 1 / (fᵀ C_j f + one reading's variance), per row and sensor, C_j the
    covariance the estimator is given (`labcal.analysis.attitude.output_variance`)."""
    weighting = cal.covariance if cal.estimator_covariance is None else cal.estimator_covariance
    calib = np.stack([np.einsum("ni,ij,nj->n", f, c, f) for c in weighting], axis=1)
    return np.asarray(1.0 / (calib + cal.reading_var), dtype=float)


def attitude_sensitivity(cal: Calibration, pitch: NDArray[np.float64], roll: NDArray[np.float64]
                         ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_]]:
    """How the sphere estimator `labcal attitude` uses moves its pitch and roll with the outputs
    (A, n×2×3), the variance its prior on local |g| brings (n×2), and where roll is defined (not at
    pitch ±90°, where only pitch is estimated): `labcal.analysis.attitude.sphere_sensitivity`."""
    g, dg_dp, dg_dr = _gravity_and_derivatives(pitch, roll)
    S = cal.X[1:]
    w = estimator_weights(cal, regressors(pitch, roll))
    defined = np.abs(np.cos(pitch)) > 1e-9
    A, known = sphere_sensitivity(np.stack([dg_dp @ S, dg_dr @ S], axis=1), w, defined, LOCAL_GRAVITY_U,
                                  g @ S)
    assert known is not None
    return A, known, defined


def _compressed(c: Component) -> NDArray[np.float64]:
    """[jac_x; jac_v] reduced to at most 15 columns with the same covariance (for the grid)."""
    J = np.concatenate([c.jac_x, c.jac_v]) * c.u
    if J.shape[1] <= J.shape[0]:
        return J
    return _factor(J @ J.T)


@dataclass(frozen=True)
class Combined:
    """Each source's standard uncertainty, the combined u_c, ν_eff, k and U = k·u_c of a set of
    outputs: pitch and roll at n attitudes (rad, n×2), or the coefficients (4×3)."""

    contributions: dict[str, NDArray[np.float64]]
    u_c: NDArray[np.float64]
    nu_eff: NDArray[np.float64]
    k: NDArray[np.float64]

    @property
    def U(self) -> NDArray[np.float64]:
        return np.asarray(self.k * self.u_c, dtype=float)


@dataclass(frozen=True)
class Propagated(Combined):
    pitch: NDArray[np.float64]
    roll: NDArray[np.float64]


def _combine(rows: list[Source], variance: Callable[[Component], NDArray[np.float64]],
             shape: tuple[int, ...]) -> Combined:
    """Sum the sources' variances (those not ``added`` are shown, not summed) and combine their
    degrees of freedom by Welch–Satterthwaite, component by component."""
    contributions = _contributions(rows, variance, shape)
    parts = [(variance(c), c.dof) for source in rows if source.added for c in source.components]
    total = sum((v for v, _ in parts), start=np.zeros(shape))
    u_c = np.sqrt(total)
    nu = welch_satterthwaite(u_c, parts)
    return Combined(contributions, u_c, nu, coverage_factor(nu, u_c))


def _contributions(rows: list[Source], variance: Callable[[Component], NDArray[np.float64]],
                   shape: tuple[int, ...]) -> dict[str, NDArray[np.float64]]:
    """Each source's standard uncertainty in the outputs (shown; the totals are not summed from it)."""
    return {s.name: np.sqrt(sum((variance(c) for c in s.components), start=np.zeros(shape))) for s in rows}


def covariance_parts(rows: list[Source]) -> tuple[CovariancePart, ...]:
    """The complete covariance of [vec(X); one new reading] as independent parts: every added Type B
    component with infinite degrees of freedom in one part (they add nothing to Welch–Satterthwaite),
    each finite-dof component in its own, components naming one estimate together. Correlations a
    component carries (across coefficients, across channels) stay in its matrix."""
    parts: dict[str, tuple[NDArray[np.float64], float, str]] = {}
    for source in rows:
        if not source.added:
            continue
        for i, c in enumerate(source.components):
            J = np.concatenate([c.jac_x, c.jac_v]) * c.u
            key = "Type B" if not np.isfinite(c.dof) else (c.estimate or f"{source.name} #{i}")
            label = "Type B (every input of known distribution)" if key == "Type B" else \
                (c.estimate or source.name)
            previous = parts.get(key, (np.zeros((N_ERRORS, N_ERRORS)), c.dof, label))[0]
            parts[key] = (previous + J @ J.T, c.dof, label)
    return tuple(CovariancePart(m, dof, label) for m, dof, label in parts.values())


def propagate(cal: Calibration, rows: list[Source], pitch: NDArray[np.float64], roll: NDArray[np.float64]
              ) -> Propagated:
    """Every source's contribution to pitch and roll at the attitudes (radians), and the totals from
    the complete covariance through `labcal.analysis.attitude.combined_uncertainty` — the one
    function every stated attitude U95 comes from."""
    pitch, roll = np.atleast_1d(pitch).astype(float), np.atleast_1d(roll).astype(float)
    A, from_gravity, _ = attitude_sensitivity(cal, pitch, roll)
    f = regressors(pitch, roll)

    def variance(c: Component) -> NDArray[np.float64]:
        J = _compressed(c)
        dv = -np.einsum("ni,ijm->njm", f, J[:12].reshape(4, 3, -1)) + J[12:][None]
        return np.asarray(np.sum(np.einsum("nab,nbm->nam", A, dv) ** 2, axis=2), dtype=float)
    with_gravity = any(s.name == LOCAL_GRAVITY and s.added for s in rows)  # `sources` always adds it
    total = combined_uncertainty(covariance_parts(rows), A, f, known=from_gravity if with_gravity else None)
    contributions = _contributions(rows, variance, (len(pitch), 2))
    if with_gravity:
        contributions[LOCAL_GRAVITY] = np.sqrt(from_gravity)  # through the estimator's prior, not the outputs
    return Propagated(contributions, total.u, total.nu_eff, total.k, pitch=pitch, roll=roll)


def coefficient_budget(rows: list[Source]) -> Combined:
    """Per coefficient of X (4×3): each source's standard uncertainty, combined u, ν_eff, k, U."""
    return _combine(rows, lambda c: (np.sum(c.jac_x**2, axis=1) * c.u**2).reshape(4, 3), (4, 3))

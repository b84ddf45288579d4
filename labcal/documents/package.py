"""What a certificate states about a sensor package of fewer than three sensors (Tripp & Tcheng
§6.1–6.5): each sensor's [b, S, Ω, A] (eq. 8), how pitch (and roll) are obtained in use, and the
uncertainty of the inferred angles over the attitudes where they can be used — computed from the
package's own fitted coefficients and their covariance, never copied from the paper.

- single-axis, used without roll (eq. 1): pitch by eq. 76, its standard deviation eq. 78 at roll 0;
- single-axis at a roll measured by the table or a roll sensor: pitch by eq. 79, its standard
  deviation eqs. 80–82, the measured roll's σ_R included;
- x–z at a measured roll: least squares in pitch, eqs. 96–98 (with eq. 80's roll term);
- x–y or x–z inferring pitch and roll together (eqs. 83–95): the usable range, the largest centred
  pitch × roll box where both inferred angles' U95 (eq. 90) stay within the stated limit
  (`labcal.analysis.packages.usable_box`), which keeps clear of the singular F_z (eqs. 86, 94).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np

from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import Fit
from labcal.analysis.packages import (
    inferred_covariance,
    output_sd,
    package_of,
    sd_pitch_at_roll,
    sensors_of,
    usable_box,
)
from labcal.config.settings import CertificateSettings
from labcal.documents.certificate import (
    AttitudeEnvelope,
    BudgetRow,
    BudgetTotal,
    CoefficientBudgetRecord,
    PackageSection,
    TrippSensor,
    UncertaintyBudget,
)
from labcal.documents.certificate_sections import BudgetInputs
from labcal.errors import LabcalError

if TYPE_CHECKING:
    from labcal.store.record import RunRecord

GRID_STEP_DEG = 1.0  # the usage envelope is judged on this grid, its ends included
DEFAULT_LIMIT_DEG = 0.1  # a two-axis package's U95 limit for its usable range, when none is stated


def output_sds(fit: Fit, alpha: np.ndarray, roll: np.ndarray) -> list[np.ndarray]:
    """σ_v of each sensor at (α, R) (rad): the calibration's part fᵀ·C·f and a new reading's
    variance (Tripp eqs. 52, 73), C the fit's covariance of (B, s)."""
    reading = np.sqrt(fit.new_measurement_variance())
    return [output_sd(fit.covariance(j)[:4, :4], reading[j], alpha, roll) for j in range(len(fit.sensors))]


def _grid(lo: float, hi: float) -> np.ndarray:
    n = max(int(np.ceil((hi - lo) / GRID_STEP_DEG - 1e-9)), 1)
    return np.radians(np.linspace(lo, hi, n + 1))


def package_section(fit: Fit, package: str, roll_in_use: str, roll_sd_deg: float | None,
                    usage_pitch_deg: tuple[float, float], usage_roll_deg: tuple[float, float],
                    u95_limit_deg: float | None = None) -> PackageSection:
    """The certificate's statement of a package of fewer than three sensors, from its fit. ``k``
    is the Student t factor of the fit's degrees of freedom (the coefficients' and the new reading's
    variance both come from its residuals)."""
    sensors = sensors_of(fit)
    k = float(t_quantile(0.975, int(np.min(fit.variance_dof))))
    described = {s.axis: TrippSensor(b=s.b, S=s.S, omega_deg=float(np.degrees(s.omega)),
                                     azimuth_deg=float(np.degrees(s.azimuth))) for s in sensors}
    common: dict[str, Any] = {"package": package, "sensors": list(fit.sensors), "coefficients": described,
              "roll_in_use": roll_in_use, "roll_sd_deg": roll_sd_deg, "k": k}
    if roll_in_use == "inferred":
        if len(sensors) != 2:
            raise LabcalError(f"a {package} package's certificate infers roll from two sensors only")
        limit = u95_limit_deg or DEFAULT_LIMIT_DEG
        span = np.radians(np.arange(-90.0, 90.0 + GRID_STEP_DEG / 2, GRID_STEP_DEG))
        a, r = np.meshgrid(span, span, indexing="ij")
        sigma_v = [float(np.max(s)) for s in output_sds(fit, a, r)]  # the worst over the sphere's half
        try:
            box = usable_box(sensors, sigma_v, np.radians(limit / k))
        except LabcalError:
            raise LabcalError(f"the {package} package cannot infer pitch and roll with U95 ≤ {limit:g}° even "
                              "at the level attitude: no usable range to certify (a larger "
                              "attitude_u95_max_deg, --tolerance-deg, gives one)") from None
        pitch, roll = float(np.degrees(box.pitch)), float(np.degrees(box.roll))
        return PackageSection(
            **common, equations=("Tripp & Tcheng eqs. 83-90" if package == "two-axis-xy" else
                                 "Tripp & Tcheng eqs. 91-95 with eq. 90"),
            u95_limit_deg=limit, usable_pitch_deg=(-pitch, pitch), usable_roll_deg=(-roll, roll),
            statement=(f"Pitch and roll are inferred together from the {' and '.join(fit.sensors)} sensors; "
                       f"both have U95 ≤ {limit:g}° (k = {k:.3g}) over pitch ±{pitch:g}° × roll ±{roll:g}°, "
                       "computed from this calibration's coefficients; beyond it the Jacobian F_z "
                       "approaches its singular attitudes (Tripp & Tcheng eqs. 86, 94)."))
    if roll_in_use == "none":
        usage_roll_deg = (0.0, 0.0)
    alpha, roll = np.meshgrid(_grid(*usage_pitch_deg), _grid(*usage_roll_deg), indexing="ij")
    sigma_roll = 0.0 if roll_in_use == "none" else np.radians(roll_sd_deg or 0.0)
    sigma = sd_pitch_at_roll(sensors, output_sds(fit, alpha, roll), alpha, roll, sigma_roll)
    worst = np.unravel_index(int(np.argmax(sigma)), sigma.shape)
    u95 = float(np.degrees(k * sigma[worst]))
    at = (round(float(np.degrees(alpha[worst])), 9), round(float(np.degrees(roll[worst])), 9))
    sd = f"σ_R = {roll_sd_deg or 0.0:g}°"
    how = {"none": "used without roll (roll 0)", "table": f"at the roll the table sets ({sd})",
           "sensor": f"at the roll a roll sensor measures ({sd})"}[roll_in_use]
    equations = "Tripp & Tcheng " + ("eqs. 76-78" if roll_in_use == "none" else
                                     "eqs. 79-82" if len(sensors) == 1 else "eqs. 96-98 with eq. 80")
    return PackageSection(
        **common, equations=equations, pitch_u95_deg=u95, pitch_u95_at_deg=at,
        usage_pitch_deg=usage_pitch_deg, usage_roll_deg=usage_roll_deg,
        statement=(f"Pitch is inferred from the {' and '.join(fit.sensors)} sensor(s) {how}; its U95 is "
                   "at most "
                   f"{u95:.3g}° (k = {k:.3g}) over pitch {usage_pitch_deg[0]:g}..{usage_pitch_deg[1]:g}° × "
                   f"roll {usage_roll_deg[0]:g}..{usage_roll_deg[1]:g}°, largest at pitch {at[0]:g}°, "
                   f"roll {at[1]:g}°."))


# --- the certificate's attitude envelope and budget of a package ----------------------------------
ARCSEC_PER_RAD = 180.0 / np.pi * 3600.0


def region(section: PackageSection) -> tuple[tuple[float, float], tuple[float, float]]:
    """The pitch and roll ranges (°) over which the section states its angles: the usage envelope
    where pitch is inferred at a known roll, the usable range where pitch and roll are inferred."""
    if section.usable_pitch_deg is not None and section.usable_roll_deg is not None:
        return section.usable_pitch_deg, section.usable_roll_deg
    assert section.usage_pitch_deg is not None and section.usage_roll_deg is not None
    return section.usage_pitch_deg, section.usage_roll_deg


@dataclass(frozen=True)
class RegionParts:
    """The standard deviations of the inferred angles (rad) on the section's grid, by source: the
    calibration's coefficients (fᵀCf), one new reading (σ₀), and the measured roll (σ_R). They add in
    quadrature: eqs. 81, 90 and 96 are linear in each variance."""

    alpha: np.ndarray
    roll: np.ndarray
    pitch: dict[str, np.ndarray]
    roll_sd: dict[str, np.ndarray] | None  # None: roll is not inferred
    calibration: np.ndarray  # (sensors, …): each sensor's calibration part of σ_v, in output units


def region_parts(fit: Fit, section: PackageSection) -> RegionParts:
    sensors = sensors_of(fit)
    pitch_range, roll_range = region(section)
    alpha, roll = np.meshgrid(_grid(*pitch_range), _grid(*roll_range), indexing="ij")
    reading = np.sqrt(fit.new_measurement_variance())
    calibration = [output_sd(fit.covariance(j)[:4, :4], 0.0, alpha, roll) for j in range(len(sensors))]
    new = [np.full(alpha.shape, reading[j]) for j in range(len(sensors))]
    if section.roll_in_use == "inferred":
        cov = {name: inferred_covariance(sensors, sv, alpha, roll)
               for name, sv in (("calibration", calibration), ("new reading", new))}
        return RegionParts(alpha, roll, {k: np.sqrt(c[..., 0, 0]) for k, c in cov.items()},
                           {k: np.sqrt(c[..., 1, 1]) for k, c in cov.items()}, np.array(calibration))
    zero = [np.zeros(alpha.shape)] * len(sensors)
    sigma_roll = 0.0 if section.roll_in_use == "none" else np.radians(section.roll_sd_deg or 0.0)
    pitch = {"calibration": sd_pitch_at_roll(sensors, calibration, alpha, roll),
             "new reading": sd_pitch_at_roll(sensors, new, alpha, roll)}
    if section.roll_in_use != "none":
        pitch["measured roll"] = sd_pitch_at_roll(sensors, zero, alpha, roll, sigma_roll)
    return RegionParts(alpha, roll, pitch, None, np.array(calibration))


def _total(parts: dict[str, np.ndarray]) -> np.ndarray:
    return np.sqrt(sum(p**2 for p in parts.values()))


def _argmax(values: np.ndarray) -> tuple[int, int]:
    """Where on the (pitch, roll) grid the values are largest."""
    i, j = np.unravel_index(int(np.argmax(values)), values.shape)
    return int(i), int(j)


def _at(parts: RegionParts, index: tuple[int, int]) -> tuple[float, float]:
    return (round(float(np.degrees(parts.alpha[index])), 9), round(float(np.degrees(parts.roll[index])), 9))


def package_envelope(fit: Fit, section: PackageSection, parts: RegionParts | None = None) -> AttitudeEnvelope:
    """The certificate's attitude envelope of a package: its inferred angles' U95 = k·σ over the
    region its section states (eqs. 78, 81, 90, 96), the largest, the RMS and where it is largest."""
    parts = parts or region_parts(fit, section)
    pitch_range, roll_range = region(section)
    u_pitch = np.degrees(section.k * _total(parts.pitch))
    i = _argmax(u_pitch)
    roll_fields: dict[str, Any] = {"roll_U95_max_deg": None, "roll_U95_rms_deg": None,
                                   "roll_U95_max_at_deg": None}
    if parts.roll_sd is not None:
        u_roll = np.degrees(section.k * _total(parts.roll_sd))
        j = _argmax(u_roll)
        roll_fields = {"roll_U95_max_deg": float(u_roll[j]),
                       "roll_U95_rms_deg": float(np.sqrt(np.mean(u_roll**2))),
                       "roll_U95_max_at_deg": _at(parts, j)}
    if section.roll_in_use == "inferred":
        how = ("pitch and roll inferred together from the package's two sensors (Tripp & Tcheng eq. 90, "
               "Newton-Raphson on eqs. 14-16) over the usable range the package section states")
    elif section.roll_in_use == "none":
        how = "pitch inferred without roll (Tripp & Tcheng eqs. 76-78); roll is not inferred by the package"
    else:
        how = (f"pitch inferred at the roll measured in use ({section.equations}); roll is not inferred by "
               "the package")
    return AttitudeEnvelope(
        method=f"{how}; σ from the coefficients' covariance and one new reading's variance (eqs. 52, 73)"
               + ("" if section.roll_in_use in ("none", "inferred") else
                  f" and the measured roll's σ_R = {section.roll_sd_deg or 0.0:g}°")
               + ", U95 = k·σ with k = t₀.₉₇₅ of the fit's degrees of freedom",
        usage_pitch_deg=pitch_range, usage_roll_deg=roll_range, grid_step_deg=GRID_STEP_DEG,
        grid_points=int(u_pitch.size), k=section.k, degrees_of_freedom=int(np.min(fit.variance_dof)),
        pitch_U95_max_deg=float(u_pitch[i]), pitch_U95_rms_deg=float(np.sqrt(np.mean(u_pitch**2))),
        pitch_U95_max_at_deg=_at(parts, i), roll_undefined_points=0, **roll_fields)


PACKAGE_BUDGET_METHOD = (
    "GUM (JCGM 100) budget of a sensor package (Tripp & Tcheng §6): each sensor's predicted output "
    "scatters by the calibration's part fᵀCf (C the fit's covariance of B and s) and one new reading's "
    "variance (eqs. 52, 73); these, and the standard deviation σ_R of a roll measured in use, propagate to "
    "the inferred angles through the package's own derivatives (eqs. 78, 81, 90, 96-98). Contributions are "
    "standard uncertainties u_i in arcsec where the angle's U95 is largest over the stated region, and "
    "their RMS over it; ν_eff is the fit's degrees of freedom (σ_R, a Type B input, has infinitely many, "
    "so this is conservative). The calibration device's stated angle errors (inputs) are not propagated "
    "into a package's coefficients: their scatter from point to point is in the fit's residuals.")


def package_budget(fit: Fit, section: PackageSection, inputs: dict[str, Any], unit: str = "V",
                   parts: RegionParts | None = None) -> UncertaintyBudget:
    """The certificate's budget of a package: rows for the calibration, a new reading and a measured
    roll, totals per inferred angle, and the coefficients' Type A U (the fit's standard errors)."""
    parts = parts or region_parts(fit, section)
    dof = int(np.min(fit.variance_dof))
    angles = {"pitch": parts.pitch} | ({} if parts.roll_sd is None else {"roll": parts.roll_sd})
    worst = {a: _argmax(_total(p)) for a, p in angles.items()}
    reading = np.sqrt(fit.new_measurement_variance())
    described: dict[str, tuple[str, Literal["A", "B"], str, float, str, int | None]] = {
        "calibration": ("calibration coefficients (fᵀCf of each sensor)", "A", "t (normal)",
                        float(np.max(parts.calibration[:, worst["pitch"][0], worst["pitch"][1]])), unit, dof),
        "new reading": ("one new reading of each sensor", "A", "t (normal)", float(np.max(reading)), unit,
                        dof),
        "measured roll": ("roll measured in use (σ_R)", "B",
                          "rectangular (the table's stated index error)" if section.roll_in_use == "table"
                          else "normal (the roll sensor's stated σ_R)",
                          float((section.roll_sd_deg or 0.0) * 3600.0), "arcsec", None),
    }
    rows = []
    for name in parts.pitch:
        source, kind, distribution, sd, row_unit, row_dof = described[name]
        p = parts.pitch[name] * ARCSEC_PER_RAD
        r = None if parts.roll_sd is None else parts.roll_sd[name] * ARCSEC_PER_RAD
        sensitivity = None
        if name == "measured roll" and sd > 0:
            sensitivity = float(p[worst["pitch"]] / sd)
        rows.append(BudgetRow(
            source=source, type=kind, distribution=distribution, standard_uncertainty=sd, unit=row_unit,
            sensitivity_pitch=sensitivity, sensitivity_roll=None,
            pitch_worst_arcsec=float(p[worst["pitch"]]), pitch_rms_arcsec=float(np.sqrt(np.mean(p**2))),
            roll_worst_arcsec=None if r is None else float(r[worst["roll"]]),
            roll_rms_arcsec=None if r is None else float(np.sqrt(np.mean(r**2))),
            degrees_of_freedom=row_dof, added=True,
            note="" if name != "calibration" else
            "standard uncertainty: the largest sensor's at the worst point"))
    totals = []
    for angle, by_source in angles.items():
        u = _total(by_source) * ARCSEC_PER_RAD
        totals.append(BudgetTotal(angle="pitch" if angle == "pitch" else "roll",
                                  worst_at_deg=_at(parts, worst[angle]),
                                  u_c_arcsec=float(u[worst[angle]]), nu_eff=float(dof), k=section.k,
                                  U95_arcsec=float(section.k * u[worst[angle]]),
                                  U95_rms_arcsec=float(section.k * np.sqrt(np.mean(u**2)))))
    se = fit.stderr[:4]
    k_coef = np.array([float(t_quantile(0.975, d)) for d in fit.variance_dof])
    parts_said = "; ".join(f"{t.angle}: U95 = {t.U95_arcsec:.3g}″ (k = {t.k:.2f}, ν_eff = {dof}) at pitch "
                           f"{t.worst_at_deg[0]:g}°, roll {t.worst_at_deg[1]:g}°" for t in totals)
    return UncertaintyBudget(
        method=PACKAGE_BUDGET_METHOD, inputs=BudgetInputs.model_validate(inputs), rows=rows, totals=totals,
        coefficients=CoefficientBudgetRecord(
            u_c=se.tolist(), nu_eff=[[float(d) for d in fit.variance_dof]] * 4,
            k=[k_coef.tolist()] * 4, U=(se * k_coef[None, :]).tolist(),
            contributions={"Type A (the fit)": se.tolist()}),
        statement=f"Combined standard uncertainty of every added source; {parts_said}.")


def record_section(record: RunRecord, fit: Fit, settings: CertificateSettings) -> PackageSection:
    """A package run's section (`package_section` of its fit, how roll is obtained as the run
    recorded it), with the calibration's temperature range and the model's reference temperature."""
    use = record.meta.package
    package = package_of(fit.sensors)
    roll_in_use = (use.roll_in_use if use else None) or ("inferred" if package == "two-axis-xy" else "table")
    section = package_section(fit, package, roll_in_use, use.roll_sd_deg if use else None,
                              settings.usage_pitch_deg, settings.usage_roll_deg,
                              settings.attitude_u95_max_deg)
    temps = record.readings.temp_c
    if temps is not None:
        low, high = float(np.min(temps)), float(np.max(temps))
        section = section.model_copy(update={
            "temperature_c": (low, high), "t_ref_c": fit.model.t_ref,
            "statement": f"{section.statement} Calibrated at {low:.2f}..{high:.2f} °C; the model's reference "
                         f"temperature is {fit.model.t_ref:.2f} °C."})
    return section


def package_documents(record: RunRecord, fit: Fit, settings: CertificateSettings, inputs: dict[str, Any]
                      ) -> tuple[PackageSection, AttitudeEnvelope, UncertaintyBudget]:
    """What a package's certificate states that a three-axis one states otherwise: its section, its
    attitude envelope and its budget, all over the one region the section states."""
    section = record_section(record, fit, settings)
    parts = region_parts(fit, section)
    return (section, package_envelope(fit, section, parts),
            package_budget(fit, section, inputs, record.readings.units, parts))

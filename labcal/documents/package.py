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

import json
from typing import TYPE_CHECKING, Any

import numpy as np

from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import Fit
from labcal.analysis.packages import (
    Sensor,
    from_linear,
    output_sd,
    sd_pitch_at_roll,
    usable_box,
)
from labcal.config.files import write_atomic
from labcal.config.settings import CertificateSettings
from labcal.documents.certificate import PackageSection, TrippSensor
from labcal.errors import LabcalError

if TYPE_CHECKING:
    from labcal.run.record import RunRecord

STATEMENT = "package.json"  # in the run directory: a package's certificate statement

GRID_STEP_DEG = 1.0  # the usage envelope is judged on this grid, its ends included
DEFAULT_LIMIT_DEG = 0.1  # a two-axis package's U95 limit for its usable range, when none is stated


def sensors_of(fit: Fit) -> list[Sensor]:
    """Tripp's [b, S, Ω, A] of every sensor the fit has (eq. 8), from its linear columns."""
    return [from_linear(fit.coefficients[0, j], fit.coefficients[1:, j], axis)
            for j, axis in enumerate(fit.sensors)]


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
        box = usable_box(sensors, sigma_v, np.radians(limit / k))
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


def package_of(sensors: tuple[str, ...]) -> str:
    """The package whose sensors these are."""
    return {("x",): "single-axis", ("x", "y"): "two-axis-xy", ("x", "z"): "two-axis-xz"}[sensors]


def write_package_statement(record: RunRecord, settings: CertificateSettings | None = None) -> PackageSection:
    """A finished package run's statement (`package_section` of its fit, how roll is obtained as
    the run recorded it), written as ``package.json`` in its run directory."""
    settings = settings or CertificateSettings()
    fit = record.fit
    if fit is None:
        raise LabcalError(f"{record.directory}: the run has no fit")
    use = record.meta.package or {}
    package = package_of(fit.sensors)
    roll_in_use = use.get("roll_in_use") or ("inferred" if package == "two-axis-xy" else "table")
    section = package_section(fit, package, roll_in_use, use.get("roll_sd_deg"), settings.usage_pitch_deg,
                              settings.usage_roll_deg, settings.attitude_u95_max_deg)
    temps = record.readings.temp_c
    if temps is not None:
        low, high = float(np.min(temps)), float(np.max(temps))
        section = section.model_copy(update={
            "temperature_c": (low, high), "t_ref_c": fit.model.t_ref,
            "statement": f"{section.statement} Calibrated at {low:.2f}..{high:.2f} °C; the model's reference "
                         f"temperature is {fit.model.t_ref:.2f} °C."})
    write_atomic(record.directory / STATEMENT,
                 (json.dumps(section.model_dump(mode="json"), indent=2, ensure_ascii=False) + "\n").encode())
    return section

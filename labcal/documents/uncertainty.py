"""The certificate's uncertainty budget: the bench's Type B inputs read from its station file, the
budget of `labcal.analysis.budget` evaluated over the usage envelope, and, when asked, its Monte
Carlo check (`labcal.analysis.montecarlo`), as the `UncertaintyBudget` section a certificate holds.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.budget import (
    Calibration,
    Propagated,
    Source,
    TypeBInputs,
    calibration_of,
    calibration_of_device,
    coefficient_budget,
    covariance_parts,
    propagate,
    sources,
)
from labcal.analysis.design import grid
from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.fit import Fit
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES
from labcal.analysis.lack_of_fit import LackOfFit, fit_lack_of_fit
from labcal.analysis.montecarlo import monte_carlo
from labcal.analysis.readings import Readings
from labcal.analysis.remounting import mount_scatter
from labcal.config.plans import plan_correction
from labcal.config.settings import CertificateSettings
from labcal.config.snapshot import StationFileSnapshot
from labcal.config.station import CertificateSection, load_certificate_section
from labcal.documents.certificate import (
    BenchCheck,
    BudgetRow,
    BudgetTotal,
    CoefficientBudgetRecord,
    CovariancePartRecord,
    FitCheck,
    InUseReading,
    MonteCarloCheck,
    UncertaintyBudget,
)
from labcal.documents.certificate_sections import BudgetInputs
from labcal.documents.simulated import with_simulator_inputs
from labcal.store.record import RunRecord

ANGLES: tuple[Literal["pitch", "roll"], ...] = ("pitch", "roll")
AGREEMENT = 0.05  # linear and Monte Carlo U95 agree when within 5 % (the criterion)
METHOD = ("GUM (JCGM 100) budget: each source's elementary inputs propagate through the least-squares fit "
          "to the coefficients (X moves by (FᵀF)⁻¹Fᵀ·δV for a bench error δ) and through the sphere "
          "estimator's sensitivity A = (F W Fᵀ)⁻¹F W to pitch and roll; errors that repeat at a table angle "
          "or for a whole mounting are one input each, so what the plan cancels shows as zero. ν_eff by "
          "Welch–Satterthwaite, k = t₀.₉₇₅(ν_eff). Contributions are standard uncertainties u_i in arcsec at "
          "the envelope point where U95 of the angle is largest, and their RMS over the envelope.")


def bench_section(record: RunRecord, station: str | Path | None) -> CertificateSection:
    """What the certificate takes from a station file: the one given, else the station the run was
    journaled with; a dry run's Type B inputs are the simulator's (`labcal.documents.simulated`)."""
    if station is not None:
        return load_certificate_section(station)
    section = CertificateSection()
    if isinstance(record.station, StationFileSnapshot):
        section = record.station.section(f"{record.directory}: the run's station")
    # a dry run: the simulator's own error sources at their simulated sizes
    return with_simulator_inputs(section, record.station, record.meta.settings)


def device_misalignment_u(device: DeviceFit | None) -> dict[str, float]:
    """The standard uncertainty (rad) of each misalignment a…k the ``device`` model estimated (its
    noise share), the budget's device-misalignment row; empty without a device model."""
    if device is None:
        return {}
    noise_u = np.sqrt(np.diag(device.noise_covariance)[:len(MISALIGNMENT_NAMES)])
    return {name: float(u) for name, u in zip(MISALIGNMENT_NAMES, noise_u, strict=True)}


def section_type_b(section: CertificateSection, unit: str, temperature_half_range_k: float) -> TypeBInputs:
    """The budget's Type B inputs in SI from what a bench states of itself (its station file's
    [uncertainty] and DMM, or the simulator's own, `labcal.documents.simulated`), for outputs in
    ``unit``: the one mapping, for a finished run's certificate (`type_b_inputs`) and for a plan's
    prediction before any run (`labcal.app.planning`)."""
    u = section.uncertainty
    conditions = (f"{section.dmm.range_v:g} V range at {section.dmm.nplc:g} PLC"
                  + (" (the 34970A's published accuracy assumes ≥ 1 PLC: add its reading-speed error to "
                     "dmm_range)" if section.dmm.nplc < 1 else ""))
    # The DMM's absolute terms are volts: stated in the readings' unit where they are volts or millivolts;
    # an instrument whose output is not a voltage (counts, m/s²) is not read through the DMM's range, so
    # only its relative term (% of reading, for whatever reads it) is kept, and the budget says so.
    volts = {"V": 1.0, "mV": 1e3}.get(unit)
    if volts is None:
        conditions = (f"the outputs are in {unit}, not volts: the DMM's range and noise terms do not apply; "
                      "the reader's own accuracy is the % of reading stated for it")
    return TypeBInputs(
        dmm_reading=u.dmm_reading, dmm_range_v=u.dmm_range * section.dmm.range_v * (volts or 0.0),
        dmm_noise_v=u.dmm_noise * (volts or 0.0), dmm_conditions=conditions, output_unit=unit,
        pitch_index=u.pitch_index, pitch_wobble=u.pitch_wobble, roll_index=u.roll_index,
        roll_wobble=u.roll_wobble, mount_repeatability=u.mount_repeatability,
        common=section.dmm.common_inputs(u.common), temperature_half_range_k=temperature_half_range_k,
        bias_tempco_v_per_k=u.bias_tempco, sensitivity_tempco_per_k=u.sensitivity_tempco)


def type_b_inputs(section: CertificateSection, record: RunRecord, device: DeviceFit | None = None
                  ) -> TypeBInputs:
    """The bench's inputs in SI (`section_type_b`); the temperature half-range is the run's own (none
    without a channel); the device misalignments' standard uncertainties where the ``device`` model
    estimated them, or where the run's plan corrected for them (its ``[device_correction]``'s u)."""
    device_misalignment = device_misalignment_u(device)
    correction = None if device is not None else \
        plan_correction(record.plan_text, f"{record.directory}: the run's plan")
    if correction is not None:  # the plan's misalignments, corrected for: their u as it carries it
        device_misalignment = correction.u_rad()
    t = record.readings.temp_c
    inputs = section_type_b(section, record.readings.units, 0.0 if t is None else float(np.ptp(t)) / 2)
    return replace(inputs, device_misalignment=device_misalignment,
                   device_misalignment_source="" if correction is None else correction.describe())


def envelope(settings: CertificateSettings) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The usage envelope's grid, pitch and roll in radians."""
    step = settings.grid_step_deg
    points = np.radians(np.array(grid(*settings.usage_pitch_deg, step, *settings.usage_roll_deg, step)))
    return points[:, 0], points[:, 1]


def _degrees(p: Propagated, i: int) -> tuple[float, float]:
    """Grid attitude i in degrees, as the grid was given (60, not 59.99999999999999)."""
    return round(float(np.degrees(p.pitch[i])), 9), round(float(np.degrees(p.roll[i])), 9)


def _arcsec(x: float) -> float | None:
    return float(x) / ARCSEC if np.isfinite(x) else None


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _worst(p: Propagated, column: int) -> int | None:
    values = p.U[:, column]
    return None if not np.any(np.isfinite(values)) else int(np.nanargmax(values))


def _rms(values: NDArray[np.float64]) -> float:
    return float(np.sqrt(np.nanmean(values**2))) if np.any(np.isfinite(values)) else float("nan")


def _rows(rows: list[Source], p: Propagated) -> list[BudgetRow]:
    i_p, i_r = _worst(p, 0), _worst(p, 1)
    out = []
    for s in rows:
        c = p.contributions[s.name]
        at_p = c[i_p, 0] if i_p is not None else float("nan")
        at_r = c[i_r, 1] if i_r is not None else float("nan")
        out.append(BudgetRow(
            source=s.name, type=s.type, distribution=s.distribution, standard_uncertainty=s.u, unit=s.unit,
            sensitivity_pitch=_arcsec(at_p / s.u) if s.u > 0 else None,
            sensitivity_roll=_arcsec(at_r / s.u) if s.u > 0 else None,
            pitch_worst_arcsec=float(at_p) / ARCSEC, pitch_rms_arcsec=_rms(c[:, 0]) / ARCSEC,
            roll_worst_arcsec=_arcsec(at_r), roll_rms_arcsec=_arcsec(_rms(c[:, 1])),
            degrees_of_freedom=_finite(s.dof), added=s.added, note=s.note))
    return out


def _totals(p: Propagated) -> list[BudgetTotal]:
    totals = []
    for column, angle in enumerate(ANGLES):
        i = _worst(p, column)
        if i is None:
            continue
        totals.append(BudgetTotal(
            angle=angle, worst_at_deg=_degrees(p, i),
            u_c_arcsec=float(p.u_c[i, column]) / ARCSEC, nu_eff=_finite(p.nu_eff[i, column]),
            k=float(p.k[i, column]), U95_arcsec=float(p.U[i, column]) / ARCSEC,
            U95_rms_arcsec=_rms(p.U[:, column]) / ARCSEC))
    return totals


def _monte_carlo(cal: Calibration, rows: list[Source], p: Propagated, trials: int, seed: int
                 ) -> list[MonteCarloCheck]:
    checks = []
    for column, angle in enumerate(ANGLES):
        i = _worst(p, column)
        if i is None:
            continue
        mc = monte_carlo(cal, rows, float(p.pitch[i]), float(p.roll[i]), trials, seed)
        linear, sampled = float(p.U[i, column]), mc.half_width[column]
        checks.append(MonteCarloCheck(
            trials=trials, seed=seed, angle=angle,
            at_deg=_degrees(p, i),
            linear_U95_arcsec=linear / ARCSEC, monte_carlo_U95_arcsec=sampled / ARCSEC,
            agree_within_5_percent=bool(abs(sampled / linear - 1) <= AGREEMENT) if linear > 0 else True))
    return checks


def _statement(totals: list[BudgetTotal], checks: list[MonteCarloCheck] | None) -> str:
    parts = [f"{t.angle}: U95 = {t.U95_arcsec:.3g}″ (k = {t.k:.2f}, ν_eff = "
             f"{'∞' if t.nu_eff is None else f'{t.nu_eff:.0f}'}) at pitch {t.worst_at_deg[0]:g}°, roll "
             f"{t.worst_at_deg[1]:g}°" for t in totals]
    text = "Combined standard uncertainty of every added source; " + "; ".join(parts) + "."
    for c in checks or []:
        if c.agree_within_5_percent:
            text += (f" Monte Carlo ({c.trials} trials) confirms the {c.angle} U95: "
                     f"{c.monte_carlo_U95_arcsec:.3g}″ against {c.linear_U95_arcsec:.3g}″ linear.")
        else:
            text += (f" The {c.angle} U95 stated is the Monte Carlo value {c.monte_carlo_U95_arcsec:.3g}″ "
                     f"({c.trials} trials), not the linear {c.linear_U95_arcsec:.3g}″: they differ by more "
                     f"than {AGREEMENT:.0%} because the output's distribution is not the scaled t the linear "
                     "method assumes (Type A inputs with few degrees of freedom, dominant rectangular "
                     "inputs, or an estimator that is not linear over the spread).")
    return text


@dataclass(frozen=True)
class BudgetView:
    """The budget's view of a fit, its rows, the inputs they were made from, and the lack-of-fit and
    drift tests of the fit against the noise and the stated bench errors (None: not testable)."""

    cal: Calibration
    rows: list[Source]
    inputs: TypeBInputs
    check: LackOfFit | None


def budget_view(readings: Readings, fit: Fit, inputs: TypeBInputs, device: DeviceFit | None = None,
                in_use_samples: int | None = None) -> BudgetView:
    """The budget of a fit of ``readings`` (or of its ``device`` model), tested first. Its Type A rows
    are the instrument's noise (the windows' scatter) where the residuals are what that noise and the
    station's stated errors explain; where the lack-of-fit test finds more, something the model or the
    statement misses is in the residuals, and the budget takes them as before — the fit's residual for
    the coefficients' Type A and for the new reading (Tripp & Tcheng §8 take the lack-of-fit mean
    square where replication shows bias, for the same reason) — and the certificate says so."""
    cal, rows, used = _budget_rows(readings, fit, inputs, device, in_use_samples)
    check = fit_lack_of_fit(cal, used, readings, fit, device)
    if check is not None and check.significant:
        cal, rows, used = _budget_rows(replace(readings, window_sd=None, window_n=None), fit, inputs, device,
                                       in_use_samples)
    return BudgetView(cal, rows, used, check)


def _budget_rows(readings: Readings, fit: Fit, inputs: TypeBInputs, device: DeviceFit | None = None,
                 in_use_samples: int | None = None) -> tuple[Calibration, list[Source], TypeBInputs]:
    """The budget's view of a fit of ``readings`` (or of its ``device`` model), its rows and the inputs
    they were made from: the tables' index and wobble the device model was fitted with, and the mount
    scatter the replicates show, over the station file's. ``in_use_samples``: the samples a reading
    in use averages (None: the calibration's window length)."""
    cal = calibration_of(fit, readings, in_use_samples) if device is None else \
        calibration_of_device(device, readings, in_use_samples)
    if device is not None and device.angle_errors is not None:
        # the tables' index and wobble the device model was fitted with are the budget's table rows
        a = device.angle_errors
        inputs = replace(inputs, pitch_index=a.pitch_index, pitch_wobble=a.pitch_wobble,
                         roll_index=a.roll_index, roll_wobble=a.roll_wobble)
    scatter = mount_scatter(readings, cal.X)
    if scatter is not None:  # the replicates say how the seating scatters: they win over the station file
        inputs = replace(inputs, mount_repeatability_sd=scatter.sd_rad, mount_repeatability_dof=scatter.dof)
    return cal, sources(cal, inputs), inputs


def inputs_record(inputs: TypeBInputs) -> dict:
    """The bench's Type B inputs as a certificate's budget records them."""
    return {k: (dict(v) if isinstance(v, dict) else v) for k, v in vars(inputs).items()
            if not (k == "output_unit" and v == "V")  # volts: as certificates always said it
            and not (k == "device_misalignment_source" and not v)}  # a device model's own: as before


def budget(record: RunRecord, fit: Fit, inputs: TypeBInputs, settings: CertificateSettings,
           trials: int = 0, seed: int = 0, device: DeviceFit | None = None) -> UncertaintyBudget:
    """The certificate's budget section for a run's fit, or for its ``device`` model where the
    certificate is built on it; ``trials`` > 0 adds the Monte Carlo check."""
    view = budget_view(record.readings, fit, inputs, device, settings.in_use_samples)
    cal, rows, inputs = view.cal, view.rows, view.inputs
    pitch, roll = envelope(settings)
    p = propagate(cal, rows, pitch, roll)
    coef = coefficient_budget(rows)
    totals = _totals(p)
    checks = _monte_carlo(cal, rows, p, trials, seed) if trials > 0 else None
    return UncertaintyBudget(
        in_use=in_use_reading(cal, inputs.output_unit), fit_check=fit_check(view.check),
        method=METHOD, inputs=BudgetInputs.model_validate(inputs_record(inputs)), rows=_rows(rows, p),
        totals=totals,
        coefficients=CoefficientBudgetRecord(
            u_c=coef.u_c.tolist(), nu_eff=[[_finite(x) for x in row] for row in coef.nu_eff],
            k=coef.k.tolist(), U=coef.U.tolist(),
            contributions={name: c.tolist() for name, c in coef.contributions.items()}),
        monte_carlo=checks, statement=_statement(totals, checks),
        covariance=[CovariancePartRecord(label=part.label, degrees_of_freedom=_finite(part.dof),
                                         matrix=part.matrix.tolist()) for part in covariance_parts(rows)])


def fit_check(check: LackOfFit | None) -> FitCheck | None:
    """The lack-of-fit and drift tests as the certificate states them."""
    if check is None:
        return None
    nu1, nu2 = check.dof
    groups = "; ".join(f"{b.name} {b.ratio:.2f}× their stated variance (p = {b.p_value:.2g})"
                       for b in check.bench)
    tested = (f"Lack-of-fit test of the residuals against the instrument's noise (the scatter inside the "
              f"windows) and the station's stated bench errors: Q/ν = {check.statistic:.3g} (ν = {nu1:.0f}, "
              f"{nu2:.0f}), p = {check.p_value:.2g}" + (f"; {groups}" if groups else "") +
              f" (each at {check.alpha:g}/{check.tests}). ")
    if check.significant:
        verdict = ("LACK OF FIT: the residuals hold more than the noise and the stated errors explain — an "
                   "effect the model or the station's statement leaves out (a table worse than stated, an "
                   "unstated seating scatter, a drift, a nonlinearity). The budget takes the fit's residual "
                   "for the coefficients and for a new reading instead of the noise; find the cause before "
                   "relying on these coefficients.")
    else:
        verdict = "No lack of fit: the model and the stated errors explain the residuals."
    drift = (f" Drift test (a trend of each output over the run, χ² with {check.drift_dof} degrees of "
             f"freedom): {check.drift_statistic:.3g}, p = {check.drift_p_value:.2g}: "
             + ("DRIFT — the outputs moved during the run." if check.drift_significant else "no drift."))
    return FitCheck(
        statistic=check.statistic, degrees_of_freedom=(nu1, nu2), p_value=check.p_value,
        bench={b.name: BenchCheck(ratio=b.ratio, p_value=b.p_value) for b in check.bench},
        alpha=check.alpha, lack_of_fit=check.significant, drift_statistic=check.drift_statistic,
        drift_degrees_of_freedom=check.drift_dof, drift_p_value=check.drift_p_value,
        drift=check.drift_significant, statement=tested + verdict + drift)


def in_use_reading(cal: Calibration, unit: str) -> InUseReading | None:
    """The averaging in use the new-reading row assumes, in words for the certificate (None: the row is
    the fit's residual)."""
    rep, samples = cal.repeatability, cal.in_use_samples_or_calibration
    if rep is None or samples is None:
        return None
    how = ("as stated for this certificate" if cal.in_use_samples
           else "as in this calibration's windows")
    return InUseReading(
        samples=samples, stated=cal.in_use_samples is not None, sample_sd=rep.sample_sd.tolist(),
        degrees_of_freedom=rep.dof, windows=rep.windows,
        statement=(f"The uncertainty of pitch and roll applies to a reading of the instrument in use that is "
                   f"the mean of {samples} samples of each output ({how}). A reading of fewer samples "
                   f"scatters more: its own term grows as 1/√N from {max(rep.sample_sd):.3g} {unit} per "
                   f"sample (the pooled scatter inside the calibration's {rep.windows} windows, "
                   f"ν = {rep.dof:.0f})."))


def stated_U95_arcsec(b: UncertaintyBudget, angle: str) -> float | None:
    """The U95 the certificate states for an angle: the Monte Carlo value where the two disagree."""
    total = next((t for t in b.totals if t.angle == angle), None)
    if total is None:
        return None
    check = next((c for c in b.monte_carlo or [] if c.angle == angle), None)
    if check is not None and not check.agree_within_5_percent:
        return check.monte_carlo_U95_arcsec
    return total.U95_arcsec

"""Issuing a certificate from a finished run: the fit's expanded uncertainties, the plan audit,
the attitude uncertainty over the usage envelope, the statement of conformity, and the sealed
document (`labcal.documents.certificate` says what a certificate is and how it is read back).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from labcal import __version__
from labcal.analysis.attitude import (
    LOCAL_GRAVITY_TOLERANCE,
    LOCAL_GRAVITY_U,
    Attitude,
    Calibration,
    calibration_from_json,
    closed_form,
    sphere_least_squares,
)
from labcal.analysis.budget import TypeBInputs
from labcal.analysis.design import LEAK_ZERO, audit, audit_summary, figure_of_merit, grid
from labcal.analysis.device_fit import DeviceFit
from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import SENSORS, Fit
from labcal.analysis.kinematics import gravity
from labcal.analysis.models import BASE_NAMES
from labcal.config.json_values import json_safe
from labcal.config.lab import certificate_settings
from labcal.config.plans import plan_correction
from labcal.config.readings_csv import coefficient_units
from labcal.config.run_metadata import Checklist
from labcal.config.settings import CertificateSettings
from labcal.config.station import CertificateSection, load_certificate_settings
from labcal.config.uncertainty import overdue_standards
from labcal.devices.winding import MOVE_EVENT
from labcal.documents.administration import ItemGiven, administration
from labcal.documents.certificate import (
    COVERAGE,
    SCHEMA,
    Administration,
    AttitudeEnvelope,
    Certificate,
    Check,
    ClosedFormEnvelope,
    Conformity,
    DeviceSection,
    Environment,
    Expanded,
    FitSection,
    JournalEvent,
    Leak,
    PlanAudit,
    RunStory,
    UncertaintyBudget,
    seal,
)
from labcal.documents.overrides import checklist_overrides, run_overrides
from labcal.documents.package import package_documents
from labcal.documents.simulated import NOTICE as SIMULATED_NOTICE
from labcal.documents.uncertainty import budget, inputs_record, stated_U95_arcsec
from labcal.errors import LabcalError
from labcal.store.record import RunRecord

SIMULATED_SERIAL = "SIMULATED"  # a dry run's instrument is the simulator's, whatever the seed


def load_settings(station_path: str | Path | None, **overrides: object) -> CertificateSettings:
    """The lab file's certificate defaults, the ``[certificate]`` table of a station file over them,
    then the command line's non-None ``overrides``; every mistake is one line naming the file and
    the field."""
    if station_path is None:
        return certificate_settings(None, "lab file").overridden("command line", **overrides)
    station = load_certificate_settings(station_path)
    return certificate_settings(station, str(station_path)).overridden(str(station_path), **overrides)


# --- attitude uncertainty over the usage envelope ---------------------------------------------------
@dataclass(frozen=True)
class EnvelopeGrid:
    """U95 of inferred pitch and roll (°) on the pitch × roll grid of the usage envelope."""

    pitch_deg: NDArray  # (n_p,)
    roll_deg: NDArray  # (n_r,)
    u95_pitch_deg: NDArray  # (n_p, n_r)
    u95_roll_deg: NDArray  # (n_p, n_r), NaN where roll is undefined
    k_pitch: NDArray  # (n_p, n_r): k = t₀.₉₇₅(ν_eff) of each attitude
    dof: int


def in_use(cal: Calibration, volts: NDArray) -> Attitude:
    """The sphere estimator as `labcal attitude` runs it: |g| known to ±LOCAL_GRAVITY_TOLERANCE."""
    return sphere_least_squares(cal, volts, LOCAL_GRAVITY_U)


def envelope_grid(cal: Calibration, settings: CertificateSettings, estimator=in_use) -> EnvelopeGrid:
    """Weighted least squares on the sphere (Tripp eqs. 99–104, with local |g| as `labcal attitude`
    takes it; or another ``estimator``) at every grid attitude, top-forward mount, for one new
    reading: the uncertainty a user of the instrument gets, in degrees."""
    step = settings.grid_step_deg
    points = np.array(grid(*settings.usage_pitch_deg, step, *settings.usage_roll_deg, step))
    pitch, roll = np.unique(points[:, 0]), np.unique(points[:, 1])
    g = gravity(np.radians(points[:, 0]), np.radians(points[:, 1]), 0.0, 0.0)
    att = estimator(cal, cal.X[0] + g @ cal.X[1:])
    shape = (len(pitch), len(roll))
    return EnvelopeGrid(pitch, roll, np.degrees(att.U_pitch).reshape(shape),
                        np.degrees(att.U_roll).reshape(shape), att.k_pitch.reshape(shape), cal.dof)


def _summary(grid_: EnvelopeGrid, values: NDArray
             ) -> tuple[float | None, float | None, tuple[float, float] | None]:
    if not np.any(np.isfinite(values)):
        return None, None, None
    i, j = np.unravel_index(np.nanargmax(values), values.shape)
    rms = float(np.sqrt(np.nanmean(values**2)))
    return float(values[i, j]), rms, (float(grid_.pitch_deg[i]), float(grid_.roll_deg[j]))


def attitude_envelope(cal: Calibration, settings: CertificateSettings) -> AttitudeEnvelope:
    env = envelope_grid(cal, settings)
    p_max, p_rms, p_at = _summary(env, env.u95_pitch_deg)
    if p_max is None or p_rms is None or p_at is None:  # pitch exists everywhere; roll may not
        low, high = settings.usage_pitch_deg
        raise LabcalError(f"the pitch uncertainty is not finite anywhere in the usage envelope (pitch "
                          f"{low:g}..{high:g}°); check the usage envelope and the calibration's "
                          "uncertainties")
    r_max, r_rms, r_at = _summary(env, env.u95_roll_deg)
    i, j = int(np.searchsorted(env.pitch_deg, p_at[0])), int(np.searchsorted(env.roll_deg, p_at[1]))
    return AttitudeEnvelope(
        method="weighted least squares on the unit sphere (Tripp & Tcheng eqs. 99–104) with local |g| "
               f"taken as unknown within ±{LOCAL_GRAVITY_TOLERANCE:g} of the calibration's (as the "
               "attitude is estimated in use), one new reading, top-forward mount; u_c from the complete "
               "covariance of the coefficients and the reading (the uncertainty budget's Type A and "
               "Type B parts, with their correlations), U95 = k·u_c with k = t₀.₉₇₅(ν_eff) at each "
               "attitude (k stated: at the largest pitch U95)",
        usage_pitch_deg=settings.usage_pitch_deg, usage_roll_deg=settings.usage_roll_deg,
        grid_step_deg=settings.grid_step_deg, grid_points=int(env.u95_pitch_deg.size),
        k=float(env.k_pitch[i, j]),
        degrees_of_freedom=env.dof,
        pitch_U95_max_deg=p_max, pitch_U95_rms_deg=p_rms, pitch_U95_max_at_deg=p_at,
        roll_U95_max_deg=r_max, roll_U95_rms_deg=r_rms, roll_U95_max_at_deg=r_at,
        roll_undefined_points=int(np.sum(~np.isfinite(env.u95_roll_deg))),
        closed_form=_closed_form_envelope(cal, settings, p_max, p_at))


def _closed_form_envelope(cal: Calibration, settings: CertificateSettings, sphere_pitch_max: float,
                          sphere_at: tuple[float, float]) -> ClosedFormEnvelope:
    """The closed form's U95 on the same grid, "undefined" (None) where it breaks down, and the
    ratio to the sphere estimator where the sphere's pitch U95 is largest."""
    env = envelope_grid(cal, settings, closed_form)
    p_max, p_rms, p_at = _summary(env, env.u95_pitch_deg)
    r_max, r_rms, r_at = _summary(env, env.u95_roll_deg)
    undefined = int(np.sum(~np.isfinite(env.u95_pitch_deg)))
    i = int(np.searchsorted(env.pitch_deg, sphere_at[0]))
    j = int(np.searchsorted(env.roll_deg, sphere_at[1]))
    ratio = env.u95_pitch_deg[i, j] / sphere_pitch_max
    statement = ("In use, labcal gives both estimators (the closed form, and least squares on the "
                 "sphere); this certificate's budget and "
                 f"conformity are for the sphere estimator. At pitch {sphere_at[0]:g}°, roll "
                 f"{sphere_at[1]:g}° the closed form's pitch U95 is "
                 + (f"{ratio:.2g}× the sphere estimator's." if np.isfinite(ratio) else "undefined.")
                 + (f" The closed form is undefined at {undefined} attitude(s) near pitch ±90°, where asin "
                    "has no usable slope and roll does not exist." if undefined else ""))
    return ClosedFormEnvelope(
        method="Soto's closed form g = (V − B)S⁻¹, pitch = asin g_x, roll = atan2(g_y, g_z) (eqs. 5–7), "
               "first-order uncertainty from the same complete covariance as the sphere estimator's",
        pitch_U95_max_deg=p_max, pitch_U95_rms_deg=p_rms, pitch_U95_max_at_deg=p_at,
        roll_U95_max_deg=r_max, roll_U95_rms_deg=r_rms, roll_U95_max_at_deg=r_at,
        undefined_points=undefined, statement=statement)


# --- building a certificate from a run -------------------------------------------------------------
def _recorded(meta_value, given: str | None, what: str, run_dir: Path) -> str | None:
    """A value the run recorded, or the one given on the command line; never two different ones.
    Whitespace around either is no difference and is dropped: a run recorded before serials were
    checked may hold "ACC-0042 ", which its certificate (and the DCC's schema) must not carry."""
    recorded = meta_value.strip() if isinstance(meta_value, str) else meta_value
    given = given.strip() if given else given
    if given and recorded and given != recorded:
        raise LabcalError(f"{run_dir}: the run records {what} {meta_value!r}; {given!r} disagrees")
    return given or recorded or None


def _expanded(fit_dof: NDArray, budget: UncertaintyBudget, sensors: tuple[str, ...] = SENSORS) -> Expanded:
    """U = k·u_c of every coefficient, u_c from the whole budget (Type A and B); per sensor the
    smallest Welch–Satterthwaite ν_eff of its coefficients, truncated (GUM G.4.1 note 1), sets k.
    With no Type B input this is the fit's own ν and standard error."""
    nu_coef = np.array([[np.inf if n is None else n for n in row] for row in budget.coefficients.nu_eff])
    nu_min = nu_coef.min(axis=0)
    nu = np.where(np.isfinite(nu_min), np.floor(np.nan_to_num(nu_min) + 1e-6), fit_dof).astype(int)
    k = t_quantile(0.5 + COVERAGE / 2, nu)
    ks = ", ".join(f"{s}: k = {kj:.2f} at ν_eff = {n}" for s, kj, n in zip(sensors, k, nu, strict=True))
    statement = ("The reported expanded uncertainty is the combined standard uncertainty of the budget's "
                 f"sources multiplied by the coverage factor k = t₀.₉₇₅(ν_eff) ({ks}), which for a "
                 "t-distribution corresponds to a coverage probability of approximately 95 %.")
    u_c = np.array(budget.coefficients.u_c)
    return Expanded(coverage_probability=COVERAGE, nu_eff=nu.tolist(), k=k.tolist(),
                    U=(k[None, :] * u_c).tolist(), statement=statement)


def _plan_audit(record: RunRecord, settings: CertificateSettings) -> PlanAudit:
    leaks = audit(record.plan)
    summary = audit_summary(leaks)
    return PlanAudit(
        zero_below=LEAK_ZERO,
        misalignments={name: Leak(**summary[name], per_radian=leaks[name].tolist()) for name in leaks},
        figure_of_merit_usage_sqrt=figure_of_merit(record.plan, settings.usage_pitch_deg) ** 0.5)


def _conformity(X: NDArray, U: NDArray, budget: UncertaintyBudget, settings: CertificateSettings,
                sensors: tuple[str, ...] = SENSORS) -> Conformity | None:
    checks, rules = [], []
    tol = settings.attitude_u95_max_deg
    if tol is not None:
        rules.append("the attitude passes when the largest 95 % expanded uncertainty of inferred pitch and "
                     "of inferred roll over the usage envelope, from the full uncertainty budget, does not "
                     "exceed the tolerance")
        for angle in ("pitch", "roll"):
            arcsec = stated_U95_arcsec(budget, angle)
            value = None if arcsec is None else arcsec / 3600.0
            if value is not None:
                checks.append(Check(quantity=f"{angle} U95, largest over the usage envelope", value=value,
                                    limit=tol, unit="°", passed=value <= tol))
    if settings.bias_max_v is not None:
        rules.append("a bias passes when |B| + U(B) does not exceed its limit (guarded acceptance with guard "
                     "band w = U, ILAC-G8)")
        for j, s in enumerate(sensors):
            value = abs(float(X[0, j])) + float(U[0, j])
            checks.append(Check(quantity=f"|B_{s}| + U(B_{s})", value=value, limit=settings.bias_max_v,
                                unit="V", passed=value <= settings.bias_max_v))
    if not checks:
        return None
    rule = "; ".join(rules)
    return Conformity(decision_rule=rule[0].upper() + rule[1:] + ".", checks=checks,
                      passed=all(c.passed for c in checks))


def _environment(record: RunRecord) -> Environment:
    t = record.readings.temp_c
    if t is None:
        return Environment(note="temperature not recorded with the readings")
    return Environment(temperature_c_min=float(t.min()), temperature_c_max=float(t.max()),
                       temperature_c_mean=float(t.mean()),
                       note="temperature at the instrument during the readings")


STORY_EVENTS = 200  # a day-long run with many remounts stays readable; the journal keeps every one


def _story(record: RunRecord) -> RunStory:
    """The journal's story: what happened to the run. The tables' moves (journaled, each before it
    starts, for the cables' winding) are the run's routine, not its story."""
    events = [e for e in record.events if e.kind != MOVE_EVENT]
    kinds = [e.kind for e in events]
    listed = events[:STORY_EVENTS]
    return RunStory(counts={k: kinds.count(k) for k in dict.fromkeys(kinds)},
                    events=[JournalEvent(utc=e.utc, station_time_s=e.station_time, kind=e.kind,
                                         message=e.message) for e in listed],
                    omitted=len(events) - len(listed))


METHOD = ("Linear model V = B + gᵀS fitted per sensor by least squares on the nominal gravity of each "
          "calibration point (Soto 2020, eqs. 13–21). Standard uncertainties are Type A: the residual "
          "standard error, or where replication shows significant lack of fit the lack-of-fit mean square "
          "(Tripp & Tcheng 1999, §8), so ν_eff is the degrees of freedom of that estimate. Systematic "
          "misalignments of the calibration device are not added to U; the plan audit states how far each "
          "one leaks into the coefficients. Attitude uncertainties propagate the full coefficient covariance "
          "and one new reading's variance (Tripp & Tcheng eqs. 99–104).")
METHOD_DEVICE = ("Device model: V = B + g(p, r, y, u; a, b, d, e, f, k)ᵀS (Soto 2020, eq. 11) fitted by "
                 "nonlinear least squares from the linear fit, estimating the calibration device's six "
                 "misalignments with the coefficients; the coefficients are corrected for them and their "
                 "uncertainty is the budget's device-misalignment row (the section 'device' gives them with "
                 "U, the instrument's intrinsic parameters and the covariance of all 18 parameters). "
                 "Each sensor's readings are weighted by its noise (replicate scatter where there are "
                 "replicates). Attitude uncertainties propagate the coefficient covariance and one new "
                 "reading's variance (Tripp & Tcheng eqs. 99–104).")
METHOD_PACKAGE = ("Linear model v = B + gᵀs fitted per sensor of the package by least squares on the nominal "
                  "gravity of each calibration point (Tripp & Tcheng 1999 eq. 8 in linear form, with the "
                  "temperature terms of their Table 2 where the fit has them); each sensor's offset b, "
                  "sensitivity S, coning angle Ω and azimuth A (eqs. 2, 4, 5) follow from its column. "
                  "Standard uncertainties of the coefficients are Type A, as for a three-sensor instrument. "
                  "The package's angles, and how roll is obtained in use, are its package section's: "
                  "Tripp & Tcheng §6.1-6.5, from this calibration's own coefficients and covariance.")
STATEMENTS = ("The results relate only to the item calibrated.",
              "Coefficient covariances are given in full in the JSON certificate; the attitude uncertainty "
              "depends on them.")


def _device_fit_doc(device: DeviceFit, linear: Fit) -> dict:
    """The fit section of a certificate built on the device model: its coefficients and their
    covariance (marginal over a…k) in the linear fit's layout, so `labcal attitude --cert` reads it
    as it reads any fit; the replication analysis is the linear fit's (Tripp & Tcheng Table 2)."""
    doc = device.to_json()
    basis = ("device model residual scatter" if device.replication is None
             else "device model σ_prec² + σ_bias²")
    return {**{k: doc[k] for k in ("model", "coefficients", "standard_errors", "covariance",
                                   "residual_standard_error", "reading_sd", "degrees_of_freedom",
                                   "uncertainty_dof", "n_points", "layout")},
            "parameters": list(BASE_NAMES), "uncertainty_basis": [basis] * 3,
            "replication": linear.to_json().get("replication"), "notes": doc.get("notes", [])}


def _device_section(device: DeviceFit, note: str) -> dict:
    doc = device.to_json()
    return DeviceSection(
        note=note, misalignments=doc["misalignments"], coverage_factor_95=doc["coverage_factor_95"],
        degrees_of_freedom=doc["degrees_of_freedom"], intrinsic=doc["intrinsic"],
        identifiability=doc["identifiability"], misalignment_test=doc["misalignment_test"],
        parameters=doc["parameters"], covariance=device.covariance.tolist()).model_dump()


# --- a re-issue keeps the identification of the certificate it replaces ---------------------------
def _identification(laboratory: str, admin: Administration | None, serial: str, operator: str | None
                    ) -> dict[str, str | None]:
    """The identification fields a re-issue carries over, by name, as the certificate states them."""
    lab = laboratory
    if admin is not None:
        lab = ", ".join(p for p in (admin.laboratory.name, admin.laboratory.address) if p) or laboratory
    item = admin.item if admin is not None else None
    return {"laboratory": lab or None, "customer": admin.customer if admin else None,
            "manufacturer": (item.manufacturer or None) if item else None,
            "model": (item.model or None) if item else None, "serial": serial,
            "received": item.received.isoformat() if item and item.received else None,
            "operator": operator}


def identification(cert: Certificate) -> dict[str, str | None]:
    return _identification(cert.laboratory, cert.administration, cert.instrument.serial, cert.operator)


def changed_fields(before: dict[str, str | None], after: dict[str, str | None]) -> list[str]:
    """Each identification field that differs, in words: ``customer ('A' → 'B')``."""
    def said(v: str | None) -> str:
        return "not stated" if v is None else repr(v)
    return [f"{k} ({said(before.get(k))} → {said(v)})" for k, v in after.items() if before.get(k) != v]


def kept_identification(previous: Certificate | None, item: ItemGiven, serial: str | None,
                        operator: str | None) -> tuple[ItemGiven, str | None, str | None]:
    """What the command line gives, and for each field it leaves out, the certificate this one
    replaces (an approved one re-issued, or a draft reported again): a re-issue never drops the
    customer, the item or its receipt date because the command line did not repeat them."""
    if previous is None:
        return item, serial, operator
    a = previous.administration
    if a is not None:
        item = ItemGiven(item.customer or a.customer, item.manufacturer or a.item.manufacturer or None,
                         item.model or a.item.model or None, item.received or a.item.received)
    return item, serial or previous.instrument.serial, operator or previous.operator


def override_statement(checklist: Checklist | None) -> list[str]:
    """The certificate's statement of `checklist_overrides` (none: an empty list)."""
    found = checklist_overrides(checklist)
    if not found:
        return []
    return ["The pre-run checklist was not met and the calibration went on at the operator's decision: "
            + "; ".join(item.rstrip(".") for item in found) + "."]


def build_certificate(record: RunRecord, fit: Fit, settings: CertificateSettings | None = None, *,
                      serial: str | None = None, operator: str | None = None,
                      issued_utc: datetime | None = None, inputs: TypeBInputs | None = None,
                      monte_carlo: int = 0, revision: int = 1, replaces: str | None = None,
                      section: CertificateSection | None = None, item: ItemGiven | None = None,
                      device: DeviceFit | None = None, model_note: str | None = None,
                      replaced: Certificate | None = None, journal_records: int | None = None,
                      lab_number: str | None = None) -> Certificate:
    """The sealed certificate of a run's fit. ``serial``/``operator`` fill in what the run did not
    record (and may not contradict it); a dry run's instrument is SIMULATED. ``inputs``: the bench's
    Type B inputs (none: a Type A budget); ``monte_carlo``: trials of the JCGM 101 check (0: none);
    ``section``: what the station file says (traceability); ``item``: customer and item details;
    ``device``: the device model the run's fit.json holds (`preferred_fit`), on which the certificate
    is then built, with ``model_note`` the line saying which model and why; ``replaced``: the
    certificate this revision replaces, whose identification fields that differ are then stated."""
    settings = settings or CertificateSettings()
    meta, run_dir = record.meta, record.directory
    serial = _recorded(meta.instrument_serial, serial, "instrument serial", run_dir) \
        or (SIMULATED_SERIAL if record.simulated else None)
    if serial is None:
        raise LabcalError(f"{run_dir}: the run does not record the instrument's serial number; give {{0}}",
                          "serial")
    calibrated = meta.started_utc
    if not calibrated:
        raise LabcalError(f"{run_dir}: run.json has no started_utc; the calibration date is unknown")
    fit_doc = json_safe(fit.to_json() if device is None else _device_fit_doc(device, fit))
    if record.readings.units != "V":  # the instrument's output units (its station's [instrument] units)
        fit_doc["layout"] = {**fit_doc["layout"], "units": coefficient_units(record.readings.units)}
    seed = int(record.readings_sha256[:8], 16)  # the same run gives the same Monte Carlo draws
    package = None
    if len(fit.sensors) < 3:  # a package of fewer sensors: its angles as Tripp & Tcheng §6.1-6.5 infer them
        package, envelope, uncertainty = package_documents(record, fit, settings,
                                                           inputs_record(inputs or TypeBInputs()))
    else:
        uncertainty = budget(record, fit, inputs or TypeBInputs(), settings, monte_carlo, seed, device)
        # the envelope states the budget's U95: the complete covariance, through the one function
        cal = replace(calibration_from_json(fit_doc, run_dir), parts=uncertainty.parts())
        envelope = attitude_envelope(cal, settings)
    X = fit.coefficients if device is None else device.coefficients
    expanded = _expanded(fit.variance_dof if device is None else np.full(3, device.dof), uncertainty,
                         fit.sensors)
    try:
        stamp = datetime.fromisoformat(calibrated).astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
    except (TypeError, ValueError):
        raise LabcalError(f"{run_dir}: run.json started_utc {calibrated!r} is not an ISO 8601 time") from None
    admin = administration(record, section or CertificateSection(), item or ItemGiven(), serial)
    notice = SIMULATED_NOTICE if record.simulated else None
    statements = [notice] * (notice is not None) + override_statement(meta.checklist) \
        + list(STATEMENTS) + ([model_note[0].upper() + model_note[1:] + "."] if model_note else [])
    correction = plan_correction(record.plan_text, f"{run_dir}: the run's plan") if device is None else None
    if correction is not None:  # the misalignments the plan's mounts do not identify, corrected for
        statements.append(correction.statement())
    if uncertainty.in_use is not None:  # what the new-reading row assumes of a reading in use
        statements.append(uncertainty.in_use.statement)
    if uncertainty.fit_check is not None:  # the lack-of-fit flag and the drift test's verdict
        statements.append(uncertainty.fit_check.statement)
    statements += overdue_standards(admin.traceability, datetime.fromisoformat(calibrated).date())
    # the checklist's are stated above, in its own words
    overrides = run_overrides(meta, record.events)
    statements += [o.sentence() for o in overrides if o.kind in ("reference standard", "fault accepted")]
    operator = _recorded(meta.operator, operator, "operator", run_dir)
    if replaced is not None:
        changes = changed_fields(identification(replaced),
                                 _identification(settings.laboratory, admin, serial, operator))
        statements.append(f"This revision replaces certificate {replaced.number}; "
                          + (f"identification changed: {'; '.join(changes)}." if changes
                             else "its identification is unchanged."))
    content = {
        "notice": notice,
        "schema": SCHEMA,
        "certificate_id": f"{serial}-{stamp}-{record.readings_sha256[:8]}" + (f"-R{revision}" if revision > 1
                                                                              else ""),
        "revision": revision,
        "replaces": replaces,
        "labcal_version": __version__,
        "laboratory": settings.laboratory,
        "instrument": {"serial": serial, "description": meta.instrument_description or ""},
        "operator": operator,
        "calibrated_utc": calibrated,
        "completed_utc": meta.ended_utc,
        "issued_utc": (issued_utc or datetime.now(UTC)).isoformat(timespec="seconds"),
        "station": {"description": meta.station or "", "device_id": meta.device_id,
                    "simulated": record.simulated,
                    "sequencer_settings": meta.settings,
                    "simulated_truth": meta.simulated_truth},
        "plan": {"name": record.plan.name, "sha256": hashlib.sha256(record.plan_text.encode()).hexdigest(),
                 "toml": record.plan_text, "replicates": record.plan.replicates,
                 "mounts": record.plan.mounts, "points": record.plan.points},
        "data": {"readings_sha256": record.readings_sha256, "n_points": len(record.readings),
                 "replicates": int(len(np.unique(record.readings.replicate))),
                 "journal": None if record.chain is None else record.chain.statement(journal_records)},
        "environment": _environment(record).model_dump(),
        "method": METHOD_PACKAGE if package is not None else METHOD if device is None else METHOD_DEVICE,
        "statements": statements,
        "administration": admin.model_dump(),
        "story": _story(record).model_dump(),
        "fit": {k: fit_doc[k] for k in FitSection.model_fields if k in fit_doc},
        "expanded_uncertainty": expanded.model_dump(),
        "plan_audit": _plan_audit(record, settings).model_dump(),
        "attitude": envelope.model_dump(),
        "device": None if device is None else _device_section(device, model_note or ""),
        "device_correction": None if correction is None else {
            **correction.model_dump(exclude={"u_history_arcsec"}), "statement": correction.statement()},
        "conformity": None if (c := _conformity(X, np.array(expanded.U), uncertainty, settings,
                                                 fit.sensors)) is None else c.model_dump(),
        "package": None if package is None else package.model_dump(),
        "uncertainty_budget": uncertainty.model_dump(),
        "overrides": [o.to_json() for o in overrides] or None,
        "lab_number": lab_number,
    }
    return seal(content)

"""The calibration certificate: a versioned, validated, digest-sealed JSON document.

What a metrologist files (ISO/IEC 17025:2017 7.8.2 and 7.8.4): identities, dates, the station,
the plan, conditions, the coefficients with full covariance, expanded uncertainties U = k·u with
k = t₀.₉₇₅(ν_eff) (GUM G.4), the replication analysis, the plan audit, the attitude uncertainty
in degrees over the usage envelope (7.8.4.1 a: the measurand's unit) and, when tolerances are
given, a statement of conformity with its decision rule (7.8.4.1 e). JSON keeps full precision;
people read U to two significant digits (ILAC-P14, GUM 7.2.6) through `format_result`.

A SHA-256 digest over the canonical JSON of the content seals it: any edit after issue, or a
truncated file, is refused with one line saying what is wrong.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, ValidationError, model_validator

from labcal import __version__
from labcal.analysis.attitude import Calibration, calibration_from_json, sphere_least_squares
from labcal.analysis.design import LEAK_ZERO, audit, audit_summary, figure_of_merit, grid
from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import SENSORS, Fit
from labcal.analysis.kinematics import gravity
from labcal.analysis.models import BASE_NAMES
from labcal.config.files import json_safe, one_line, read_text, write_json
from labcal.config.settings import CertificateSettings
from labcal.config.station import load_certificate_settings
from labcal.errors import LabcalError
from labcal.run.record import RunRecord

# The document format's name, not the module's: certificates issued before the subpackages
# (a8863ee and earlier) carry it, and a format that did not change keeps its name.
SCHEMA = "labcal.certificate/1"
SCHEMA_PREFIX = "labcal.certificate/"
COVERAGE = 0.95
SIMULATED_SERIAL = "SIMULATED"  # a dry run's instrument is the simulator's, whatever the seed


def load_settings(station_path: str | Path | None, **overrides: object) -> CertificateSettings:
    """The ``[certificate]`` table of a station file (defaults without one), then the command
    line's non-None ``overrides``; every mistake is one line naming the file and the field."""
    if station_path is None:
        return CertificateSettings().overridden("command line", **overrides)
    return load_certificate_settings(station_path).overridden(str(station_path), **overrides)


# --- the schema ----------------------------------------------------------------------------------
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _shape(value: list, shape: tuple[int, ...], what: str) -> None:
    if np.shape(value) != shape:
        raise ValueError(f"{what} must have shape {'×'.join(map(str, shape))}, not "
                         f"{'×'.join(map(str, np.shape(value)))}")


class Instrument(_Strict):
    serial: str = Field(min_length=1)
    description: str = ""


class StationRecord(_Strict):
    """What the certificate records of the calibration device and how the sequencer ran it (not the
    live station the sequencer drives, `labcal.run.station.Station`); a dry run keeps the
    simulator's truth."""

    description: str
    device_id: str | None = None
    simulated: bool
    sequencer_settings: dict
    simulated_truth: dict | None = None


class PlanRecord(_Strict):
    name: str
    sha256: str = Field(pattern="^[0-9a-f]{64}$")
    toml: str
    replicates: int = Field(ge=1)
    mounts: list[tuple[float, float]]
    points: list[tuple[float, float]]

    @model_validator(mode="after")
    def _hash(self) -> PlanRecord:
        if hashlib.sha256(self.toml.encode()).hexdigest() != self.sha256:
            raise ValueError("sha256 does not match the plan text")
        return self


class DataRecord(_Strict):
    readings_sha256: str = Field(pattern="^[0-9a-f]{64}$")
    n_points: int = Field(ge=1)
    replicates: int = Field(ge=1)


class Environment(_Strict):
    temperature_c_min: float | None = None
    temperature_c_max: float | None = None
    temperature_c_mean: float | None = None
    note: str = ""


class FitSection(_Strict):
    """The fit JSON contract (DESIGN.md §5) as `labcal.fit.Fit.to_json` writes it, so that
    `labcal attitude --cert` reads a certificate exactly as it reads a fit."""

    model: Literal["linear"]
    parameters: list[str]
    coefficients: list[list[float]]
    standard_errors: list[list[float]]
    covariance: list[list[list[float]]]
    residual_standard_error: list[float]
    reading_sd: list[float]
    degrees_of_freedom: int = Field(ge=1)
    uncertainty_dof: list[int]
    uncertainty_basis: list[str]
    n_points: int
    layout: dict
    extensions: dict | None = None
    replication: dict | None = None
    notes: list[str] = []

    @model_validator(mode="after")
    def _shapes(self) -> FitSection:
        n = len(self.parameters)
        _shape(self.coefficients, (4, 3), "coefficients")
        _shape(self.standard_errors, (4, 3), "standard_errors")
        _shape(self.covariance, (3, n, n), "covariance")
        for name in ("residual_standard_error", "reading_sd", "uncertainty_dof", "uncertainty_basis"):
            _shape(getattr(self, name), (3,), name)
        return self


class Expanded(_Strict):
    """U = k·u per coefficient, k = t at ν_eff per sensor (GUM G.4)."""

    coverage_probability: float
    nu_eff: list[int]
    k: list[float]
    U: list[list[float]]
    statement: str

    @model_validator(mode="after")
    def _shapes(self) -> Expanded:
        _shape(self.U, (4, 3), "U")
        _shape(self.k, (3,), "k")
        _shape(self.nu_eff, (3,), "nu_eff")
        return self


class Leak(_Strict):
    bias_max: float
    off_diagonal_max: float
    diagonal_max: float
    cancelled: bool
    per_radian: list[list[float]]


class PlanAudit(_Strict):
    """Leakage of each CD misalignment into X per radian (Soto §7) and Box's V over usage pitch."""

    zero_below: float
    misalignments: dict[str, Leak]
    figure_of_merit_usage_sqrt: float


class AttitudeEnvelope(_Strict):
    method: str
    usage_pitch_deg: tuple[float, float]
    usage_roll_deg: tuple[float, float]
    grid_step_deg: float
    grid_points: int
    k: float
    degrees_of_freedom: int
    pitch_U95_max_deg: float
    pitch_U95_rms_deg: float
    pitch_U95_max_at_deg: tuple[float, float]
    roll_U95_max_deg: float | None
    roll_U95_rms_deg: float | None
    roll_U95_max_at_deg: tuple[float, float] | None
    roll_undefined_points: int


class Check(_Strict):
    quantity: str
    value: float
    limit: float
    unit: str
    passed: bool


class Conformity(_Strict):
    decision_rule: str
    checks: list[Check]
    passed: bool


class Digest(_Strict):
    algorithm: Literal["sha256"] = "sha256"
    value: str = Field(pattern="^[0-9a-f]{64}$")


class Certificate(_Strict):
    model_config = ConfigDict(validate_by_alias=True, validate_by_name=True, serialize_by_alias=True)

    schema_id: Literal["labcal.certificate/1"] = Field(alias="schema")
    certificate_id: str
    labcal_version: str
    laboratory: str
    instrument: Instrument
    operator: str | None
    calibrated_utc: AwareDatetime
    completed_utc: AwareDatetime | None
    issued_utc: AwareDatetime
    station: StationRecord
    plan: PlanRecord
    data: DataRecord
    environment: Environment
    method: str
    statements: list[str]
    fit: FitSection
    expanded_uncertainty: Expanded
    plan_audit: PlanAudit
    attitude: AttitudeEnvelope
    conformity: Conformity | None
    digest: Digest

    @property
    def coefficients(self) -> NDArray:
        return np.array(self.fit.coefficients)

    @property
    def standard_uncertainty(self) -> NDArray:
        return np.array(self.fit.standard_errors)

    @property
    def U(self) -> NDArray:
        return np.array(self.expanded_uncertainty.U)

    def calibration(self) -> Calibration:
        return calibration_from_json(self.fit.model_dump(), self.certificate_id)

    def to_json(self) -> dict:
        return self.model_dump(mode="json")


def content_digest(doc: dict) -> str:
    """SHA-256 of the canonical JSON (sorted keys, no spaces, UTF-8) of everything but the digest."""
    content = {k: v for k, v in doc.items() if k != "digest"}
    canonical = json.dumps(content, sort_keys=True, separators=(",", ":"), ensure_ascii=False,
                           allow_nan=False)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def seal(content: dict) -> Certificate:
    """Validate the content and attach its digest."""
    try:
        draft = Certificate.model_validate({**content, "digest": {"value": "0" * 64}})
    except ValidationError as exc:  # a bug, not a user error: the builder made an invalid document
        raise ValueError(f"certificate content is invalid: {one_line(exc)}") from exc
    doc = draft.to_json()
    return Certificate.model_validate({**doc, "digest": {"value": content_digest(doc)}})


# --- reading and writing ---------------------------------------------------------------------------
def parse_json(text: str, source: str):
    """JSON text, or one line saying why not — naming truncation, the usual way files break."""
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        if exc.pos >= len(text.rstrip()) or exc.msg.startswith("Unterminated string"):
            raise LabcalError(f"{source}: not valid JSON: the file is truncated (it stops at line "
                              f"{text.rstrip().count(chr(10)) + 1} before the document ends)") from None
        raise LabcalError(f"{source}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


def is_certificate(doc) -> bool:
    return isinstance(doc, dict) and str(doc.get("schema", "")).startswith(SCHEMA_PREFIX)


def certificate_from_doc(doc, source: str) -> Certificate:
    """Validate a parsed certificate against its schema, then check its digest."""
    if not isinstance(doc, dict) or "schema" not in doc:
        raise LabcalError(f"{source}: not a labcal certificate (no \"schema\": \"{SCHEMA}\")")
    if doc["schema"] != SCHEMA:
        raise LabcalError(f"{source}: certificate schema {doc['schema']!r} is not supported; this labcal "
                          f"reads {SCHEMA}")
    try:
        cert = Certificate.model_validate(doc)
    except ValidationError as exc:
        raise LabcalError(f"{source}: invalid certificate: {one_line(exc)}") from None
    actual = content_digest(cert.to_json())
    if actual != cert.digest.value:
        raise LabcalError(f"{source}: digest mismatch: the content was altered after issue (recorded "
                          f"sha256 {cert.digest.value[:12]}…, content hashes to {actual[:12]}…)")
    return cert


def read_certificate(path: str | Path) -> Certificate:
    return certificate_from_doc(parse_json(read_text(path, "certificate"), str(path)), str(path))


def write_certificate(path: str | Path, cert: Certificate) -> Path:
    """Write atomically after checking the certificate against its schema and digest again."""
    path = Path(path)
    certificate_from_doc(cert.to_json(), str(path))
    try:
        write_json(path, cert.to_json())
    except OSError as exc:
        raise LabcalError(f"{path}: cannot write certificate ({exc.strerror})") from None
    return path


# --- human-readable numbers (ILAC-P14, GUM 7.2.6) --------------------------------------------------
def round_uncertainty(u: float) -> tuple[float, int]:
    """U rounded to two significant digits, and the number of decimals that keeps them."""
    decimals = 1 - math.floor(math.log10(u))
    rounded = round(u, decimals)
    if rounded >= 10 ** (2 - decimals):  # 9.96 → 10: two digits are now one place further left
        decimals -= 1
        rounded = round(u, decimals)
    return rounded, decimals


def format_uncertainty(u: float) -> str:
    if not (math.isfinite(u) and u > 0):
        return "—" if not math.isfinite(u) else "0"
    rounded, decimals = round_uncertainty(u)
    return f"{rounded:.{max(decimals, 0)}f}"


def format_result(value: float, u: float, unit: str = "") -> str:
    """'y ± U unit' with U to two significant digits and y rounded to U's last digit."""
    unit = f" {unit}" if unit else ""
    if not (math.isfinite(u) and u > 0):
        return f"{value:.7g}{unit}"
    _, decimals = round_uncertainty(u)
    return f"{round(value, decimals):.{max(decimals, 0)}f} ± {format_uncertainty(u)}{unit}"


# --- attitude uncertainty over the usage envelope ---------------------------------------------------
@dataclass(frozen=True)
class EnvelopeGrid:
    """U95 of inferred pitch and roll (°) on the pitch × roll grid of the usage envelope."""

    pitch_deg: NDArray  # (n_p,)
    roll_deg: NDArray  # (n_r,)
    u95_pitch_deg: NDArray  # (n_p, n_r)
    u95_roll_deg: NDArray  # (n_p, n_r), NaN where roll is undefined
    k: float
    dof: int


def envelope_grid(cal: Calibration, settings: CertificateSettings) -> EnvelopeGrid:
    """Weighted least squares on the sphere (Tripp eqs. 99–104) at every grid attitude, top-forward
    mount, for one new reading: the uncertainty a user of the instrument gets, in degrees."""
    step = settings.grid_step_deg
    points = np.array(grid(*settings.usage_pitch_deg, step, *settings.usage_roll_deg, step))
    pitch, roll = np.unique(points[:, 0]), np.unique(points[:, 1])
    g = gravity(np.radians(points[:, 0]), np.radians(points[:, 1]), 0.0, 0.0)
    att = sphere_least_squares(cal, cal.X[0] + g @ cal.X[1:])
    shape = (len(pitch), len(roll))
    return EnvelopeGrid(pitch, roll, (att.k95 * np.degrees(att.u_pitch)).reshape(shape),
                        (att.k95 * np.degrees(att.u_roll)).reshape(shape), att.k95, cal.dof)


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
    return AttitudeEnvelope(
        method="weighted least squares on the unit sphere (Tripp & Tcheng eqs. 99–104), one new reading, "
               "top-forward mount; U95 = k·u with k = t₀.₉₇₅(ν)",
        usage_pitch_deg=settings.usage_pitch_deg, usage_roll_deg=settings.usage_roll_deg,
        grid_step_deg=settings.grid_step_deg, grid_points=int(env.u95_pitch_deg.size), k=env.k,
        degrees_of_freedom=env.dof,
        pitch_U95_max_deg=p_max, pitch_U95_rms_deg=p_rms, pitch_U95_max_at_deg=p_at,
        roll_U95_max_deg=r_max, roll_U95_rms_deg=r_rms, roll_U95_max_at_deg=r_at,
        roll_undefined_points=int(np.sum(~np.isfinite(env.u95_roll_deg))))


# --- building a certificate from a run -------------------------------------------------------------
def _recorded(meta_value, given: str | None, what: str, run_dir: Path) -> str | None:
    """A value the run recorded, or the one given on the command line; never two different ones."""
    if given and meta_value and given != meta_value:
        raise LabcalError(f"{run_dir}: the run records {what} {meta_value!r}; {given!r} disagrees")
    return given or meta_value or None


def _expanded(fit: Fit) -> Expanded:
    nu = fit.variance_dof
    k = t_quantile(0.5 + COVERAGE / 2, nu)
    ks = ", ".join(f"{s}: k = {kj:.2f} at ν_eff = {n}" for s, kj, n in zip(SENSORS, k, nu, strict=True))
    statement = ("The reported expanded uncertainty is the standard uncertainty multiplied by the coverage "
                 f"factor k = t₀.₉₇₅(ν_eff) ({ks}), which for a t-distribution corresponds to a coverage "
                 "probability of approximately 95 %.")
    return Expanded(coverage_probability=COVERAGE, nu_eff=nu.tolist(), k=k.tolist(),
                    U=(k[None, :] * fit.stderr[: len(BASE_NAMES)]).tolist(), statement=statement)


def _plan_audit(record: RunRecord, settings: CertificateSettings) -> PlanAudit:
    leaks = audit(record.plan)
    summary = audit_summary(leaks)
    return PlanAudit(
        zero_below=LEAK_ZERO,
        misalignments={name: Leak(**summary[name], per_radian=leaks[name].tolist()) for name in leaks},
        figure_of_merit_usage_sqrt=figure_of_merit(record.plan, settings.usage_pitch_deg) ** 0.5)


def _conformity(fit: Fit, U: NDArray, env: AttitudeEnvelope, settings: CertificateSettings
                ) -> Conformity | None:
    checks, rules = [], []
    tol = settings.attitude_u95_max_deg
    if tol is not None:
        rules.append("the attitude passes when the largest 95 % expanded uncertainty of inferred pitch and "
                     "of inferred roll over the usage envelope does not exceed the tolerance")
        for angle, value in (("pitch", env.pitch_U95_max_deg), ("roll", env.roll_U95_max_deg)):
            if value is not None:
                checks.append(Check(quantity=f"{angle} U95, largest over the usage envelope", value=value,
                                    limit=tol, unit="°", passed=value <= tol))
    if settings.bias_max_v is not None:
        rules.append("a bias passes when |B| + U(B) does not exceed its limit (guarded acceptance with guard "
                     "band w = U, ILAC-G8)")
        for j, s in enumerate(SENSORS):
            value = abs(float(fit.coefficients[0, j])) + float(U[0, j])
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


METHOD = ("Linear model V = B + gᵀS fitted per sensor by least squares on the nominal gravity of each "
          "calibration point (Soto 2020, eqs. 13–21). Standard uncertainties are Type A: the residual "
          "standard error, or where replication shows significant lack of fit the lack-of-fit mean square "
          "(Tripp & Tcheng 1999, §8), so ν_eff is the degrees of freedom of that estimate. Systematic "
          "misalignments of the calibration device are not added to U; the plan audit states how far each "
          "one leaks into the coefficients. Attitude uncertainties propagate the full coefficient covariance "
          "and one new reading's variance (Tripp & Tcheng eqs. 99–104).")
STATEMENTS = ("The results relate only to the item calibrated.",
              "Coefficient covariances are given in full in the JSON certificate; the attitude uncertainty "
              "depends on them.")


def build_certificate(record: RunRecord, fit: Fit, settings: CertificateSettings | None = None, *,
                      serial: str | None = None, operator: str | None = None,
                      issued_utc: datetime | None = None) -> Certificate:
    """The sealed certificate of a run's fit. ``serial``/``operator`` fill in what the run did not
    record (and may not contradict it); a dry run's instrument is SIMULATED."""
    settings = settings or CertificateSettings()
    meta, run_dir = record.meta, record.directory
    serial = _recorded(meta.get("instrument_serial"), serial, "instrument serial", run_dir) \
        or (SIMULATED_SERIAL if record.simulated else None)
    if serial is None:
        raise LabcalError(f"{run_dir}: the run does not record the instrument's serial number; give --serial")
    calibrated = meta.get("started_utc")
    if not calibrated:
        raise LabcalError(f"{run_dir}: run.json has no started_utc; the calibration date is unknown")
    fit_doc = json_safe(fit.to_json())
    expanded = _expanded(fit)
    cal = calibration_from_json(fit_doc, run_dir)
    envelope = attitude_envelope(cal, settings)
    try:
        stamp = datetime.fromisoformat(calibrated).astimezone(UTC).strftime("%Y%m%dT%H%M%SZ")
    except (TypeError, ValueError):
        raise LabcalError(f"{run_dir}: run.json started_utc {calibrated!r} is not an ISO 8601 time") from None
    content = {
        "schema": SCHEMA,
        "certificate_id": f"{serial}-{stamp}-{record.readings_sha256[:8]}",
        "labcal_version": __version__,
        "laboratory": settings.laboratory,
        "instrument": {"serial": serial, "description": meta.get("instrument_description", "")},
        "operator": _recorded(meta.get("operator"), operator, "operator", run_dir),
        "calibrated_utc": calibrated,
        "completed_utc": meta.get("ended_utc"),
        "issued_utc": (issued_utc or datetime.now(UTC)).isoformat(timespec="seconds"),
        "station": {"description": meta.get("station", ""), "device_id": meta.get("device_id"),
                    "simulated": record.simulated,
                    "sequencer_settings": meta.get("settings", {}),
                    "simulated_truth": meta.get("simulated_truth")},
        "plan": {"name": record.plan.name, "sha256": hashlib.sha256(record.plan_text.encode()).hexdigest(),
                 "toml": record.plan_text, "replicates": record.plan.replicates,
                 "mounts": record.plan.mounts, "points": record.plan.points},
        "data": {"readings_sha256": record.readings_sha256, "n_points": len(record.readings),
                 "replicates": int(len(np.unique(record.readings.replicate)))},
        "environment": _environment(record).model_dump(),
        "method": METHOD,
        "statements": list(STATEMENTS),
        "fit": {k: fit_doc[k] for k in FitSection.model_fields if k in fit_doc},
        "expanded_uncertainty": expanded.model_dump(),
        "plan_audit": _plan_audit(record, settings).model_dump(),
        "attitude": envelope.model_dump(),
        "conformity": None if (c := _conformity(fit, np.array(expanded.U), envelope, settings)) is None
        else c.model_dump(),
    }
    return seal(content)


def load_calibration(path: str | Path) -> Calibration:
    """Read the coefficients and their uncertainty from a fit JSON or a certificate; a certificate's
    schema and digest are verified first, so a tampered certificate never converts a voltage."""
    doc = parse_json(read_text(path, "calibration"), str(path))
    if is_certificate(doc):
        doc = certificate_from_doc(doc, str(path)).fit.model_dump()
    return calibration_from_json(doc.get("fit", doc) if isinstance(doc, dict) else doc, path)

"""The calibration certificate: a versioned, validated, digest-sealed JSON document.

What a metrologist files (ISO/IEC 17025:2017 7.8.2 and 7.8.4): identities, dates, the station,
the plan, conditions, the coefficients with full covariance, expanded uncertainties U = k·u with
k = t₀.₉₇₅(ν_eff) (GUM G.4), the replication analysis, the plan audit, the attitude uncertainty
in degrees over the usage envelope (7.8.4.1 a: the measurand's unit) and, when tolerances are
given, a statement of conformity with its decision rule (7.8.4.1 e). JSON keeps full precision;
people read U to two significant digits (ILAC-P14, GUM 7.2.6) through `format_result`.

A SHA-256 digest over the canonical JSON of the content seals it: any edit after issue, or a
truncated file, is refused with one line saying what is wrong. This module is the document and
how it is read back; `labcal.documents.issuing` builds one from a finished run.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import replace
from datetime import date
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    AwareDatetime,
    ConfigDict,
    Field,
    ValidationError,
    model_validator,
)

from labcal.analysis.attitude import Calibration, CovariancePart, calibration_from_json
from labcal.analysis.packages import PackageCalibration, Sensor
from labcal.config.files import MAX_DEPTH, check_depth, one_line, read_text, write_json
from labcal.config.run_metadata import SequencerRecord, SimulatedTruth, Strict
from labcal.documents.certificate_sections import (
    BudgetInputs,
    DeviceCorrectionRecord,
    Extensions,
    Identifiability,
    Intrinsic,
    Layout,
    MisalignmentTest,
    Replication,
)
from labcal.errors import LabcalError

# The document format's name, not the module's: certificates issued before the subpackages
# (a8863ee and earlier) carry it, and a format that did not change keeps its name.
SCHEMA = "labcal.certificate/1"
SCHEMA_PREFIX = "labcal.certificate/"
COVERAGE = 0.95


# --- the schema ----------------------------------------------------------------------------------
def _shape(value: list, shape: tuple[int, ...], what: str) -> None:
    if np.shape(value) != shape:
        raise ValueError(f"{what} must have shape {'×'.join(map(str, shape))}, not "
                         f"{'×'.join(map(str, np.shape(value)))}")


class Instrument(Strict):
    serial: str = Field(min_length=1)
    description: str = ""


class StationRecord(Strict):
    """What the certificate records of the calibration device and how the sequencer ran it (not the
    live station the sequencer drives, `labcal.devices.station.Station`); a dry run keeps the
    simulator's truth."""

    description: str
    device_id: str | None = None
    simulated: bool
    sequencer_settings: SequencerRecord
    simulated_truth: SimulatedTruth | None = None


class PlanRecord(Strict):
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


def _absent(value: object) -> bool:
    return value is None


class JournalChainRecord(Strict):
    """The run's journal as a chain of digests (`labcal.store.chain`): its first ``records`` records
    after the manifest end in ``head``. Signed with the rest, it ties the approval to the journal's
    every record, not only to the readings the fit used."""

    run_uuid: str = Field(min_length=1)
    records: int = Field(ge=0)
    head: str = Field(pattern="^[0-9a-f]{64}$")


class DataRecord(Strict):
    readings_sha256: str = Field(pattern="^[0-9a-f]{64}$")
    n_points: int = Field(ge=1)
    replicates: int = Field(ge=1)
    # None: the run was journaled before digests (and certificates issued before it state none)
    journal: JournalChainRecord | None = Field(default=None, exclude_if=_absent)


class Environment(Strict):
    temperature_c_min: float | None = None
    temperature_c_max: float | None = None
    temperature_c_mean: float | None = None
    note: str = ""


class FitSection(Strict):
    """The fit JSON contract (docs/design.md §5) as `labcal.analysis.fit.Fit.to_json` writes it, so that
    `labcal attitude --cert` reads a certificate exactly as it reads a fit."""

    model: Literal["linear", "device"]  # device: the coefficients of the device model (DeviceSection)
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
    layout: Layout
    extensions: Extensions | None = None
    replication: dict[str, Replication] | None = None  # per sensor
    notes: list[str] = []

    @model_validator(mode="after")
    def _shapes(self) -> FitSection:
        n, m = len(self.parameters), len(self.layout.columns)  # m sensors: 3, or a package's 1 or 2
        if not 1 <= m <= 3:
            raise ValueError(f"layout has {m} sensor columns; a package has 1 to 3 sensors")
        _shape(self.coefficients, (4, m), "coefficients")
        _shape(self.standard_errors, (4, m), "standard_errors")
        _shape(self.covariance, (m, n, n), "covariance")
        for name in ("residual_standard_error", "reading_sd", "uncertainty_dof", "uncertainty_basis"):
            _shape(getattr(self, name), (m,), name)
        return self


class Misalignment(Strict):
    value_arcsec: float
    u_arcsec: float
    U_arcsec: float


class DeviceSection(Strict):
    """The calibration device estimated with the instrument: its six misalignments with
    U at the device model's k, the instrument's intrinsic parameters, what the plan identifies, the
    F test that judged the model, and θ's full covariance (θ in `parameters` order, misalignments in
    rad², B in V², S in (V/g)²). Present where the certificate is built on the device model."""

    note: str
    misalignments: dict[str, Misalignment]
    coverage_factor_95: float
    degrees_of_freedom: int
    intrinsic: Intrinsic
    identifiability: Identifiability
    misalignment_test: MisalignmentTest
    parameters: list[str]
    covariance: list[list[float]]

    @model_validator(mode="after")
    def _shapes(self) -> DeviceSection:
        _shape(self.covariance, (len(self.parameters),) * 2, "device covariance")
        return self


class Expanded(Strict):
    """U = k·u per coefficient, k = t at ν_eff per sensor (GUM G.4)."""

    coverage_probability: float
    nu_eff: list[int]
    k: list[float]
    U: list[list[float]]
    statement: str

    @model_validator(mode="after")
    def _shapes(self) -> Expanded:
        m = np.shape(self.U)[1] if np.ndim(self.U) == 2 else 0  # one column per sensor
        _shape(self.U, (4, max(m, 1)), "U")
        _shape(self.k, (m,), "k")
        _shape(self.nu_eff, (m,), "nu_eff")
        return self


class Leak(Strict):
    bias_max: float
    off_diagonal_max: float
    diagonal_max: float
    cancelled: bool
    per_radian: list[list[float]]


class PlanAudit(Strict):
    """Leakage of each CD misalignment into X per radian (Soto §7) and Box's V over usage pitch."""

    zero_below: float
    misalignments: dict[str, Leak]
    figure_of_merit_usage_sqrt: float


class ClosedFormEnvelope(Strict):
    """Soto's closed form (eqs. 5–7) on the same grid: its Type A U95 (None: undefined, where the
    closed form breaks down — asin at |g_x| → 1, roll at pitch ±90°) and the statement of which
    estimator `labcal attitude` uses."""

    method: str
    pitch_U95_max_deg: float | None
    pitch_U95_rms_deg: float | None
    pitch_U95_max_at_deg: tuple[float, float] | None
    roll_U95_max_deg: float | None
    roll_U95_rms_deg: float | None
    roll_U95_max_at_deg: tuple[float, float] | None
    undefined_points: int
    statement: str


class AttitudeEnvelope(Strict):
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
    closed_form: ClosedFormEnvelope | None = Field(default=None, exclude_if=_absent)


class TrippSensor(Strict):
    """One sensor of a package in Tripp & Tcheng's terms (eq. 8): offset b, sensitivity S (signed as
    their eqs. 14-16 read), coning angle Ω and azimuth A."""

    b: float
    S: float
    omega_deg: float
    azimuth_deg: float


class PackageSection(Strict):
    """A package of fewer than three sensors (Tripp & Tcheng §6.1-6.5): how its angles are obtained
    in use and their uncertainty, from its own coefficients (`labcal.documents.package`)."""

    package: Literal["single-axis", "two-axis-xy", "two-axis-xz"]
    sensors: list[str]
    coefficients: dict[str, TrippSensor]
    roll_in_use: Literal["inferred", "none", "table", "sensor"]
    roll_sd_deg: float | None
    equations: str
    k: float
    # pitch at a known roll (none, table, sensor): the largest U95 over the usage envelope
    pitch_u95_deg: float | None = Field(default=None, exclude_if=_absent)
    pitch_u95_at_deg: tuple[float, float] | None = Field(default=None, exclude_if=_absent)
    usage_pitch_deg: tuple[float, float] | None = Field(default=None, exclude_if=_absent)
    usage_roll_deg: tuple[float, float] | None = Field(default=None, exclude_if=_absent)
    # pitch and roll inferred together: the usable range where both U95 stay within the limit
    u95_limit_deg: float | None = Field(default=None, exclude_if=_absent)
    usable_pitch_deg: tuple[float, float] | None = Field(default=None, exclude_if=_absent)
    usable_roll_deg: tuple[float, float] | None = Field(default=None, exclude_if=_absent)
    # the calibration's temperatures and the model's reference temperature (where its temperature
    # terms are centred, Tripp Table 2 footnote b; the run's mean temperature)
    temperature_c: tuple[float, float] | None = Field(default=None, exclude_if=_absent)
    t_ref_c: float | None = Field(default=None, exclude_if=_absent)
    statement: str


class Check(Strict):
    quantity: str
    value: float
    limit: float
    unit: str
    passed: bool


class Conformity(Strict):
    decision_rule: str
    checks: list[Check]
    passed: bool


class BudgetRow(Strict):
    """One source of the GUM budget: its input and its contribution u_i to pitch and roll (arcsec)
    at the envelope's worst point (where U95 of that angle is largest) and RMS over the envelope."""

    source: str
    type: Literal["A", "B"]
    distribution: str
    standard_uncertainty: float
    unit: str
    sensitivity_pitch: float | None  # arcsec per unit of the input, at the worst point
    sensitivity_roll: float | None
    pitch_worst_arcsec: float
    pitch_rms_arcsec: float
    roll_worst_arcsec: float | None
    roll_rms_arcsec: float | None
    degrees_of_freedom: float | None  # None: infinite (a Type B input with known bounds)
    added: bool
    note: str = ""


class BudgetTotal(Strict):
    angle: Literal["pitch", "roll"]
    worst_at_deg: tuple[float, float]
    u_c_arcsec: float
    nu_eff: float | None
    k: float
    U95_arcsec: float
    U95_rms_arcsec: float


class MonteCarloCheck(Strict):
    """JCGM 101 propagation of the same inputs at each angle's worst point."""

    trials: int = Field(ge=1)
    seed: int
    angle: Literal["pitch", "roll"]
    at_deg: tuple[float, float]
    linear_U95_arcsec: float
    monte_carlo_U95_arcsec: float
    agree_within_5_percent: bool


class CoefficientBudgetRecord(Strict):
    """Per coefficient (4×3, as X): combined standard uncertainty, ν_eff (None: infinite), k, U, and
    each source's standard uncertainty."""

    u_c: list[list[float]]
    nu_eff: list[list[float | None]]
    k: list[list[float]]
    U: list[list[float]]
    contributions: dict[str, list[list[float]]]


class CovariancePartRecord(Strict):
    """One independent part of the complete covariance of [vec(X) row-major; one new reading]
    (`labcal.analysis.attitude.CovariancePart`): V², V²/g and (V/g)²; dof None: infinite."""

    label: str
    degrees_of_freedom: float | None
    matrix: list[list[float]]

    @model_validator(mode="after")
    def _shapes(self) -> CovariancePartRecord:
        _shape(self.matrix, (15, 15), "covariance part")
        return self

    def part(self) -> CovariancePart:
        dof = np.inf if self.degrees_of_freedom is None else self.degrees_of_freedom
        return CovariancePart(np.array(self.matrix, dtype=float), dof, self.label)


class InUseReading(Strict):
    """What the budget's new-reading row assumes of a reading of the instrument in use: the mean of
    ``samples`` samples, each scattering by the pooled within-window standard deviation of the
    calibration (per channel, in the outputs' unit) with its degrees of freedom."""

    samples: int = Field(ge=1)
    stated: bool  # True: stated for this certificate; False: the calibration's window length
    sample_sd: list[float]
    degrees_of_freedom: float
    windows: int = Field(ge=1)
    statement: str


class BenchCheck(Strict):
    """One group of the bench's stated errors, tested: its variance in the residuals over the stated."""

    ratio: float
    p_value: float


class FitCheck(Strict):
    """The lack-of-fit test of the fit's residuals against the noise (pooled within-window scatter)
    and the station's stated bench errors, and the drift test of the outputs over the run
    (`labcal.analysis.lack_of_fit`)."""

    statistic: float  # Q / ν₁
    degrees_of_freedom: tuple[float, float]
    p_value: float
    bench: dict[str, BenchCheck]
    alpha: float
    lack_of_fit: bool  # the flag: True where any of the tests is significant
    drift_statistic: float
    drift_degrees_of_freedom: int
    drift_p_value: float
    drift: bool
    statement: str


class UncertaintyBudget(Strict):
    method: str
    inputs: BudgetInputs
    rows: list[BudgetRow]
    totals: list[BudgetTotal]
    coefficients: CoefficientBudgetRecord
    monte_carlo: list[MonteCarloCheck] | None = None
    statement: str
    # The complete covariance the totals come from; `labcal attitude --cert` and every other output
    # state the attitude U95 from it (absent in certificates issued before: their fit's Type A).
    covariance: list[CovariancePartRecord] | None = Field(default=None, exclude_if=_absent)
    # The averaging a reading in use is assumed to have (absent: certificates whose new-reading row is
    # the fit's residual, issued before, or from readings that do not carry their windows' scatter).
    in_use: InUseReading | None = Field(default=None, exclude_if=_absent)
    # The lack-of-fit and drift tests (absent: certificates issued before, or readings without their
    # windows' scatter, which give the tests no pure error)
    fit_check: FitCheck | None = Field(default=None, exclude_if=_absent)

    def parts(self) -> tuple[CovariancePart, ...]:
        return tuple(p.part() for p in self.covariance or [])


class LaboratoryRecord(Strict):
    name: str
    address: str
    accreditation_id: str
    country_code: str


class Item(Strict):
    """The item calibrated (ISO/IEC 17025 §7.8.2.1 f) and when it was received."""

    manufacturer: str
    model: str
    serial: str
    received: date | None


class Equipment(Strict):
    """Equipment used, with the identity it reported or its station-file settings. The fields by
    name are what the device reported (None: it reports no such field, or a certificate issued
    before they were recorded)."""

    role: str
    description: str
    identity: str | None
    maker: str | None = Field(default=None, exclude_if=_absent)
    model: str | None = Field(default=None, exclude_if=_absent)
    serial: str | None = Field(default=None, exclude_if=_absent)
    firmware: str | None = Field(default=None, exclude_if=_absent)

    def reported(self) -> str:
        """Maker, model, serial and firmware in words, saying which the device does not report."""
        if self.maker is None and self.model is None:
            return self.identity or "no identity"
        return (f"{' '.join(p for p in (self.maker, self.model) if p)}, serial "
                f"{self.serial or 'not reported by the device'}, firmware {self.firmware or 'not reported'}")


class TraceabilityRecord(Strict):
    equipment: str
    identity: str
    certificate: str
    issued_by: str
    due: date


class OverrideRecord(Strict):
    """A decision to go on regardless that the run was measured under (`labcal.documents.overrides`): an
    unmet checklist item, an overdue reference standard under an approver's override, a fault accepted."""

    kind: str
    what: str
    by: str | None
    reason: str | None
    utc: str | None


class Administration(Strict):
    """ISO/IEC 17025 §7.8.2.1 administrative contents a run alone does not say."""

    laboratory: LaboratoryRecord
    customer: str | None
    item: Item
    equipment: list[Equipment]
    traceability: list[TraceabilityRecord]
    ambient: str


class JournalEvent(Strict):
    utc: str
    station_time_s: float | None
    kind: str
    message: str


class RunStory(Strict):
    """What the journal recorded while the run went on: faults, retries, wrong mounts, pauses,
    resumes, operator prompts and answers, with their times."""

    counts: dict[str, int]
    events: list[JournalEvent]
    omitted: int = Field(ge=0)


Authentication = Literal["password re-entered", "API token"]  # how an approver authenticated to sign


class ServerSignature(Strict):
    """The approval was signed by the lab server's key for an approver signed in to it
    (`labcal.app.server_approval`): which registered server key signed, for which of the server's
    users, with what meaning (21 CFR Part 11 §11.50) and how the approver authenticated for this
    signing (§11.200)."""

    signer: str = Field(min_length=1)  # the server key's registered name
    user_id: int = Field(ge=1)  # the approver among the lab server's users (`labcal user list`)
    meaning: Literal["approved"]
    authentication: Authentication


class Approval(Strict):
    """Who approved the certificate (ISO/IEC 17025 §7.8.2.1 o) and their Ed25519 signature over the
    canonical content (`labcal.documents.approval`)."""

    by: str = Field(min_length=1)
    role: str = Field(min_length=1)
    approved_utc: AwareDatetime
    algorithm: Literal["Ed25519"]
    key_id: str = Field(pattern="^[0-9a-f]{64}$")
    signature: str
    # SHA-256 of the DCC written with the approval, signed with the rest (None: approved before)
    dcc_sha256: str | None = Field(default=None, pattern="^[0-9a-f]{64}$", exclude_if=_absent)
    # Signed by the lab server's key for ``by`` (None: by ``by``'s own key), signed with the rest
    server: ServerSignature | None = Field(default=None, exclude_if=_absent)


class Digest(Strict):
    algorithm: Literal["sha256"] = "sha256"
    value: str = Field(pattern="^[0-9a-f]{64}$")


class Certificate(Strict):
    model_config = ConfigDict(validate_by_alias=True, validate_by_name=True, serialize_by_alias=True)

    # First, so that the document's first line says it: a dry run's results are simulated
    notice: str | None = Field(default=None, exclude_if=_absent)
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
    # Sections added to format 1 are left out of the document when absent, so that certificates
    # issued before them read back and hash exactly as they were issued.
    uncertainty_budget: UncertaintyBudget | None = Field(default=None, exclude_if=_absent)
    administration: Administration | None = Field(default=None, exclude_if=_absent)
    story: RunStory | None = Field(default=None, exclude_if=_absent)
    revision: int | None = Field(default=None, ge=1, exclude_if=_absent)
    replaces: str | None = Field(default=None, exclude_if=_absent)
    approval: Approval | None = Field(default=None, exclude_if=_absent)
    device: DeviceSection | None = Field(default=None, exclude_if=_absent)
    device_correction: DeviceCorrectionRecord | None = Field(default=None, exclude_if=_absent)
    package: PackageSection | None = Field(default=None, exclude_if=_absent)
    overrides: list[OverrideRecord] | None = Field(default=None, exclude_if=_absent)
    lab_number: str | None = Field(default=None, exclude_if=_absent)  # the lab's own number, if it numbers
    digest: Digest

    @model_validator(mode="after")
    def _package(self) -> Certificate:
        """A certificate of fewer than three sensors is a package's, and says so in its section."""
        columns = len(self.fit.layout.columns)
        if self.package is None and columns != 3:
            raise ValueError(f"a fit of {columns} sensor(s) needs the package section that says how its "
                             "angles are obtained")
        if self.package is not None and len(self.package.sensors) != columns:
            raise ValueError(f"the package states {len(self.package.sensors)} sensor(s), the fit {columns}")
        return self

    @property
    def output_unit(self) -> str:
        """The instrument's output unit (V, mV, counts, m/s2) as the fit's layout states it ("counts
        (bias), counts/g (sensitivity)"); volts in certificates issued before it could be another."""
        return self.fit.layout.units.split(" (bias)")[0]

    @property
    def number(self) -> str:
        """The certificate number with its revision, as printed (ISO/IEC 17025 §7.8.2.1 c): the lab's own
        number where the lab numbers its certificates (`labcal.app.numbering`), else labcal's id."""
        return f"{self.lab_number or self.certificate_id} rev. {self.revision or 1}"

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors the coefficients' columns are ("sensor x" → "x"), in order."""
        return tuple(c.removeprefix("sensor ") for c in self.fit.layout.columns)

    def by_sensor(self, values: NDArray) -> NDArray:
        """``values`` (rows × this certificate's sensors) in the three sensors' columns x, y, z, NaN
        in those of sensors a package has not: certificates of one instrument side by side."""
        full = np.full((np.shape(values)[0], 3), np.nan)
        full[:, ["xyz".index(s) for s in self.sensors]] = values
        return full

    @property
    def draft(self) -> bool:
        return self.approval is None

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
        """The calibration `labcal attitude` uses: the fit's coefficients and weights, and the budget's
        complete covariance where the certificate states one."""
        if self.package is not None:
            raise LabcalError(f"certificate {self.certificate_id} is of a {self.package.package} package: "
                              "its "
                              "angles are inferred as its package section states (labcal attitude reads it), "
                              "not by the three-axis estimator")
        cal = calibration_from_json(self.fit.model_dump(), self.certificate_id)
        parts = self.uncertainty_budget.parts() if self.uncertainty_budget is not None else ()
        return replace(cal, parts=parts) if parts else cal

    def package_calibration(self) -> PackageCalibration:
        """What `labcal attitude` uses of a package's certificate: its sensors as its package section
        states them, its coefficients' covariance and a new reading's SD for σ_v, k, how roll is
        obtained in use (σ_R) and the usable range where pitch and roll are inferred together."""
        p = self.package
        if p is None:
            raise LabcalError(f"certificate {self.certificate_id} is of a three-axis instrument, not a "
                              "package")
        sensors = tuple(Sensor(a, c.b, c.S, math.radians(c.omega_deg), math.radians(c.azimuth_deg))
                        for a, c in ((a, p.coefficients[a]) for a in p.sensors))
        usable = None
        if p.usable_pitch_deg is not None and p.usable_roll_deg is not None:
            usable = (tuple(np.radians(p.usable_pitch_deg)), tuple(np.radians(p.usable_roll_deg)))
        return PackageCalibration(
            p.package, sensors, np.array([np.array(c)[:4, :4] for c in self.fit.covariance]),
            np.array(self.fit.reading_sd), p.k, p.roll_in_use, math.radians(p.roll_sd_deg or 0.0),
            usable)

    def coefficient_covariance(self) -> NDArray:
        """The complete 12×12 covariance of vec(X) (row-major), Type A and B, across channels; a
        package's (4m × 4m for its m sensors) is its fit's, each sensor fitted on its own."""
        if self.package is not None:
            m = len(self.fit.layout.columns)
            cov = np.zeros((4 * m, 4 * m))
            for j, block in enumerate(self.fit.covariance):
                idx = np.arange(4) * m + j
                cov[np.ix_(idx, idx)] = np.array(block)[:4, :4]
            return cov
        parts = self.calibration().uncertainty_parts
        return np.sum([p.matrix[:12, :12] for p in parts], axis=0)

    def to_json(self) -> dict:
        return self.model_dump(mode="json")


SCHEMA_FILE = "schemas/certificate.schema.json"  # in the repository, beside labcal/


def json_schema() -> dict:
    """The JSON Schema (draft 2020-12) of certificate.json, generated from these models: published
    in the repository as `SCHEMA_FILE` (`tools/schemas.py` writes it; a test keeps it
    equal to this), so that a customer's software validates a certificate without labcal. Checks
    that JSON Schema cannot state (a plan's SHA-256 of its text, the digest, array shapes) are
    labcal's own on reading."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema",
            **Certificate.model_json_schema(by_alias=True, mode="validation"),
            "title": f"labcal calibration certificate ({SCHEMA})"}


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
_CUT_TOKEN = re.compile(r"[-+0-9.eE]+|t(r(u)?)?|f(a(l(s)?)?)?|n(u(l)?)?")


def parse_json(text: str, source: str):
    """JSON text, or one line saying why not — naming truncation, the usual way files break."""
    try:
        doc = json.loads(text)
    except RecursionError:
        raise LabcalError(f"{source}: nested more than {MAX_DEPTH} deep; a certificate is not nested like "
                          "that") from None
    except json.JSONDecodeError as exc:
        rest = text.rstrip()[exc.pos:]
        # cut inside a number ("0." or "1e-") or a literal ("tr"): the parser stops at its last character
        # or inside a \uXXXX escape of a non-ASCII character ("\u22")
        cut_escape = exc.msg.startswith("Invalid \\uXXXX escape") and len(rest) < 6
        if not rest or _CUT_TOKEN.fullmatch(rest) or exc.msg.startswith("Unterminated string") or cut_escape:
            raise LabcalError(f"{source}: not valid JSON: the file is truncated (it stops at line "
                              f"{text.rstrip().count(chr(10)) + 1} before the document ends)") from None
        raise LabcalError(f"{source}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    check_depth(doc, source)
    return doc


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


def load_calibration(path: str | Path) -> Calibration:
    """Read the coefficients and their uncertainty from a fit JSON or a certificate; a certificate's
    schema and digest are verified first, so a tampered certificate never converts a voltage."""
    doc = parse_json(read_text(path, "calibration"), str(path))
    if is_certificate(doc):
        return certificate_from_doc(doc, str(path)).calibration()
    return calibration_from_json(doc.get("fit", doc) if isinstance(doc, dict) else doc, path)

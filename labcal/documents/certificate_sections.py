"""The certificate's records of what other parts of labcal computed: the fit's layout,
extensions and replication analysis (`labcal.analysis.fit`, `labcal.analysis.replication`), the
device model's intrinsic parameters, identifiability and F test (`labcal.analysis.device_fit`), and
the uncertainty budget's Type B inputs (`labcal.analysis.budget.TypeBInputs`).

They were untyped dicts; typed, a wrong type or a missing field is refused when a certificate is
sealed or read, the DCC and the report read them by attribute, and the published JSON Schema
(`schemas/certificate.schema.json`) states them. Each is written exactly as the code that computed
it wrote it: signatures are over the canonical JSON, so a certificate issued before these models
must serialise to the same bytes. A field added to a section after certificates were issued
without it is optional and, where the document does not carry it, stays out of the document
(`Recorded`); a field the document carries as null stays null.

The sequencer's settings and a dry run's simulated truth are the run's own records, which the
certificate states as the journal keeps them: their models, and the `Strict` and `Recorded` bases,
are the run metadata's (`labcal.config.run_metadata`).
"""

from __future__ import annotations

from labcal.config.run_metadata import Recorded, Strict


# --- the fit (fit.layout, fit.extensions, fit.replication) -----------------------------------------
class Layout(Strict):
    """How the coefficient arrays are laid out, in words (docs/design.md §5)."""

    rows: list[str]
    columns: list[str]
    units: str


class Extensions(Strict):
    """The terms beyond B and S (temperature, …) with their coefficients, rows in ``names`` order."""

    names: list[str]
    t_ref_c: float
    coefficients: list[list[float]]
    standard_errors: list[list[float]]


class FTestRecord(Strict):
    """An F test of one sensor (`labcal.analysis.replication.FTest.to_json`)."""

    F: float
    df: tuple[int, int]
    critical_95: float
    p_value: float
    significant: bool


class DriftTestRecord(Recorded):
    F: float
    df: tuple[int, int]
    critical_95: float
    p_value: float
    significant: bool
    sigma_drift: float | None = None  # absent: issued before the drift's size was stated


class Replication(Recorded):
    """One sensor's replication analysis (Tripp & Tcheng Table 2): precision and bias, lack of fit
    against the pure error, and drift between replicates."""

    distinct_points: int
    replicates: int
    sigma_prec: float
    sigma_bias: float
    lack_of_fit: FTestRecord
    lack_of_fit_classical: FTestRecord | None = None  # absent: issued before the drift-aware test
    lack_of_fit_drift_robust: FTestRecord | None = None
    drift: dict[str, DriftTestRecord]


# --- the device model (device.intrinsic, device.identifiability, device.misalignment_test) --------
class Estimate(Strict):
    value: float
    u: float


class InterAxisAngle(Strict):
    value_deg: float
    deviation_from_90_arcsec: float
    u_arcsec: float


class Intrinsic(Strict):
    """The instrument's mount-independent parameters: each sensor's sensitivity |s_j| (V/g) and the
    angle between each pair of sensitive axes, with standard uncertainties."""

    sensitivity_v_per_g: dict[str, Estimate]
    inter_axis_angle_deg: dict[str, InterAxisAngle]


class Confounded(Strict):
    """A direction the readings cannot see: misalignments with a combination of coefficients, and a
    mount (y, u in degrees) whose addition separates them, if one does."""

    misalignments: list[str]
    coefficients: dict[str, float]
    description: str
    add_mount: tuple[float, float] | None


class Identifiability(Strict):
    """What the plan's points tell about the device model's parameters (condition None: infinite)."""

    rank: int
    parameters: int
    condition: float | None
    u_arcsec_per_ug_noise: dict[str, float | None]
    confounded: list[str]
    confounded_directions: list[Confounded]
    ill_conditioned: list[str]


class MisalignmentTest(Strict):
    """The F test that judged the device model against the linear one."""

    F: float
    df: tuple[int, int]
    p_value: float
    critical_95: float
    warranted: bool
    denominator: str


# --- the budget's Type B inputs (uncertainty_budget.inputs) ----------------------------------------
class BudgetInputs(Recorded):
    """`labcal.analysis.budget.TypeBInputs` in SI units, half-widths of rectangular distributions
    unless said; zero: not a source here."""

    dmm_reading: float
    dmm_range_v: float
    dmm_noise_v: float | None = None  # absent: issued before the DMM's noise was shown
    dmm_conditions: str | None = None
    output_unit: str | None = None  # the readings' unit where not volts (absent: volts)
    common: list[str] | None = None
    pitch_index: float
    pitch_wobble: float
    roll_index: float
    roll_wobble: float
    mount_repeatability: float
    mount_repeatability_sd: float | None = None  # absent: issued before remount scatter was estimated
    mount_repeatability_dof: int | None = None
    temperature_half_range_k: float
    bias_tempco_v_per_k: float
    sensitivity_tempco_per_k: float
    device_misalignment: dict[str, float]
    # The estimate a plan's device correction took them from; absent: this run's device model
    device_misalignment_source: str | None = None


# --- a plan's device correction --------------------------------------------------------
class DeviceCorrectionRecord(Strict):
    """The calibration device's misalignments a…k were not measured in this run: the plan's
    ``[device_correction]`` held them at an earlier estimate of the device's (its history in the lab
    database, in control when the run started), each value with its U (95 %) as the history states it
    and the standard uncertainty u the budget carries as a Type B input (arcseconds)."""

    device_id: str
    source: str  # the run the estimate came from
    calibrated_utc: str  # when that run calibrated
    value_arcsec: dict[str, float]
    U_arcsec: dict[str, float]
    u_arcsec: dict[str, float]
    statement: str


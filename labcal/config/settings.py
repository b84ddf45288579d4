"""The settings a station file carries besides its devices: how the sequencer settles, orders and
times a run (``[sequencer]``), and what a certificate says and checks (``[certificate]``).

A station file's `[sequencer]` table is a `SequencerSettings`; the command line's options go over
it. The journal keeps the settings a run started with, validated again by these models on resume.
Its `[certificate]` table is a `CertificateSettings`, with the command line's tolerances over it.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from labcal.config.files import one_line
from labcal.errors import LabcalError


class SettleSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tau_s: float = Field(default=0.5, gt=0, description="sensor output time constant")
    noise_v: float = Field(default=20e-6, gt=0, description="noise of one DMM sample, V rms")
    sensitivity_v_per_g: float = Field(default=5.0, gt=0, description="nominal, to size a step in volts")
    samples: int = Field(default=10, ge=4, le=10000, description="samples in the test window = averaged")
    k_sigma: float = Field(default=3.0, gt=0, description="significance of the slope and halves tests")
    off_axis_arcsec: float = Field(default=60.0, ge=0, le=3600, description="how far gravity may sit off "
                                   "the axis a table turns it about (the device's misalignments, the mount): "
                                   "a roll at pitch ±90°, which nominally leaves no transient, leaves this "
                                   "much of the roll's lag")
    leftover: float = Field(default=0.1, gt=0, le=1, description="the transient a window's mean may keep "
                            "after the dead time, in σ/√N (the noise of a reading): 0.1 keeps its bias out "
                            "of the budget (1: the dead time of labcal ≤ 0.9, +2 to +3 µV on average)")
    max_dwell_s: float = Field(default=60.0, gt=0, description="give up on a point after this dwell")
    fixed_dwell_s: float | None = Field(default=None, ge=0,
                                        description="dwell this long and take one window, no test")
    mode: Literal["detect", "model"] = Field(
        default="detect", description="detect: wait out the transient, then test a window; model: fit "
        "the exponential tail (τ pooled over the run's points), waiting like detect until the run's "
        "records rule out a slower tail and whenever the sensor does not follow it")
    pool: Literal["instrument", "type", "none"] = Field(
        default="instrument", description="model settling: whose earlier runs' step records a run starts "
        "with (in the lab database, per station): the same instrument's (serial; a simulated one's "
        "truth), every instrument of `instrument_type`, or none (each run pools only its own)")
    instrument_type: str | None = Field(default=None, min_length=1, description="with pool = \"type\": the "
                                        "type of every instrument calibrated on this station")
    prior: Literal["none", "type", "station"] = Field(
        default="none", description="model settling: a new instrument's pool starts from the step records "
        "of every instrument of `instrument_type` on this station (\"type\") or of every instrument on it "
        "(\"station\"), worth `prior_records` records; each record of the instrument's own earlier runs "
        "replaces one of them. Only where the station's instruments share their time constant and tail")
    prior_records: int = Field(default=640, ge=1, le=100000, description="with prior: how many step records "
                               "the type's or station's records count as in a new instrument's pool")

    @model_validator(mode="after")
    def _type_named(self) -> SettleSettings:
        if (self.pool == "type" or self.prior == "type") and self.instrument_type is None:
            raise ValueError(f'{"pool" if self.pool == "type" else "prior"} = "type" needs instrument_type '
                             "(the instruments' type, as one name)")
        if self.prior != "none" and self.pool != "instrument":
            raise ValueError(f'prior = "{self.prior}" needs pool = "instrument" (a prior is other '
                             "instruments' records, for one instrument's pool)")
        return self


class ThermalGate(BaseModel):
    """Before each mount's points, wait until the instrument's temperature changes by less than
    ``rate_c_per_min`` over ``hold_s`` (the least-squares slope of the temperatures read every
    ``poll_s`` within that span): a warm-up, or the handling of a remount, settles first, so that
    the temperature terms need correct only a slow drift (Tripp & Tcheng §9.2.1, Table 2 footnote b)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    rate_c_per_min: float = Field(default=0.05, gt=0)
    hold_s: float = Field(default=300.0, gt=0, le=86400)
    poll_s: float = Field(default=30.0, gt=0, le=3600, description="time between temperature reads")
    max_wait_s: float = Field(default=7200.0, gt=0, description="then the run goes on, and says so")

    def describe(self) -> str:
        return f"< {self.rate_c_per_min:g} °C/min over {self.hold_s:g} s"


class SequencerSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    settle: SettleSettings = SettleSettings()
    order: Literal["shortest", "plan", "sweep", "random"] = "shortest"
    seed: int = Field(default=0, description="for the random order")
    move_timeout_s: float = Field(default=120.0, gt=0)
    position_tolerance_deg: float = Field(default=0.01, gt=0)
    check_mount: bool = True
    on_failure: Literal["skip", "pause", "abort"] = Field(
        default="skip", description="what to do with a point that does not settle after one retry")
    speed_dps: float = Field(default=20.0, gt=0, description="table speed, for ordering and estimates")
    accel_dps2: float = Field(default=40.0, gt=0)
    thermal_gate: ThermalGate | None = Field(default=None, exclude_if=lambda gate: gate is None)


class CertificateSettings(BaseModel):
    """Who issues, the usage envelope and the tolerances of the conformity statement."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    laboratory: str = Field(default="", description="laboratory name and address, as printed")
    attitude_u95_max_deg: float | None = Field(default=None, gt=0, description="tolerance on the largest "
                                               "95 % expanded uncertainty of pitch and of roll")
    bias_max_v: float | None = Field(default=None, gt=0, description="limit on |B| + U(B) per sensor")
    usage_pitch_deg: tuple[float, float] = (-60.0, 60.0)
    usage_roll_deg: tuple[float, float] = (-180.0, 180.0)
    grid_step_deg: float = Field(default=5.0, gt=0, le=45)
    in_use_samples: int | None = Field(default=None, ge=1, le=1_000_000, description=(
        "samples a reading of the instrument in use averages, for the new-reading row of the budget "
        "(default: as many as the calibration's windows)"))

    @model_validator(mode="after")
    def _envelope(self) -> CertificateSettings:
        (p0, p1), (r0, r1) = self.usage_pitch_deg, self.usage_roll_deg
        if not -90 <= p0 < p1 <= 90:
            raise ValueError(f"usage_pitch_deg [{p0:g}, {p1:g}] must be increasing within -90..90")
        if not -180 <= r0 < r1 <= 180:
            raise ValueError(f"usage_roll_deg [{r0:g}, {r1:g}] must be increasing within -180..180")
        return self

    def overridden(self, source: str, **overrides: object) -> CertificateSettings:
        """These settings with the command line's non-None ``overrides`` over them, validated again
        (a tolerance typed on the command line is checked like one in the file); ``source`` names
        where these settings came from, for the message."""
        data = {**self.model_dump(), **{k: v for k, v in overrides.items() if v is not None}}
        try:
            return CertificateSettings.model_validate(data)
        except ValidationError as exc:
            raise LabcalError(f"{source}: certificate.{one_line(exc, CertificateSettings)}") from None

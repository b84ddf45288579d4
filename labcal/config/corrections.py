"""A plan's device correction: the ``[device_correction]`` table `labcal plan optimize
--device` writes where the calibration device's misalignments are known from its in-control history,
read into a validated model, and written back as TOML."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, Misalignment


class DeviceCorrectionTable(BaseModel):
    """A plan's ``[device_correction]`` (`labcal plan optimize --device`): the calibration device's
    misalignments a…k (Soto Table 1, arcseconds) as its latest in-control estimate states them, which
    a run of the plan corrects the readings' gravity for instead of identifying them by remounting,
    carrying ``u_arcsec`` as the budget's Type B device-misalignment input. ``source`` and
    ``calibrated_utc`` name that estimate (the run it came from, and when)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    device_id: str = Field(min_length=1)
    source: str = Field(min_length=1)
    calibrated_utc: str = Field(min_length=1)
    value_arcsec: dict[str, float]
    U_arcsec: dict[str, float]
    u_arcsec: dict[str, float]
    # The correction's own u (the history's, aged to the plan's writing) where ``u_arcsec`` is larger:
    # the budget's u covers the change a run of the plan would miss (`analysis.correction_check`); the
    # run's check judges a change against this one. Absent (plans written before): ``u_arcsec``.
    u_history_arcsec: dict[str, float] | None = None

    @field_validator("value_arcsec", "U_arcsec", "u_arcsec", "u_history_arcsec")
    @classmethod
    def _six(cls, values: dict[str, float] | None) -> dict[str, float] | None:
        if values is None:
            return None
        if set(values) != set(MISALIGNMENT_NAMES):
            raise ValueError(f"needs exactly the misalignments {', '.join(MISALIGNMENT_NAMES)}")
        return {n: values[n] for n in MISALIGNMENT_NAMES}

    @field_validator("U_arcsec", "u_arcsec", "u_history_arcsec")
    @classmethod
    def _not_negative(cls, values: dict[str, float] | None) -> dict[str, float] | None:
        if values is not None and any(v < 0 for v in values.values()):
            raise ValueError("an uncertainty cannot be negative")
        return values

    def misalignment(self) -> Misalignment:
        """The values as the kinematic model takes them (radians)."""
        return Misalignment(**{n: v * ARCSEC for n, v in self.value_arcsec.items()})

    def u_rad(self) -> dict[str, float]:
        """Each one's standard uncertainty (radians): the budget's device-misalignment input."""
        return {n: v * ARCSEC for n, v in self.u_arcsec.items()}

    def u_history_rad(self) -> dict[str, float]:
        """The correction's own standard uncertainty (radians): what a run's check judges a change by."""
        own = self.u_arcsec if self.u_history_arcsec is None else self.u_history_arcsec
        return {n: v * ARCSEC for n, v in own.items()}

    def describe(self) -> str:
        """The estimate in words: 'device D's estimate from run R (calibrated T)'."""
        return f"device {self.device_id}'s estimate from run {self.source} (calibrated {self.calibrated_utc})"

    def model_note(self) -> str:
        """Which model a run of the plan fits, and why (fit.json's first note, the certificate's
        statement)."""
        return ("linear model on the gravity the calibration device's misalignments a…k give, held at "
                f"{self.describe()} (the plan's device correction): this run's mounts do not identify "
                "them, and their uncertainty is a Type B input of the budget")

    def statement(self) -> str:
        """What the certificate says of the correction: not measured here, corrected from which estimate,
        with each value and its u."""
        values = "; ".join(f"{n} = {self.value_arcsec[n]:.2f}″ (u = {self.u_arcsec[n]:.2f}″)"
                           for n in MISALIGNMENT_NAMES)
        checked = "" if self.u_history_arcsec is None else (
            " This run checked them: none moved by more than its test detects (a change of 3 u with 95 % "
            "probability); each u is the larger of the estimate's own (aged) and a third of that change.")
        return (f"The calibration device's misalignments were not measured in this run: they were corrected "
                f"for from {self.describe()}: {values}; their standard uncertainties enter the uncertainty "
                "budget as the Type B row \"device misalignment estimates\"." + checked)


"""The run's settings: how the sequencer settles, orders and times a run.

A station file's `[sequencer]` table is a `SequencerSettings`; the command line's options go over
it. The journal keeps the settings a run started with, validated again by these models on resume.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class SettleSettings(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tau_s: float = Field(default=0.5, gt=0, description="sensor output time constant")
    noise_v: float = Field(default=20e-6, gt=0, description="noise of one DMM sample, V rms")
    sensitivity_v_per_g: float = Field(default=5.0, gt=0, description="nominal, to size a step in volts")
    samples: int = Field(default=10, ge=4, le=10000, description="samples in the test window = averaged")
    k_sigma: float = Field(default=3.0, gt=0, description="significance of the slope and halves tests")
    max_dwell_s: float = Field(default=60.0, gt=0, description="give up on a point after this dwell")
    fixed_dwell_s: float | None = Field(default=None, ge=0,
                                        description="dwell this long and take one window, no test")


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

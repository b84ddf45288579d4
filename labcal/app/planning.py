"""Planning a calibration before anything moves: the use cases behind `labcal plan optimize` and the
instrument-package verdict of `labcal plan audit --station`.

`optimize_plan` chooses the quickest plan whose predicted attitude U95 meets a target, on the bench
a station file (or the simulated rig) describes: its Type B inputs, its timing model (the one
`labcal run --dry-run` uses, the tour of ``--order shortest`` included) and, with a device whose
history knows its misalignments, the correction that may replace remounts. The command line only
parses and prints; the search itself is `labcal.analysis.optimize`.

The libraries the prediction needs (numpy, the optimizer, the station's assembly) are imported in the
functions that use them: `labcal --help` imports this module for `CORRECTION_NOTE` and must not pay
for them.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.config.plans import correction_toml, load_plan, plan_toml
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    import numpy as np

    from labcal.analysis import kinematics, optimize, packages
    from labcal.analysis import plan as analysis_plan
    from labcal.analysis.optimize import Bench, DeviceCorrection, Evaluated
    from labcal.analysis.plan import Plan
    from labcal.bench import setup as bench_setup
    from labcal.config import corrections, emulation, lab, snapshot
    from labcal.config import settings as config_settings
    from labcal.config import station as config_station
    from labcal.config.settings import SequencerSettings
    from labcal.documents import device_history, uncertainty
    from labcal.run import estimate as run_estimate
    from labcal.run import sequencer
else:
    analysis_plan = lazy("labcal.analysis.plan")  # start-up without numpy, pydantic
    bench_setup = lazy("labcal.bench.setup")  # start-up without scipy, numpy, pydantic
    config_settings = lazy("labcal.config.settings")  # start-up without pydantic
    config_station = lazy("labcal.config.station")  # start-up without scipy, numpy, pydantic
    corrections = lazy("labcal.config.corrections")  # start-up without numpy, pydantic
    device_history = lazy("labcal.documents.device_history")  # start-up without scipy, numpy, pydantic
    emulation = lazy("labcal.config.emulation")  # start-up without scipy, numpy, pydantic
    kinematics = lazy("labcal.analysis.kinematics")  # start-up without numpy
    lab = lazy("labcal.config.lab")  # start-up without pydantic
    np = lazy("numpy")  # start-up without numpy
    optimize = lazy("labcal.analysis.optimize")  # start-up without scipy, numpy, pydantic
    packages = lazy("labcal.analysis.packages")  # start-up without scipy, numpy
    run_estimate = lazy("labcal.run.estimate")  # start-up without scipy, numpy, pydantic, …
    sequencer = lazy("labcal.run.sequencer")  # start-up without scipy, numpy, pydantic, …
    snapshot = lazy("labcal.config.snapshot")  # start-up without scipy, numpy, pydantic
    uncertainty = lazy("labcal.documents.uncertainty")  # start-up without scipy, numpy, pydantic

CORRECTION_NOTE = ("labcal run checks that the station's calibration device is that device and its history "
                   "is still in control, fits with the misalignments held at the estimate's values, carries "
                   "their u in the budget and states the correction on the certificate")


def type_b(section, temperature_half_range_k: float):
    """The budget's Type B inputs from a station's (or the simulator's) inputs, before a run: the
    mapping a finished run's certificate makes (`labcal.documents.uncertainty.section_type_b`), for
    outputs in volts, with the temperature range given instead of observed."""
    return uncertainty.section_type_b(section, "V", temperature_half_range_k)


def planning_bench(station: str | None):
    """The prediction's bench, the station's timing model and its sequencer settings: the simulated
    rig of `labcal run --sim` (its instrument, its Type B inputs as a dry run's certificate states them,
    its lab's temperature swing as the half-range), or a station file's (nominal instrument from its
    [sequencer.settle], its [uncertainty] and [certificate] envelope, temperature not predicted)."""
    if station is None:
        rig = emulation.RigConfig()
        setup = bench_setup.sim_station(None, rig.seed)
        settings = config_settings.SequencerSettings(
            settle=setup.settle, speed_dps=rig.speed_dps, accel_dps2=rig.accel_dps2
        )
        section = config_station.CertificateSection().model_copy(update={
            "uncertainty": snapshot.simulator_inputs(rig.model_dump(), setup.settle.samples)})
        inst = rig.instrument
        envelope = config_settings.CertificateSettings()
        bench = optimize.Bench(inst.X, inst.noise_v, type_b(section, rig.lab_temp_swing_c),
                               envelope.usage_pitch_deg, envelope.usage_roll_deg, envelope.grid_step_deg,
                               envelope.in_use_samples)
        return bench, setup.timing, settings
    config, _ = config_station.load_station(station)
    section = config_station.load_certificate_section(station)
    s = config.sequencer.settle
    settings = config.sequencer.model_copy(update={
        "speed_dps": min(config.pitch.speed_dps, config.roll.speed_dps),
        "accel_dps2": min(config.pitch.accel_dps2, config.roll.accel_dps2)})
    X = np.vstack([np.zeros(3), s.sensitivity_v_per_g * np.eye(3)])
    envelope = section.certificate
    bench = optimize.Bench(
        X,
        s.noise_v,
        type_b(section, 0.0),
        envelope.usage_pitch_deg,
        envelope.usage_roll_deg,
        envelope.grid_step_deg,
        envelope.in_use_samples,
    )
    return bench, bench_setup.station_timing(config), settings


def device_correction(device_id: str, db, said: Callable[[str], None] | None = None):
    """The device's misalignments where its history knows them (`device_history.correction_for`):
    (correction, "") or (None, why). ``said`` hears the line saying the lab could not be reached."""
    return device_history.correction_for(device_id, db, said=said)


def optimized_plan_toml(plan, e, correction, target_deg: float, reference,
                        budget_u: dict[str, float] | None = None) -> str:
    """The plan file: the plan, what was predicted for it, and the device corrections it relies on."""
    head = [
        f"# Written by labcal plan optimize --target-attitude-u95-deg {target_deg:g}.",
        f"# Run it with --samples {e.candidate.samples} (the measurement window it was planned with).",
        f"# Predicted: rig time {e.rig_time_s:.0f} s ({e.rig_time_s / reference.rig_time_s:.3f}× "
        f"four-mount-64's {reference.rig_time_s:.0f} s), attitude U95 {math.degrees(e.u95_rad):.5f}° "
        f"(pitch {e.u95_pitch_rad / kinematics.ARCSEC:.2f}″, "
        f"roll {e.u95_roll_rad / kinematics.ARCSEC:.2f}″) over the usage envelope.",
    ]
    body = plan_toml(plan)
    if correction is None:
        return "\n".join(head) + "\n" + body
    head.append(f"# It relies on the device correction below: {CORRECTION_NOTE}.")
    table = corrections.DeviceCorrectionTable(
        device_id=correction.device_id,
        source=correction.source,
        calibrated_utc=correction.calibrated_utc,
        value_arcsec={n: correction.value_rad[n] / kinematics.ARCSEC for n in kinematics.MISALIGNMENT_NAMES},
        U_arcsec={n: correction.U_rad[n] / kinematics.ARCSEC for n in kinematics.MISALIGNMENT_NAMES},
        u_arcsec={
            n: (budget_u or correction.u_rad)[n] / kinematics.ARCSEC for n in kinematics.MISALIGNMENT_NAMES
        },
        u_history_arcsec={n: correction.u_rad[n] / kinematics.ARCSEC for n in kinematics.MISALIGNMENT_NAMES},
    )
    return "\n".join(head) + "\n" + body + "\n" + correction_toml(table)


@dataclass(frozen=True)
class OptimizedPlan:
    """What `optimize_plan` chose, against four-mount-64 on the same bench."""

    plan: Plan
    chosen: Evaluated
    reference: Evaluated  # four-mount-64 with the station's window
    found: list[Evaluated]  # every candidate evaluated (the frontier is drawn from them)
    correction: DeviceCorrection | None  # the device's correction the plan relies on; None: it remounts
    budget_u: dict[str, float] | None  # the correction's u its run carries, where it relies on one
    why: str  # why a device's history could not replace remounts ("" where it could, or none was named)
    target_rad: float


def rig_time_of(settings: SequencerSettings, timing) -> Callable[[Any], float]:
    """A candidate's predicted rig time on the station's timing model (`labcal run --dry-run`), the tour
    of `--order shortest` included; the tour is computed once per set of mounts and points."""
    steps: dict = {}

    def rig_time(c) -> float:
        plan = analysis_plan.Plan(name="candidate", mounts=list(c.mounts), points=list(c.points))
        window = settings.settle.model_copy(update={"samples": c.samples})
        run = settings.model_copy(update={"settle": window})
        if (c.mounts, c.points) not in steps:  # the tour does not depend on the window
            steps[(c.mounts, c.points)] = sequencer.schedule(plan, run)
        return run_estimate.estimate(plan, run, timing, steps[(c.mounts, c.points)]).total_s

    return rig_time


def optimize_plan(target_u95_deg: float, station: str | None = None, device: str | None = None, db=None,
                  out: str | None = None, said: Callable[[str], None] | None = None) -> OptimizedPlan:
    """The quickest plan whose predicted attitude U95 is at most ``target_u95_deg`` over the usage
    envelope, written to ``out`` (never over an existing file: a plan file may be the record of a
    past calibration). ``device``: a calibration device whose in-control history may replace remounts."""
    if out and os.path.lexists(out):
        raise LabcalError(f"{out}: exists; choose another --out (or delete it first)")
    bench: Bench
    bench, timing, settings = planning_bench(station)
    correction, why = (None, "") if device is None else device_correction(device, db, said)
    rig_time = rig_time_of(settings, timing)
    fm64, _ = load_plan("four-mount-64")
    ref = optimize.Candidate(tuple(fm64.mounts), tuple(fm64.points), settings.settle.samples)
    reference = optimize.evaluate(ref, bench, None, rig_time(ref))
    assert reference is not None  # four mounts identify a…k
    target = math.radians(target_u95_deg)
    found = optimize.search(bench, correction, rig_time)
    chosen = optimize.choose(found, bench, correction, target)
    c = chosen.candidate
    relies = not chosen.identified  # (`search` offers such a plan only with a correction)
    # the u its run carries: the correction's, or a third of the change the run's check detects (95 %)
    budget_u = optimize.corrected_u(c, bench, correction) if relies and correction is not None else None
    plan = analysis_plan.Plan(name=Path(out).stem if out else "optimized",
                              description=f"optimized for attitude U95 ≤ {target_u95_deg:g}° "
                                          f"(labcal plan optimize, {c.samples} samples per point)",
                              mounts=list(c.mounts), points=list(c.points))
    relied = correction if relies else None
    if out:
        try:
            with open(out, "x", encoding="utf-8") as f:
                f.write(optimized_plan_toml(plan, chosen, relied, target_u95_deg, reference, budget_u))
        except OSError as exc:
            raise LabcalError(f"{out}: cannot write plan ({exc.strerror})") from None
    return OptimizedPlan(plan, chosen, reference, found, relied, budget_u, why, target)


def package_verdict(station: str) -> dict:
    """The station's instrument package, how it obtains roll in use, and why it cannot be used over the
    certificate's usage envelope (None when it can). Every plan labcal accepts determines [1, gᵀ] of
    each sensor (rank 4), hence every sensor's b, S, Ω and A (Tripp eq. 8)."""
    config, _ = config_station.load_station(station)
    envelope = lab.certificate_settings(config.certificate, station)  # as labcal run judges it
    inst = config.instrument
    roll = inst.roll_source
    assert roll is not None  # required of a single axis by the station file's validation
    return {
        "package": inst.package,
        "axes": list(packages.PACKAGES[inst.package]),
        "roll_in_use": roll,
        "roll_sd_deg": inst.roll_sd_deg,
        "usage_pitch_deg": list(envelope.usage_pitch_deg),
        "usage_roll_deg": list(envelope.usage_roll_deg),
        "problem": packages.package_problem(
            inst.package, roll, envelope.usage_pitch_deg, envelope.usage_roll_deg
        ),
    }

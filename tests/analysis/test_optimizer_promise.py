"""The optimizer keeps its promise: the certificate a run of the chosen plan delivers states a U95 within
the target X in at least 95 % of the runs.

The prediction is checked against what it did not compute: each run is simulated on the bench with its
realistic errors (`labcal.sim.direct.simulate_readings`: the instrument's noise per sample over each
window, a new table's index errors and wobble per run, the plate seated anew at each mounting, the
instrument's drift over the run, the lab's temperature ±0.15 K about its mean through the instrument's
temperature coefficients, and for a corrected plan the device's true misalignments drawn about
the correction with the correction's own u), fitted as `labcal run` fits it and budgeted as its
certificate is (`labcal.documents.uncertainty.budget_view`, the lack-of-fit test and its fall-back
included), and its stated U95 is the largest over the certificate's envelope grid. Fixed seeds.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from labcal.analysis import optimize
from labcal.analysis.budget import TypeBInputs, propagate
from labcal.analysis.device_fit import preferred_fit
from labcal.analysis.fit import fit_readings, reference_temperature
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble, Misalignment, gravity
from labcal.analysis.models import Model
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.app.planning import planning_bench
from labcal.config.plans import load_plan
from labcal.documents.uncertainty import budget_view, device_misalignment_u
from labcal.run.estimate import estimate
from labcal.run.sequencer import schedule
from labcal.sim.coverage import Bench as SimBench
from labcal.sim.coverage import coverage
from labcal.sim.direct import simulate_readings

SIM = SimBench()  # the simulated rig, its plate seated within 1″ (σ) at each mounting, stated so
RUNS = 60


def bench() -> tuple[optimize.Bench, object, object]:
    """The optimizer's bench for the simulated rig with the seating it states (the temperature range
    and DMM terms of `labcal plan optimize`'s, the tables' and the seating's of the simulated bench)."""
    planning, timing, settings = planning_bench(None)
    s = SIM.type_b()
    type_b = replace(planning.type_b, mount_repeatability=s.mount_repeatability)
    return replace(planning, type_b=type_b), timing, settings


def chosen(factor: float, correction: optimize.DeviceCorrection | None) -> tuple[optimize.Evaluated, float]:
    """The plan the optimizer chooses for X = ``factor`` × four-mount-64's predicted U95, and X (rad)."""
    b, timing, settings = bench()
    steps: dict = {}

    def rig_time(c: optimize.Candidate) -> float:  # the station's timing model, as `plan optimize` times
        plan = Plan(name="candidate", mounts=list(c.mounts), points=list(c.points))
        window = settings.settle.model_copy(update={"samples": c.samples})
        run = settings.model_copy(update={"settle": window})
        if (c.mounts, c.points) not in steps:
            steps[(c.mounts, c.points)] = schedule(plan, run)
        return estimate(plan, run, timing, steps[(c.mounts, c.points)]).total_s

    fm64, _ = load_plan("four-mount-64")
    reference = optimize.Candidate(tuple(fm64.mounts), tuple(fm64.points), settings.settle.samples)
    ref = optimize.evaluate(reference, b, None, 0.0)
    assert ref is not None
    target = factor * ref.u95_rad
    return optimize.choose(optimize.search(b, correction, rig_time), b, correction, target), target


def delivered(e: optimize.Evaluated, correction: optimize.DeviceCorrection | None, runs: int,
              first_seed: int) -> np.ndarray:
    """The worst attitude U95 (rad) the certificates of ``runs`` simulated runs of ``e``'s plan state."""
    b, _, _ = bench()
    c = e.candidate
    plan = Plan(name="chosen", mounts=list(c.mounts), points=list(c.points))
    rig = SIM.rig
    truth, device = rig.instrument, rig.device
    effects = replace(SIM.effects, samples=c.samples)
    pitch, roll = optimize.envelope_attitudes(b)
    budget_u = None if e.identified or correction is None else optimize.corrected_u(c, b, correction)
    rng = np.random.default_rng([first_seed, 0x9A0])
    stated = []
    for seed in range(first_seed, first_seed + runs):
        if correction is None or e.identified:
            true_mis = device.misalignment()
        else:  # the device as the correction knows it, within the correction's own u
            true_mis = Misalignment(**{n: correction.value_rad[n] + rng.normal(0.0, correction.u_rad[n])
                                       for n in MISALIGNMENT_NAMES})
        readings = simulate_readings(plan, truth, true_mis,
                                     IndexWobble(device.index_arcsec, device.wobble_arcsec, seed),
                                     truth.noise_v, seed, effects)
        readings = warmed(readings, true_mis, seed)
        if budget_u is None:  # as `labcal run` fits a plan that identifies the device
            fit = fit_readings(readings)
            model, _ = preferred_fit(readings, fit, SIM.angle_errors())
            inputs = replace(observed(b, readings), device_misalignment=device_misalignment_u(model))
        else:  # held at the correction, its u the plan's
            assert correction is not None
            fit = fit_readings(readings, Model(t_ref=reference_temperature(readings),
                                               device=Misalignment(**correction.value_rad)))
            model = None
            inputs = replace(observed(b, readings), device_misalignment=budget_u,
                             device_misalignment_source="the plan's device correction")
        view = budget_view(readings, fit, inputs, model)
        stated.append(float(np.nanmax(propagate(view.cal, view.rows, pitch, roll).U)))
    return np.array(stated)


def warmed(readings: Readings, misalignment: Misalignment, seed: int) -> Readings:
    """The readings with the lab's temperature moving ±0.15 K over the run (a phase per seed), each
    reading moved by the true instrument's temperature coefficients (bias, and sensitivity times the
    gravity it reads), as the simulated rig's instrument does."""
    truth = SIM.rig.instrument
    k = len(readings.volts)
    temp = 20.0 + 0.15 * np.sin(2 * np.pi * (np.arange(k) / k + seed / 7.0))
    g = gravity(*(np.radians(a) for a in (readings.pitch_deg, readings.roll_deg, readings.y_deg,
                                          readings.u_deg)), misalignment)
    shift = (temp - 20.0)[:, None] * (np.asarray(truth.tc_bias_v_per_c)
                                      + np.asarray(truth.tc_scale_per_c) * (g @ np.asarray(truth.S)))
    return replace(readings, volts=readings.volts + shift, temp_c=temp)


def observed(b: optimize.Bench, readings: Readings) -> TypeBInputs:
    """The run's Type B inputs: the temperature's half-range the run observed, as a certificate's."""
    assert readings.temp_c is not None
    return replace(b.type_b, temperature_half_range_k=float(np.ptp(readings.temp_c)) / 2)


def device_correction() -> optimize.DeviceCorrection:
    """The simulated device as two four-mount-64 sittings of other seeds know it (their mean, each u
    the larger of the two estimates' U/2), as `device_history.correction_for` would carry it."""
    from labcal.analysis.device_fit import fit_device

    rig = SIM.rig
    truth, device = rig.instrument, rig.device
    fm64, _ = load_plan("four-mount-64")
    docs = []
    for seed in (71, 72):
        readings = simulate_readings(fm64, truth, device.misalignment(),
                                     IndexWobble(device.index_arcsec, device.wobble_arcsec, seed),
                                     truth.noise_v / math.sqrt(10), seed)
        docs.append(fit_device(readings, angle_errors=SIM.angle_errors()).to_json()["misalignments"])
    value = {n: float(np.mean([d[n]["value_arcsec"] for d in docs])) * ARCSEC for n in MISALIGNMENT_NAMES}
    u = {n: max(d[n]["U_arcsec"] for d in docs) / 2 * ARCSEC for n in MISALIGNMENT_NAMES}
    return optimize.DeviceCorrection("SIMULATED", "sittings 71 and 72", value, u)


def within(stated: np.ndarray, target: float) -> float:
    return float(np.mean(stated <= target))


@pytest.mark.slow
def test_the_plan_chosen_for_one_and_a_half_times_four_mount_64_states_within_x_in_95_percent_of_runs():
    """X = 1.5 × four-mount-64's predicted U95: the chosen plan (four mounts: a corrected plan's device
    row alone exceeds X) is run 60 times; at least 95 % of its certificates state U95 ≤ X, and the
    prediction is no loose bound: the runs' 95th percentile is within 10 % of it (the prediction takes
    each channel's scatter at its 0.95^(1/3) quantile, a few per cent above the joint 95th percentile
    for these degrees of freedom)."""
    e, target = chosen(1.5, None)
    stated = delivered(e, None, RUNS, 5000)
    share = within(stated, target)
    print(f"X = 1.5 × four-mount-64: {len(e.candidate.mounts)} mounts × {len(e.candidate.points)} points, "
          f"{e.candidate.samples} samples: certificates within X in {100 * share:.1f} % of {RUNS} runs "
          f"(target ≥ 95 %); their 95th percentile {np.quantile(stated, 0.95) / e.u95_rad:.3f}× the "
          "prediction (target 0.9–1)")
    assert share >= 0.95
    assert np.quantile(stated, 0.95) / e.u95_rad > 0.9


@pytest.mark.slow
def test_a_corrected_plan_states_within_x_in_95_percent_of_runs():
    """A target loose enough that relying on the device's correction pays (6 × four-mount-64's U95):
    the corrected plan chosen is run 60 times on a device drawn about the correction with its u; at
    least 95 % of its certificates state U95 ≤ X."""
    correction = device_correction()
    e, target = chosen(6.0, correction)
    assert not e.identified  # it relies on the correction
    stated = delivered(e, correction, RUNS, 6000)
    share = within(stated, target)
    print(f"X = 6 × four-mount-64, corrected plan: {len(e.candidate.mounts)} mounts × "
          f"{len(e.candidate.points)} points, {e.candidate.samples} samples: certificates within X in "
          f"{100 * share:.1f} % of {RUNS} runs (target ≥ 95 %); median stated/predicted "
          f"{np.median(stated) / e.u95_rad:.3f}")
    assert share >= 0.95


@pytest.mark.slow(seconds=40)
def test_the_chosen_plans_certificates_cover_new_readings_in_use_on_both_sides():
    """The plan the optimizer chooses for X = 1.5 × four-mount-64 (it identifies the device: no
    correction) is calibrated 600 times on the simulated bench with its realistic errors (noise per
    sample, the tables' index errors and wobble drawn afresh, the plate seated anew at each mounting,
    the bias drift over the run), each followed by 5 new readings in use. Its certificates' U95 must
    cover 95 ± 2 % of the errors with RMS(error / U95) 0.45–0.6, as the default plan's do
    (test_attitude_coverage): the optimizer's plans are budgeted by the same rule, with fewer points
    and fewer degrees of freedom, which is where a rule that holds for 64 points could fail. With 600
    calibrations the binomial standard error of a 95 % coverage is 0.9 % at worst (the readings of one
    calibration share its coefficients' error), under half the ±2 % band."""
    e, _ = chosen(1.5, None)
    c = e.candidate
    plan = Plan(name="chosen", mounts=list(c.mounts), points=list(c.points))
    sim = replace(SIM, effects=replace(SIM.effects, samples=c.samples))
    result = coverage(plan, sim, 600, 5, first_seed=5000)
    for angle, covered, rms in zip(("pitch", "roll"), result.covered, result.rms_ratio, strict=True):
        print(f"the chosen plan ({len(c.mounts)} mounts × {len(c.points)} points, {c.samples} samples): "
              f"{angle} coverage {covered:.3f} (target 0.95 ± 0.02), RMS(error/U95) {rms:.3f} "
              f"(target 0.45–0.6), over {result.readings} readings")
        assert 0.93 <= covered <= 0.97, (angle, covered)
        assert 0.45 <= rms <= 0.6, (angle, rms)

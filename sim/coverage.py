"""Does the certificate's U95 cover what the instrument does in use? Calibrate on the simulated bench,
then measure with the calibrated instrument, many times over (JCGM 101 in spirit: the whole chain,
not its linearisation).

One trial is one calibration and its use: a new table (index errors and wobble drawn afresh, at the
rig's amplitudes), the device's misalignments, the plate seated anew at each mounting, the
instrument's per-sample noise over each window and its drift over the run (`labcal.sim.direct`); the
fit and budget a certificate of those readings states (`labcal.store.exports.run_fits`' model choice,
`labcal.documents.uncertainty.budget_view`); then new readings of the instrument in use at random
attitudes of the usage envelope — the true instrument at the true attitude, each reading the mean of
the samples the certificate assumes — turned into pitch and roll by the sphere estimator, as
`labcal attitude --cert` does. The error of each against the U95 the certificate states for that
attitude gives the coverage (a 95 % interval should hold 95 % of them) and RMS(error / U95) (a normal
error within U95 = 1.96 u gives 1/1.96 = 0.51; a U95 three times too large gives 0.17).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from labcal.analysis.attitude import LOCAL_GRAVITY_U, sphere_least_squares
from labcal.analysis.attitude import Calibration as AttitudeCalibration
from labcal.analysis.budget import Calibration, Source, TypeBInputs, propagate
from labcal.analysis.device_fit import AngleErrors, DeviceFit, preferred_fit
from labcal.analysis.fit import Fit, fit_readings
from labcal.analysis.kinematics import ARCSEC, IndexWobble, gravity
from labcal.analysis.lack_of_fit import LackOfFit
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.config.emulation import RigConfig
from labcal.documents.uncertainty import budget_view, device_misalignment_u
from labcal.sim.direct import BenchEffects, simulate_readings

SQRT3 = math.sqrt(3.0)


@dataclass(frozen=True)
class Bench:
    """The simulated bench of a coverage study: the rig (instrument, device, table amplitudes), the
    effects beyond the plain simulation, and what the station file states to the budget."""

    rig: RigConfig = field(default_factory=RigConfig)
    # four-mount-64 on the simulated rig: 1927 s of rig time for 64 points, remounts included (30 s a point)
    effects: BenchEffects = BenchEffects(samples=10, mount_repeat_arcsec=1.0, point_s=30.0)
    # what the certificate is told; None: the rig's own sizes (the station file states them truly)
    stated_index_arcsec: float | None = None
    stated_wobble_arcsec: float | None = None
    stated_mount_repeat_arcsec: float | None = None

    def type_b(self) -> TypeBInputs:
        """The station's Type B inputs as a dry run's certificate states them: the tables' amplitudes
        as ± half-widths, the plate's seating σ as the rectangular half-width of equal variance."""
        d = self.rig.device
        index = (d.index_arcsec if self.stated_index_arcsec is None else self.stated_index_arcsec) * ARCSEC
        wobble = (d.wobble_arcsec if self.stated_wobble_arcsec is None
                  else self.stated_wobble_arcsec) * ARCSEC
        mount = self.effects.mount_repeat_arcsec if self.stated_mount_repeat_arcsec is None else \
            self.stated_mount_repeat_arcsec
        return TypeBInputs(pitch_index=index, pitch_wobble=wobble, roll_index=index, roll_wobble=wobble,
                           mount_repeatability=SQRT3 * mount * ARCSEC)

    def angle_errors(self) -> AngleErrors:
        b = self.type_b()
        return AngleErrors(b.pitch_index, b.pitch_wobble, b.roll_index, b.roll_wobble)


@dataclass(frozen=True)
class Calibrated:
    """One simulated calibration: its readings, fits, budget view and rows."""

    readings: Readings
    fit: Fit
    device: DeviceFit | None
    cal: Calibration
    rows: list[Source]
    check: LackOfFit | None  # the lack-of-fit and drift tests the certificate states


def calibrate(plan: Plan, bench: Bench, seed: int, in_use_samples: int | None = None,
              windows: bool = True) -> Calibrated:
    """One calibration of the plan on a new table (seed), fitted and budgeted as a certificate is;
    without ``windows`` the readings do not carry their windows' scatter (the budget then takes the
    fit's residual for the new reading and the coefficients' Type A, as certificates did before)."""
    d, truth = bench.rig.device, bench.rig.instrument
    table = IndexWobble(d.index_arcsec, d.wobble_arcsec, seed)
    readings = simulate_readings(plan, truth, d.misalignment(), table, truth.noise_v, seed, bench.effects)
    if not windows:
        readings = replace(readings, window_sd=None, window_n=None)
    fit = fit_readings(readings)
    device, _ = preferred_fit(readings, fit, bench.angle_errors())
    inputs = replace(bench.type_b(), device_misalignment=device_misalignment_u(device))
    view = budget_view(readings, fit, inputs, device, in_use_samples)
    return Calibrated(readings, fit, device, view.cal, view.rows, view.check)


def in_use(calibrated: Calibrated, bench: Bench, n: int, samples: int, rng: np.random.Generator
           ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``n`` new readings of the true instrument, each the mean of ``samples`` samples, at random
    attitudes of the default usage envelope (pitch ±60°, any roll): the attitude errors of the sphere
    estimator with the calibrated coefficients and the U95 the budget states there (both n×2, rad)."""
    truth, cal = bench.rig.instrument, calibrated.cal
    pitch, roll = np.radians(rng.uniform(-60, 60, n)), np.radians(rng.uniform(-180, 180, n))
    volts = truth.static_volts(gravity(pitch, roll, 0.0, 0.0)) + \
        rng.normal(0.0, truth.noise_v / math.sqrt(samples), (n, 3))
    weighting = cal.covariance if cal.estimator_covariance is None else cal.estimator_covariance
    estimator = AttitudeCalibration(cal.X, weighting, np.sqrt(cal.reading_var), int(cal.dof[0]))
    att = sphere_least_squares(estimator, volts, LOCAL_GRAVITY_U)
    error = np.column_stack([att.pitch - pitch, np.angle(np.exp(1j * (att.roll - roll)))])
    return error, propagate(cal, calibrated.rows, pitch, roll).U


@dataclass(frozen=True)
class Coverage:
    covered: NDArray[np.float64]  # (2,) pitch, roll: fraction of errors within the stated U95
    rms_ratio: NDArray[np.float64]  # (2,) RMS(error / U95)
    readings: int  # new readings in all
    U95_median_arcsec: NDArray[np.float64]  # (2,) the stated U95, median over the readings


def coverage(plan: Plan, bench: Bench, trials: int, per_trial: int, first_seed: int = 0,
             in_use_samples: int | None = None, windows: bool = True) -> Coverage:
    """Coverage of the certificate's U95 over ``trials`` calibrations × ``per_trial`` new readings,
    each averaging ``in_use_samples`` samples (None: the calibration's window); ``windows``: as in
    `calibrate`."""
    samples = in_use_samples or max(bench.effects.samples, 1)
    rng = np.random.default_rng([first_seed, 0xC0FE])
    errors, Us = [], []
    for seed in range(first_seed, first_seed + trials):
        calibrated = calibrate(plan, bench, seed, in_use_samples, windows)
        e, U = in_use(calibrated, bench, per_trial, samples, rng)
        errors.append(e)
        Us.append(U)
    e, U = np.concatenate(errors), np.concatenate(Us)
    return Coverage(np.mean(np.abs(e) <= U, axis=0), np.sqrt(np.mean((e / U) ** 2, axis=0)), len(e),
                    np.median(U, axis=0) / ARCSEC)


def flagged(plan: Plan, bench: Bench, trials: int, first_seed: int = 0) -> tuple[float, float]:
    """The fraction of ``trials`` calibrations on ``bench`` whose lack-of-fit test, and whose drift
    test, is significant: the false-alarm rate on a clean bench stated truly, the power on one with an
    effect the model or the station's statement leaves out."""
    checks = [calibrate(plan, bench, seed).check for seed in range(first_seed, first_seed + trials)]
    return (float(np.mean([c is not None and c.significant for c in checks])),
            float(np.mean([c is not None and c.drift_significant for c in checks])))


def with_effect(effect: str, bench: Bench | None = None) -> Bench:
    """The bench with one effect the model or the station's statement leaves out, at the size a
    lack-of-fit test must see (the tables at 3× their stated error; an unstated 3″ seating scatter on
    top of the stated one; a 60 µg/h bias drift; a 50 µg/g² nonlinearity), or the bench itself
    ("clean"). The instrument's sensitivities (~5 V/g) turn µg into volts."""
    bench = bench or Bench()
    rig, effects = bench.rig, bench.effects
    volts_per_g = np.abs(np.diag(np.asarray(rig.instrument.S)))
    if effect == "clean":
        return bench
    if effect == "tables 3×":
        d = rig.device
        worse = rig.model_copy(update={"device": d.model_copy(update={
            "index_arcsec": 3 * d.index_arcsec, "wobble_arcsec": 3 * d.wobble_arcsec})})
        return replace(bench, rig=worse, stated_index_arcsec=d.index_arcsec,
                       stated_wobble_arcsec=d.wobble_arcsec)
    if effect == "seating +3″":
        seat = math.hypot(effects.mount_repeat_arcsec, 3.0)
        return replace(bench, effects=replace(effects, mount_repeat_arcsec=seat),
                       stated_mount_repeat_arcsec=effects.mount_repeat_arcsec)
    if effect == "drift 60 µg/h":
        inst = rig.instrument.model_copy(update={"drift_v_per_h": (60e-6 * volts_per_g).tolist()})
        return replace(bench, rig=rig.model_copy(update={"instrument": inst}))
    if effect == "nonlinearity 50 µg/g²":
        k2 = tuple(float(x) for x in 50e-6 * volts_per_g)
        return replace(bench, effects=replace(effects, quadratic_v_per_g2=(k2[0], k2[1], k2[2])))
    raise ValueError(f"no such effect: {effect}")


EFFECTS = ("tables 3×", "seating +3″", "drift 60 µg/h", "nonlinearity 50 µg/g²")

"""The simulated rig's physics: motion profile, low-pass output, clock accounting, truth recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import run_on_rig

from labcal.analysis.kinematics import Mount
from labcal.config.emulation import DeviceTruth, InstrumentTruth, RigConfig, coning_axes
from labcal.config.settings import SequencerSettings, SettleSettings
from labcal.run.sequencer import move_both
from labcal.sim.clock import VirtualClock
from labcal.sim.rig import SimRig
from labcal.sim.tables import SimAxis, trapezoid_duration, trapezoid_travel

QUIET_DEVICE = DeviceTruth(misalignment_deg={}, index_arcsec=0, wobble_arcsec=0)


@pytest.mark.parametrize("distance", [0.5, 10.0, 90.0, -180.0])
def test_trapezoid_ends_at_target_with_continuous_speed(distance):
    speed, accel = 20.0, 40.0
    total = trapezoid_duration(distance, speed, accel)
    t = np.linspace(0, total, 20001)
    x = trapezoid_travel(t, distance, speed, accel)
    assert x[0] == 0 and math.isclose(x[-1], distance, rel_tol=1e-12)
    v = np.diff(x) / np.diff(t)
    assert np.max(np.abs(v)) <= speed * (1 + 1e-9)
    assert np.max(np.abs(np.diff(v))) / (t[1] - t[0]) <= accel * 1.01  # bounded acceleration
    if abs(distance) > speed**2 / accel:
        assert math.isclose(total, abs(distance) / speed + speed / accel)


def test_axis_takes_shortest_way_round_and_clamps():
    clock = VirtualClock()
    axis = SimAxis("roll", clock, speed_dps=20, accel_dps2=40, clamp_s=1.0)
    axis.move_to(270)  # -90° the short way
    assert axis.wait_in_position(60) == pytest.approx(270)
    assert clock.now() == pytest.approx(90 / 20 + 20 / 40 + 1.0)  # cruise + the two ramps' lost time, clamp
    assert axis.travel_deg == pytest.approx(90)


def test_low_pass_output_decays_with_the_time_constant():
    """After a 90° pitch step the x output approaches its final value as exp(−t/τ)."""
    tau = 0.5
    config = RigConfig(device=QUIET_DEVICE, instrument=InstrumentTruth(tau_s=tau), clamp_s=0.0,
                       lab_temp_swing_c=0)
    rig = SimRig(config)
    station = rig.station()
    move_both(station, 90, 0, SequencerSettings())
    errors = []
    for _ in range(4):
        v = rig.read(1).volts[0, 0]  # one sample: 0.2 s of integration, centred 0.1 s in
        errors.append(1.0 - v)
    ratios = np.array(errors[1:]) / np.array(errors[:-1])
    assert np.allclose(ratios, math.exp(-0.2 / tau), rtol=1e-9)


def test_rig_time_is_the_sum_of_its_parts():
    config = RigConfig(device=QUIET_DEVICE, clamp_s=1.5, nplc=10, line_hz=50)
    rig = SimRig(config)
    station = rig.station()
    settings = SequencerSettings()
    move_both(station, 0, 90, settings)
    assert rig.clock.now() == pytest.approx(90 / 20 + 20 / 40 + 1.5)  # a 90° trapezoid (5 s), then the clamp
    t0 = rig.clock.now()
    rig.read(10)
    assert rig.clock.now() - t0 == pytest.approx(10 * 10 / 50)


def test_coning_axes_are_unit_and_reduce_to_identity():
    axes = coning_axes(np.radians([0.3, 0.2, 0.1]), np.radians([10, 100, 200]))
    assert np.allclose(np.linalg.norm(axes, axis=0), 1.0, atol=1e-15)
    assert np.allclose(coning_axes(np.zeros(3), np.radians([10, 100, 200])), np.eye(3), atol=0)


def test_drift_and_temperature_enter_the_output():
    truth = InstrumentTruth(drift_v_per_h=[1e-3, 0, 0], tc_bias_v_per_c=[0, 2e-3, 0],
                            tc_scale_per_c=[0, 0, 1e-3], t_ref_c=20)
    g = np.array([0.0, 0.0, 1.0])
    v = truth.static_volts(g, elapsed_s=7200, temp_c=22)
    assert np.allclose(v, [2e-3, 4e-3, 1 + 2e-3], atol=1e-15)


def test_remount_changes_what_the_instrument_feels():
    rig = SimRig(RigConfig(device=QUIET_DEVICE, instrument=InstrumentTruth(), remount_s=0,
                           lab_temp_swing_c=0))
    rig.remounted(Mount(0, 180))  # bottom side: level instrument now reads −1 g on z
    assert np.allclose(rig.read(1).volts[0], [0, 0, -1], atol=1e-12)


def test_noisy_four_mount_run_recovers_a_non_ideal_truth(tmp_path):
    """Sequencer + settle detection + rig dynamics + noise, no CD misalignment: every coefficient
    within 3 of its stated standard errors of the truth, and S_E matches the noise model."""
    truth = InstrumentTruth.from_coning(
        b=[0.0123, -0.0081, 0.0047], sensitivity=[4.9871, 5.0124, 4.9958],
        omega_deg=[0.21, 0.14, 0.09], azimuth_deg=[35, -120, 200], noise_v=50e-6, tau_s=0.5)
    rig = SimRig(RigConfig(device=QUIET_DEVICE, instrument=truth), seed=11)
    settings = SequencerSettings(settle=SettleSettings(tau_s=0.5, noise_v=50e-6, samples=10))
    fit = run_on_rig(rig, "four-mount-64", tmp_path, settings).fit
    z = (fit.coefficients - truth.X) / fit.stderr
    assert np.all(np.abs(z) < 3), z
    # the noise model is honest too: S_E ≈ 50 µV/√10 per averaged point
    assert np.allclose(fit.ls.residual_se, 50e-6 / math.sqrt(10), rtol=0.25)


def test_a_move_is_integrated_alike_wherever_the_rigs_clock_stands():
    """The same move, the same readings, whatever rig time it starts at: a resumed run's clock runs
    on from another instant than the uninterrupted run's, and the soak compares their readings.

    At rig time 2044.4635931025139 s (where the soak's resumed segment began point 44's move) a 5 s
    motion's (t_still − t0)/(τ/10) rounds to 100.00000000000455, and a bare ceil integrated it in 101
    steps instead of 100: 7e-8 V one second after the motion here. Otherwise only the rounding of rig
    times differs: below 8192 s (a soaked 64-point run's clock stays below it) an ulp is at most
    1.8e-12 s; times the output's rate one second after a 90° move (the transient, ≲ 0.1 V/s by
    then) that is ~2e-13 V, so 1e-12 V is allowed. The reference is the same rig at rig time 0,
    where every quotient is exact; 200 other instants of the same range besides."""
    config = RigConfig(instrument=InstrumentTruth(noise_v=2e-5, tau_s=0.5), lab_temp_swing_c=0.0)

    def reading(start: float) -> np.ndarray:
        clock = VirtualClock(start)
        rig = SimRig(config, seed=11, clock=clock)
        rig.pitch.place(90.0)
        rig.roll.place(90.0)
        rig.set_mount(Mount(0, 180))
        rig.pitch.move_to(180.0, travel_deg=90.0)  # the soak's move to its point 44
        rig.roll.move_to(0.0, travel_deg=-90.0)
        clock.advance_to(rig.pitch.motion_end + 1.0)
        rig.at_point("44")
        return rig.read(10).volts

    reference = reading(0.0)
    starts = [2044.4635931025139, *np.random.default_rng(44).uniform(1.0, 8000.0, 200)]
    worst = max(float(np.abs(reading(s) - reference).max()) for s in starts)
    assert worst <= 1e-12, worst

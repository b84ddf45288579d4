"""The check a run of a corrected plan makes of the misalignments it corrects for: what the plan's
Jacobian says it can see of a change (its analytic power) against what simulated runs detect.

The Monte Carlo is independent of the analytic power: readings come from the simulator (its own
kinematics, noise and, where said, a new table of index errors and wobble per run), each run is fitted
as `labcal run` fits a corrected plan (`run_fits`), and only the check's verdict is counted.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm

from labcal.analysis import correction_check as cc
from labcal.analysis import optimize
from labcal.analysis.device_fit import AngleErrors, PointMeans
from labcal.analysis.device_model import Geometry
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble, Misalignment
from labcal.analysis.plan import Plan
from labcal.config.corrections import DeviceCorrectionTable
from labcal.config.emulation import RigConfig
from labcal.config.plans import correction_toml, plan_toml
from labcal.sim.direct import simulate_readings
from labcal.store.exports import run_fits

RIG = RigConfig()
TRUTH, DEVICE = RIG.instrument, RIG.device
THREE = ((0.0, 0.0), (180.0, 0.0), (0.0, 180.0))  # fore/aft and top/bottom reversals: all six seen
SAMPLES = 4
NOISE = TRUTH.noise_v / math.sqrt(SAMPLES)  # of one reading, a window's mean
U_HISTORY = np.array([1.1, 0.9, 1.4, 0.9, 1.7, 0.75]) * ARCSEC  # a two-estimate history's u, as the rig's
HELD = np.array([DEVICE.misalignment_deg[n] for n in MISALIGNMENT_NAMES]) * 3600 * ARCSEC


def plan_of(mounts, n: int) -> Plan:
    points = optimize.d_optimal_sequence(mounts, optimize.candidate_articulations(), n)
    return Plan(name="corrected", mounts=list(mounts), points=[list(p) for p in points])


def corrected_text(plan: Plan, u_budget: np.ndarray) -> str:
    """The plan file with its correction held at the rig's misalignments."""
    table = DeviceCorrectionTable(
        device_id="SIMULATED", source="run-2", calibrated_utc="2026-02-01T00:00:00+00:00",
        value_arcsec={n: float(v / ARCSEC) for n, v in zip(MISALIGNMENT_NAMES, HELD, strict=True)},
        U_arcsec={n: float(1.96 * u / ARCSEC) for n, u in zip(MISALIGNMENT_NAMES, U_HISTORY, strict=True)},
        u_arcsec={n: float(u / ARCSEC) for n, u in zip(MISALIGNMENT_NAMES, u_budget, strict=True)},
        u_history_arcsec={n: float(u / ARCSEC) for n, u in zip(MISALIGNMENT_NAMES, U_HISTORY, strict=True)})
    return plan_toml(plan) + "\n" + correction_toml(table)


def detection_rate(plan: Plan, change: np.ndarray, trials: int, seed: int, tables: bool,
                   u_budget: np.ndarray) -> float:
    """The fraction of simulated corrected runs whose check detects a change: the device's truth drawn
    about the correction with its history's u (normal), then moved by ``change``."""
    text = corrected_text(plan, u_budget)
    errors = AngleErrors(*(np.array([DEVICE.index_arcsec, DEVICE.wobble_arcsec] * 2) * ARCSEC)) if tables \
        else None
    rng = np.random.default_rng(seed)
    detected = 0
    for trial in range(trials):
        truth = HELD + rng.normal(0.0, U_HISTORY) + change
        table = IndexWobble(DEVICE.index_arcsec, DEVICE.wobble_arcsec, seed + trial) if tables else None
        readings = simulate_readings(plan, TRUTH, Misalignment(*truth), table, NOISE, seed + trial)
        fit, device, _ = run_fits(readings, text, None)
        assert device is None
        found = cc.check(PointMeans.of(readings), fit.ls.residuals, fit.coefficients, np.full(3, NOISE), HELD,
                         U_HISTORY, u_budget, errors)
        detected += any(c.detected for c in found)
    return detected / trials


def sensitivity_of(plan: Plan, tables: bool) -> cc.Sensitivity:
    errors = AngleErrors(*(np.array([DEVICE.index_arcsec, DEVICE.wobble_arcsec] * 2) * ARCSEC)) if tables \
        else None
    return cc.sensitivity(Geometry.of_plan([tuple(p) for p in plan.points], list(plan.mounts)), TRUTH.X,
                          np.full(3, NOISE), HELD, errors)


@pytest.mark.parametrize(("mounts", "unseen"), [(((0.0, 0.0),), {"e", "f", "k"}),
                                                (((0.0, 0.0), (180.0, 180.0)), {"e"}),
                                                (((0.0, 0.0), (180.0, 0.0)), {"k"}),
                                                (((0.0, 0.0), (0.0, 180.0)), {"f"}),
                                                (THREE, set())])
def test_a_misalignment_no_mount_pair_reverses_is_invisible_and_its_change_undetectable(mounts, unseen):
    """Soto's reversals: one mount never sees e, f, k; fore/aft flips e and f, top/bottom e and k, both
    together f and k; so each pair leaves one unseen and three mounts see all six. An unseen one has
    no power at all and an infinite budget u: a plan cannot rely on a correction of it."""
    sens = sensitivity_of(plan_of(mounts, 12), tables=True)
    assert set(MISALIGNMENT_NAMES) - set(sens.observable) == unseen
    power = sens.power(3 * U_HISTORY, U_HISTORY)
    u = sens.budget_u(U_HISTORY)
    for i, name in enumerate(MISALIGNMENT_NAMES):
        assert (power[i] == 0.0 and not np.isfinite(u[i])) if name in unseen else np.isfinite(u[i])


def test_the_budget_u_makes_a_change_of_three_u_detected_with_95_percent_power():
    """By the rule: Φ(3u/s − c) + Φ(−3u/s − c) ≥ 0.95 for every seen misalignment, c the Bonferroni
    critical value for a 1 % family-wise false alarm over six tests (2.865, from the normal quantile
    here, not from the module)."""
    sens = sensitivity_of(plan_of(THREE, 12), tables=True)
    u = sens.budget_u(U_HISTORY)
    c = norm.ppf(1 - 0.01 / 12)
    assert sens.critical == pytest.approx(c, rel=1e-12)
    s = np.sqrt(sens.run_sd**2 + U_HISTORY**2)
    by_hand = norm.cdf(3 * u / s - c) + norm.cdf(-3 * u / s - c)
    assert np.all(by_hand >= 0.95 - 1e-12), by_hand
    assert np.all(u >= U_HISTORY)


def test_without_table_errors_the_analytic_power_is_the_monte_carlo_detection_rate():
    """Noise only (no index errors or wobble, so the analytic variance is exact, not a bound): a change
    of e or k by 3 null standard deviations is detected at the analytic rate, within 3 binomial
    standard deviations of 150 simulated runs each; with nothing moved, at the false-alarm rate."""
    plan = plan_of(THREE, 12)
    sens = sensitivity_of(plan, tables=False)
    u_budget = sens.budget_u(U_HISTORY)
    null = sens.null_sd(U_HISTORY)
    trials = 150
    for name in ("e", "k"):
        i = MISALIGNMENT_NAMES.index(name)
        change = np.zeros(6)
        change[i] = 3.0 * null[i]
        expected = float(sens.power(change, U_HISTORY)[i])
        assert 0.3 < expected < 0.9  # where a wrong variance would show
        seen = detection_rate(plan, change, trials, 7100 + 1000 * i, False, u_budget)
        margin = 3 * math.sqrt(expected * (1 - expected) / trials)
        assert abs(seen - expected) <= margin, (name, seen, expected)
    alarms = detection_rate(plan, np.zeros(6), trials, 9100, False, u_budget)
    assert alarms <= 0.01 + 3 * math.sqrt(0.01 * 0.99 / trials), alarms


@pytest.mark.slow
def test_with_the_rigs_tables_a_three_u_change_of_any_one_misalignment_is_detected_in_95_percent_of_runs():
    """The rig's ±2″ index errors and wobble, a new table per run: a change of each misalignment by 3 of
    its budget u is detected in ≥ 95 % of 100 simulated runs (less 3 binomial standard deviations),
    and with nothing moved the check raises an alarm in at most 1 % (plus the same margin)."""
    plan = plan_of(THREE, 12)
    sens = sensitivity_of(plan, tables=True)
    u_budget = sens.budget_u(U_HISTORY)
    trials = 100
    margin = 3 * math.sqrt(0.95 * 0.05 / trials)
    rates = {}
    for i, name in enumerate(MISALIGNMENT_NAMES):
        change = np.zeros(6)
        change[i] = 3 * u_budget[i]
        rates[name] = detection_rate(plan, change, trials, 11000 + 1000 * i, True, u_budget)
    print("detected, a change of 3 u in one misalignment (target ≥ 95 %):",
          ", ".join(f"{n} {100 * r:.0f} %" for n, r in rates.items()))
    assert min(rates.values()) >= 0.95 - margin, rates
    alarms = detection_rate(plan, np.zeros(6), trials, 19000, True, u_budget)
    print(f"false alarms with nothing moved: {100 * alarms:.0f} % (stated ≤ 1 %)")
    assert alarms <= 0.01 + 3 * math.sqrt(0.01 * 0.99 / trials)

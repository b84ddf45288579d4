"""Inferred-angle uncertainty of Tripp & Tcheng's sensor packages (§6): each against the paper's
closed form typed here from the equation, and by Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.analysis.design import d1
from labcal.analysis.distributions import t_quantile, welch_satterthwaite
from labcal.analysis.kinematics import nominal_gravity
from labcal.analysis.packages import (
    Sensor,
    derivatives,
    determinant,
    from_linear,
    infer,
    inferred_covariance,
    output,
    output_sd,
    package_problem,
    pitch_at_roll,
    pitch_without_roll,
    sd_pitch_at_roll,
    sd_pitch_without_roll,
    usable_box,
    without_roll,
)
from labcal.analysis.regression import least_squares
from labcal.errors import LabcalError

DEG = np.pi / 180
ALPHA = np.radians(np.linspace(-80, 80, 17))
ROLL = np.radians(np.linspace(-170, 170, 18))


def test_sensitivities_are_the_derivatives_of_eqs_14_to_16():
    """Eqs. 87, 88, 95 against central differences of the outputs (eqs. 14–16)."""
    a, r = np.meshgrid(ALPHA, ROLL, indexing="ij")
    h = 1e-6
    for axis in "xyz":
        s = Sensor(axis, 0.1, 2.5, 0.7 * DEG, 40 * DEG)
        f_a, f_r = derivatives(s, a, r)
        assert np.allclose(f_a, (output(s, a + h, r) - output(s, a - h, r)) / (2 * h), atol=1e-8)
        assert np.allclose(f_r, (output(s, a, r + h) - output(s, a, r - h)) / (2 * h), atol=1e-8)


def test_eq_1_is_eq_14_with_the_substitution_of_eq_17():
    b, S, phi = 0.02, 1.7, 0.4 * DEG
    by_eq_1 = b + S * np.sin(ALPHA - phi)  # Tripp eq. 1
    assert np.allclose(output(without_roll(b, S, phi), ALPHA, 0.0), by_eq_1, atol=1e-15)


def test_eq_76_inverts_eq_1():
    b, S, phi = -0.01, 2.2, 0.3 * DEG
    v = b + S * np.sin(ALPHA - phi)
    assert np.allclose(pitch_without_roll(v, b, S, phi), ALPHA, atol=1e-13)


def test_eq_78_is_sigma_v_over_s_at_zero_pitch_without_misalignment():
    sigma_v, S = 1.3e-4, 2.0
    assert sd_pitch_without_roll(sigma_v, S, 0.0, 0.0) == pytest.approx(sigma_v / S, rel=1e-15)


def test_eq_78_over_pitch_and_unbounded_at_90_degrees():
    sigma_v, S, phi = 1.3e-4, 2.0, 0.5 * DEG
    expected = sigma_v / (S * np.abs(np.cos(ALPHA - phi)))  # Tripp eq. 78
    assert np.allclose(sd_pitch_without_roll(sigma_v, S, phi, ALPHA), expected, rtol=1e-14)
    assert sd_pitch_without_roll(sigma_v, S, 0.0, np.pi / 2) > 1e10 * sigma_v / S
    # the same sensor as eq. 14's x sensor at R = 0 (eq. 17) gives the same σ through eq. 80
    at_roll = sd_pitch_at_roll([without_roll(0.0, S, phi)], [sigma_v], ALPHA, 0.0)
    assert np.allclose(at_roll, expected, rtol=1e-12)


def test_eq_79_inverts_eq_2_at_the_known_roll():
    s = Sensor("x", 0.03, 1.9, 1.2 * DEG, 70 * DEG)
    a, r = np.meshgrid(ALPHA, ROLL, indexing="ij")
    assert np.allclose(pitch_at_roll(output(s, a, r), s, r), a, atol=1e-12)


@pytest.mark.parametrize("omega_deg,azimuth_deg", [(0.3, 0.0), (1.0, 90.0), (5.0, 233.0)])
def test_eq_81_single_axis_with_independently_measured_roll(omega_deg, azimuth_deg):
    S, om, A = 2.1, omega_deg * DEG, azimuth_deg * DEG
    sigma_v, sigma_r = 1.1e-4, 0.5 * DEG
    a, r = np.meshgrid(ALPHA, ROLL, indexing="ij")
    # Tripp eq. 81, written out
    numerator = np.sqrt(sigma_v**2 / S**2 + (np.sin(om) * np.cos(a) * np.cos(r + A)) ** 2 * sigma_r**2)
    expected = numerator / np.abs(np.cos(om) * np.cos(a) + np.sin(om) * np.sin(a) * np.sin(r + A))
    got = sd_pitch_at_roll([Sensor("x", 0.0, S, om, A)], [sigma_v], a, r, sigma_r)
    assert np.allclose(got, expected, rtol=1e-12)


def test_eq_82_without_coning_the_roll_does_not_matter():
    S, sigma_v = 2.1, 1.1e-4
    a, r = np.meshgrid(ALPHA, ROLL, indexing="ij")
    got = sd_pitch_at_roll([Sensor("x", 0.0, S)], [sigma_v], a, r, 2 * DEG)
    assert np.allclose(got, sigma_v / (S * np.cos(a)), rtol=1e-13)  # Tripp eq. 82


def test_eq_98_x_z_package_at_30_60_degrees():
    """Ω = 0, S = 1: f_α·f_αᵀ = (1 − cos²R)cos²α + cos²R (eq. 98) = 0.8125 at {30°, 60°}, so with
    equal output uncertainties σ the pitch's is σ/√0.8125 (eq. 96)."""
    sigma = 1e-4
    package = [Sensor("x", 0.0, 1.0), Sensor("z", 0.0, 1.0)]
    moment = (1 - np.cos(60 * DEG) ** 2) * np.cos(30 * DEG) ** 2 + np.cos(60 * DEG) ** 2
    assert moment == pytest.approx(0.8125, rel=1e-15)
    got = sd_pitch_at_roll(package, [sigma, sigma], 30 * DEG, 60 * DEG)
    assert got == pytest.approx(sigma / np.sqrt(0.8125), rel=1e-13)
    a, r = np.meshgrid(ALPHA, ROLL, indexing="ij")
    eq_98 = (1 - np.cos(r) ** 2) * np.cos(a) ** 2 + np.cos(r) ** 2
    assert np.allclose(sd_pitch_at_roll(package, [sigma, sigma], a, r), sigma / np.sqrt(eq_98), rtol=1e-12)


def test_x_z_package_is_unbounded_only_at_90_90():
    package = [Sensor("x", 0.0, 1.0), Sensor("z", 0.0, 1.0)]
    sd = sd_pitch_at_roll(package, [1e-4, 1e-4], np.radians([90, 90, 0, 45]), np.radians([90, 0, 90, 90]))
    assert sd[0] > 1e8 and np.all(np.isfinite(sd[1:])) and np.all(sd[1:] < 2e-4)


@pytest.mark.parametrize("omega_deg,ax_deg,az_deg", [(0.1, 90.0, 0.0), (1.0, 0.0, 0.0), (2.0, 30.0, 200.0)])
def test_eq_96_x_z_package_with_coning(omega_deg, ax_deg, az_deg):
    om, Ax, Az, Sx, Sz = omega_deg * DEG, ax_deg * DEG, az_deg * DEG, 2.0, 1.5
    sx, sz = 1e-4, 3e-4
    a, r = np.meshgrid(ALPHA, ROLL, indexing="ij")
    # eq. 97's f_α from eqs. 87 and 95, written out; eq. 96's variance f_α Σ f_αᵀ / (f_α f_αᵀ)²
    f_xa = Sx * (np.cos(om) * np.cos(a) + np.sin(om) * np.sin(a) * np.sin(r + Ax))
    f_za = Sz * (np.cos(om) * np.sin(a) * np.cos(r) + np.sin(om) * (np.cos(Az) * np.cos(a)
                                                                      + np.sin(Az) * np.sin(a) * np.sin(r)))
    expected = np.sqrt(f_xa**2 * sx**2 + f_za**2 * sz**2) / (f_xa**2 + f_za**2)
    got = sd_pitch_at_roll([Sensor("x", 0, Sx, om, Ax), Sensor("z", 0, Sz, om, Az)], [sx, sz], a, r)
    assert np.allclose(got, expected, rtol=1e-12)


def test_eq_90_x_y_package_without_coning():
    """Ω = 0 in eqs. 87–88: F_z = [[S_x cos α, S_y sin α sin R], [0, −S_y cos α cos R]], so by hand
    σ_α̂ = σ_x/(S_x cos α) and σ_R̂² = (σ_y² + S_y² tan²α sin²R σ_x²/S_x²)/(S_y² cos²α cos²R)."""
    Sx, Sy, sx, sy = 2.0, 1.5, 1e-4, 4e-4
    a, r = np.meshgrid(np.radians(np.linspace(-80, 80, 9)), np.radians([-150, -60, 0, 30, 75, 120]),
                       indexing="ij")
    cov = inferred_covariance([Sensor("x", 0, Sx), Sensor("y", 0, Sy)], [sx, sy], a, r)
    assert np.allclose(np.sqrt(cov[..., 0, 0]), sx / (Sx * np.cos(a)), rtol=1e-12)
    var_r = (sy**2 + Sy**2 * np.tan(a) ** 2 * np.sin(r) ** 2 * sx**2 / Sx**2) / (Sy**2 * np.cos(a) ** 2
                                                                                   * np.cos(r) ** 2)
    assert np.allclose(cov[..., 1, 1], var_r, rtol=1e-11)
    # det F_z = −S_x S_y cos²α cos R: singular at α = ±90° and R = ±90° (§6.4)
    assert np.allclose(determinant([Sensor("x", 0, Sx), Sensor("y", 0, Sy)], a, r),
                       -Sx * Sy * np.cos(a) ** 2 * np.cos(r), atol=1e-15)


def test_eq_90_agrees_with_monte_carlo_of_the_newton_inference():
    """Noisy outputs of a coned x–y package inverted by Newton–Raphson: the scatter of (α̂, R̂) is
    eq. 90's. 3000 draws: the sample SD is within 4 % (3 × its 1.3 % standard error)."""
    package = [Sensor("x", 0.01, 2.0, 1.0 * DEG, 90 * DEG), Sensor("y", -0.02, 1.5, 1.0 * DEG, 90 * DEG)]
    sigma = [2e-4, 5e-4]
    alpha, roll = 25 * DEG, 40 * DEG
    v0 = np.array([output(s, alpha, roll) for s in package])
    rng = np.random.default_rng(37)
    noisy = v0 + rng.normal(size=(3000, 2)) * sigma
    assert np.allclose(infer(package, v0), [alpha, roll], atol=1e-12)
    z = infer(package, noisy)
    cov = inferred_covariance(package, sigma, alpha, roll)
    assert np.allclose(z.std(axis=0, ddof=1), np.sqrt(np.diag(cov)), rtol=0.04)
    corr = cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1])
    assert float(np.corrcoef(z[:, 0], z[:, 1])[0, 1]) == pytest.approx(corr, abs=0.06)  # SE ≈ 0.02


def test_newton_refuses_the_singular_attitude():
    package = [Sensor("x", 0.0, 1.0), Sensor("y", 0.0, 1.0)]
    with pytest.raises(LabcalError, match="singular"):
        infer(package, [1.0, 0.0], (np.pi / 2, 0.0))


def test_usable_box_of_an_x_y_package_avoids_its_singularities():
    """The box computed from the package's coefficients: every attitude in it meets the limit by the
    Ω = 0 closed forms (above), it stops short of α = ±90° and R = ±90°, and it cannot grow in both
    directions."""
    Sx, Sy, sx, sy = 2.0, 2.0, 1e-4, 1e-4
    limit = 4 * sx / Sx
    box = usable_box([Sensor("x", 0, Sx), Sensor("y", 0, Sy)], [sx, sy], limit)
    assert 0 < box.pitch < np.pi / 2 and 0 < box.roll < np.pi / 2

    def worst(p: float, r: float) -> float:
        a, rr = np.meshgrid(np.arange(0, p + 1e-9, DEG), np.arange(0, r + 1e-9, DEG), indexing="ij")
        sd_a = sx / (Sx * np.cos(a))
        sd_r = np.sqrt((sy**2 + Sy**2 * np.tan(a) ** 2 * np.sin(rr) ** 2 * sx**2 / Sx**2)
                       / (Sy**2 * np.cos(a) ** 2 * np.cos(rr) ** 2))
        return float(max(sd_a.max(), sd_r.max()))

    assert worst(box.pitch, box.roll) <= limit
    assert worst(box.pitch + DEG, box.roll) > limit or worst(box.pitch, box.roll + DEG) > limit


def test_usable_box_excludes_the_coned_singular_locus():
    """Tripp Fig. 9(c)–(d): A_x = 90° bends the locus of det F_z = 0 away from R = 90° as α grows.
    No attitude in the box has det F_z of the sign change that marks the locus."""
    package = [Sensor("x", 0, 1.0, 1.0 * DEG, 90 * DEG), Sensor("y", 0, 1.0, 1.0 * DEG, 90 * DEG)]
    box = usable_box(package, [1e-4, 1e-4], 1e-3)
    a, r = np.meshgrid(np.linspace(-box.pitch, box.pitch, 181), np.linspace(-box.roll, box.roll, 181),
                       indexing="ij")
    det = determinant(package, a, r)
    assert np.all(det < 0) or np.all(det > 0)


def test_from_linear_recovers_tripps_parameters_from_a_fit():
    """Outputs of eqs. 14–16 at a D1 design, fitted by the linear model v = B + s·g, give back
    [b, S, Ω, A] of each sensor."""
    points = np.radians(d1(60, 9, 8))
    g = nominal_gravity(points[:, 0], points[:, 1], 0.0, 0.0)
    design = np.column_stack([np.ones(len(g)), g])
    for truth in (Sensor("x", 0.01, 2.0, 0.8 * DEG, 35 * DEG),
                  Sensor("y", -0.02, -1.5, 0.4 * DEG, -100 * DEG),
                  Sensor("z", 0.03, -2.5, 1.5 * DEG, 170 * DEG)):
        fit = least_squares(design, output(truth, points[:, 0], points[:, 1]))
        got = from_linear(fit.coef[0, 0], fit.coef[1:, 0], truth.axis)
        assert got.axis == truth.axis
        assert np.allclose([got.b, got.S, got.omega, got.azimuth],
                           [truth.b, truth.S, truth.omega, truth.azimuth], atol=1e-12)


def test_u95_of_pitch_with_independent_roll_covers_95_percent():
    """Single-axis sensor with roll (Tripp §6.3): calibrated on a D1 design (±30°, N = 13, M = 8)
    with Gaussian output noise, used at a roll measured with σ_R; the inferred pitch (eq. 79, with
    the fit's b̂, Ŝ, Ω̂, Â and the measured roll) and U95 = k·σ_α̂ (eq. 81, σ_v from the fit, ν_eff by
    Welch–Satterthwaite) covers the true pitch 95 ± 2 % of the time, both where the output noise
    dominates and where the roll's does. 4000 calibrations: coverage SE 0.34 %."""
    truth = Sensor("x", 0.012, 2.0, 1.0 * DEG, 20 * DEG)
    sigma, sigma_r = 2e-4, 0.4 * DEG
    points = np.radians(d1(30, 13, 8))
    g = nominal_gravity(points[:, 0], points[:, 1], 0.0, 0.0)
    design = np.column_stack([np.ones(len(g)), g])
    clean = output(truth, points[:, 0], points[:, 1])
    rng = np.random.default_rng(2026)
    trials = 4000
    fits = least_squares(design, clean[:, None] + sigma * rng.normal(size=(len(clean), trials)))
    for alpha, roll in ((20 * DEG, 80 * DEG), (10 * DEG, -5 * DEG)):
        v_new = output(truth, alpha, roll) + sigma * rng.normal(size=trials)
        roll_measured = roll + sigma_r * rng.normal(size=trials)
        hits = 0
        for t in range(trials):
            s_hat = from_linear(fits.coef[0, t], fits.coef[1:, t], "x")
            alpha_hat = float(pitch_at_roll(v_new[t], s_hat, roll_measured[t]))
            se = float(fits.residual_se[t])
            sigma_v = float(output_sd(fits.cov_unscaled * se**2, se, alpha_hat, roll_measured[t]))
            u = float(sd_pitch_at_roll([s_hat], [sigma_v], alpha_hat, roll_measured[t], sigma_r))
            u_noise = float(sd_pitch_at_roll([s_hat], [sigma_v], alpha_hat, roll_measured[t]))
            nu = welch_satterthwaite(np.array(u), [(np.array(u_noise**2), float(fits.dof)),
                                                   (np.array(u**2 - u_noise**2), np.inf)])
            hits += abs(alpha_hat - alpha) <= float(t_quantile(0.975, nu)) * u
        assert 0.93 <= hits / trials <= 0.97, (np.degrees([alpha, roll]), hits / trials)


@pytest.mark.parametrize("package,roll_in_use,pitch,roll,why", [
    ("two-axis-xy", "inferred", (-60, 60), (-180, 180), "singular"),  # §6.4: R = ±90°
    ("two-axis-xy", "inferred", (-89, 89), (-80, 80), None),
    ("two-axis-xz", "inferred", (-60, 60), (-30, 30), "singular"),  # §6.5: R = 0°
    ("two-axis-xz", "inferred", (-60, 60), (30, 150), None),  # §6.5's usable roll range
    ("two-axis-xz", "table", (-90, 90), (-180, 180), "pitch -90°, roll -90°"),  # eq. 98: {±90°, ±90°}
    ("two-axis-xz", "table", (-90, 90), (0, 80), None),
    ("single-axis", "sensor", (-90, 60), (-180, 180), "pitch -90°"),  # eq. 81 at α = ±90°
    ("single-axis", "sensor", (-89, 89), (-180, 180), None),
    ("single-axis", "none", (-60, 60), (-10, 10), "roll 0 only"),  # eq. 1
    ("single-axis", "none", (-60, 60), (0, 0), None),
    ("single-axis", "inferred", (-60, 60), (0, 0), "cannot infer roll"),
    ("three-axis", "inferred", (-90, 90), (-180, 180), None),  # eq. 108: pitch bounded everywhere
])
def test_package_problem_over_a_usage_envelope(package, roll_in_use, pitch, roll, why):
    problem = package_problem(package, roll_in_use, pitch, roll)
    assert problem is None if why is None else (problem is not None and why in problem)


def test_figures_7_and_8_as_section_6_3_describes_them():
    """§6.3 on Figs. 7–8 (Ω = 1°, A = 90°): with σ_R 1 and 10 times the pitch sensor's uncertainty
    the inferred pitch's hardly varies with roll, with 100 times it does; and it is about 15 % greater
    at α = 30° than at α = 0°."""
    single = [Sensor("x", 0.0, 1.0, 1.0 * DEG, 90 * DEG)]
    roll = np.radians(np.linspace(0, 180, 181))
    spread = {k: np.ptp(sd_pitch_at_roll(single, [1.0], 0.0, roll, k)) for k in (1, 10, 100)}
    assert spread[1] < 0.001 and spread[10] < 0.02 and spread[100] > 0.5
    at_30, at_0 = (sd_pitch_at_roll(single, [1.0], a, 0.0, 1.0) for a in (30 * DEG, 0.0))
    assert at_30 / at_0 == pytest.approx(1.15, abs=0.01)


def test_u95_holds_inside_the_usable_box_of_a_coned_x_y_package():
    """Tripp Fig. 10(a)'s package (Ω = 1°, A_x = 90°, A_y = 0°, σ_x = σ_y). Its usable box for a
    limit of 4σ/S: at the box's centre, corner and edge midpoints, noisy outputs inverted by
    Newton–Raphson from the level attitude give pitch and roll within 1.96·σ (eq. 90) 95 ± 2 % of the
    time (2000 draws each: standard error 0.5 %)."""
    package = [Sensor("x", 0.0, 1.0, 1.0 * DEG, 90 * DEG), Sensor("y", 0.0, 1.0, 1.0 * DEG, 0.0)]
    sigma = [2e-3, 2e-3]
    box = usable_box(package, sigma, 4 * sigma[0])
    assert 40 * DEG < box.pitch < 90 * DEG and 40 * DEG < box.roll < 90 * DEG
    rng = np.random.default_rng(90)
    for alpha, roll in ((0.0, 0.0), (box.pitch, box.roll), (-box.pitch, 0.0), (0.0, -box.roll)):
        v0 = np.array([output(s, alpha, roll) for s in package])
        z = infer(package, v0 + rng.normal(size=(2000, 2)) * sigma)
        sd = np.sqrt(np.diag(inferred_covariance(package, sigma, alpha, roll)))
        covered = np.abs(z - [alpha, roll]) <= 1.96 * sd
        assert np.all((covered.mean(axis=0) >= 0.93) & (covered.mean(axis=0) <= 0.97)), (
            np.degrees([alpha, roll]), covered.mean(axis=0))


def test_a_package_used_without_roll_infers_pitch_by_eq_76_and_refuses_a_measured_roll():
    """A single-axis calibration used without roll (Tripp eq. 1): pitch from eq. 76 written out
    here, its U95 k·σ_v/(S|cos(α − φ)|) (eq. 78) with σ_v from the covariance at roll 0; a roll given
    to it is refused in one line, and a package used at a measured roll needs one."""
    from labcal.analysis.packages import PackageCalibration, package_attitude

    b, S, phi = 0.02, 1.9, 0.4 * DEG
    cov = np.diag([1e-8, 2e-8, 3e-8, 3e-8])
    sensor = (without_roll(b, S, phi),)
    cal = PackageCalibration("single-axis", sensor, cov[None], np.array([1e-4]), 2.01, "none")
    v = np.array([[0.02], [1.0], [-0.7]])
    att = package_attitude(cal, v)
    expected = np.arcsin((v[:, 0] - b) / S) + phi  # eq. 76
    assert np.allclose(att.pitch, expected, atol=1e-13) and np.all(att.roll == 0)
    f = np.stack([np.ones(3), np.sin(expected), np.zeros(3), np.cos(expected)], axis=-1)  # g at roll 0
    sigma_v = np.sqrt(np.einsum("ij,jk,ik->i", f, cov, f) + 1e-8)
    assert np.allclose(att.U_pitch, 2.01 * sigma_v / (S * np.abs(np.cos(expected - phi))), rtol=1e-10)
    with pytest.raises(LabcalError, match="without roll"):
        package_attitude(cal, v, roll=np.radians(10.0))
    at_table = PackageCalibration("single-axis", sensor, cov[None], np.array([1e-4]), 2.01, "table", 1e-4)
    with pytest.raises(LabcalError, match="give it"):
        package_attitude(at_table, v)

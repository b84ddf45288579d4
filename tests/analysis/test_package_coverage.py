"""The checks of a sensor package's stated uncertainty against what was not written by the code
that states it: Tripp & Tcheng's eq. 98 at {30°, 60°} from central differences of their eqs. 2 and 5
typed here; an x–y certificate's usable range against Monte Carlo of its use and the singular locus
of its Jacobian; and the U95 of pitch inferred at an independently measured roll after Tripp
§9.2.1's six-replication calibration drifting 1 °C, by Monte Carlo coverage."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labcal.analysis.distributions import t_quantile, welch_satterthwaite
from labcal.analysis.packages import Sensor, from_linear, output_sd, pitch_at_roll, sd_pitch_at_roll
from labcal.analysis.regression import least_squares
from labcal.documents.certificate import read_certificate

DEG = math.pi / 180


def test_eq_98_at_30_60_degrees_from_central_differences_of_eqs_2_and_5():
    """Ω = 0, S = 1: the x and z outputs of eqs. 2 and 5 typed here, differentiated in α by central
    differences at {α, R} = {30°, 60°}: f_α·f_αᵀ = (1 − cos²R)cos²α + cos²R = 0.8125 (eq. 98), and
    the package's inferred pitch SD with equal output SDs σ is σ/√0.8125 (eq. 96)."""
    def v_x(a, r):  # eq. 2 with b = 0, S = 1, Ω = 0
        return np.sin(a)

    def v_z(a, r):  # eq. 5 with b = 0, S = 1, Ω = 0
        return -np.cos(r) * np.cos(a)

    a, r, h = 30 * DEG, 60 * DEG, 1e-6
    f_a = np.array([(v(a + h, r) - v(a - h, r)) / (2 * h) for v in (v_x, v_z)])
    moment = float(f_a @ f_a)
    assert moment == pytest.approx(0.75 * 0.75 + 0.25, abs=1e-9)  # (1 − 1/4)(3/4) + 1/4 = 0.8125
    sigma = 2e-4
    got = sd_pitch_at_roll([Sensor("x", 0.0, 1.0), Sensor("z", 0.0, -1.0)], [sigma, sigma], a, r)
    assert float(got) == pytest.approx(sigma / math.sqrt(0.8125), rel=1e-9)


@pytest.fixture(scope="module")
def xy_certificate(tmp_path_factory):
    from labcal.cli import main

    out = tmp_path_factory.mktemp("xy")
    assert main(["run", "--sim", "--instrument", "two-axis-xy", "--yes", "--out", str(out / "run"), "--db",
                 str(out / "lab.sqlite")]) == 0
    return read_certificate(out / "run" / "certificate.json")


def _outputs(coef: np.ndarray, alpha, roll) -> np.ndarray:
    """Each sensor's output B + s·g at (α, R) under labcal's linear model, written out here."""
    alpha, roll = np.broadcast_arrays(np.asarray(alpha, dtype=float), np.asarray(roll, dtype=float))
    g = np.stack([np.sin(alpha), np.cos(alpha) * np.sin(roll), np.cos(alpha) * np.cos(roll)], axis=-1)
    return coef[..., 0, :] + np.einsum("...k,...kj->...j", g, coef[..., 1:, :])


def _invert(coef: np.ndarray, v: np.ndarray, alpha0: float, roll0: float) -> np.ndarray:
    """(α, R) with the nominal coefficients' outputs equal to ``v`` (n × 2): Newton's method with
    the Jacobian by central differences, written here, from the true attitude."""
    z = np.tile([alpha0, roll0], (len(v), 1))
    h = 1e-7
    for _ in range(30):
        f = _outputs(coef, z[:, 0], z[:, 1])
        ja = (_outputs(coef, z[:, 0] + h, z[:, 1]) - _outputs(coef, z[:, 0] - h, z[:, 1])) / (2 * h)
        jr = (_outputs(coef, z[:, 0], z[:, 1] + h) - _outputs(coef, z[:, 0], z[:, 1] - h)) / (2 * h)
        J = np.stack([ja, jr], axis=-1)  # (n, outputs, angles)
        step = np.linalg.solve(J, (v - f)[..., None])[..., 0]
        z = z + step
        if np.max(np.abs(step)) < 1e-13:
            break
    return z


@pytest.mark.slow
def test_a_two_axis_xy_certificates_usable_range_holds_its_u95_and_excludes_the_singular_jacobian(
        xy_certificate):
    """The certificate of a simulated x–y run states a usable range where both inferred angles' U95
    is within its limit. At every attitude of a 7 × 7 grid over that range (edges and corners
    included), Monte Carlo of the use — coefficients drawn from the certificate's covariance, a new
    reading's noise, pitch and roll inverted here — keeps the 95th percentile error of both angles
    within the limit (2000 draws; 10 % for the percentile's own scatter); no attitude of the range
    has a singular Jacobian (det F_z by central differences keeps one sign, at least 5 % of its
    level value), while the locus where it vanishes (R = ±90° near level) lies outside it; and the
    range is the largest its rule allows: one degree beyond its corner, in pitch or in roll, the
    Monte Carlo U95 exceeds the limit somewhere."""
    cert = xy_certificate
    p = cert.package
    assert p is not None and p.package == "two-axis-xy" and p.usable_pitch_deg and p.usable_roll_deg
    limit = p.u95_limit_deg
    coef = np.array(cert.fit.coefficients)  # (4, 2)
    cov = [np.array(c)[:4, :4] for c in cert.fit.covariance]
    reading = np.array(cert.fit.reading_sd)
    rng = np.random.default_rng(9805)
    n = 2000

    def mc_u95(alpha_deg: float, roll_deg: float) -> np.ndarray:
        a, r = alpha_deg * DEG, roll_deg * DEG
        drawn = np.stack([rng.multivariate_normal(coef[:, j], cov[j], size=n) for j in range(2)], axis=-1)
        v = _outputs(drawn, a, r) + rng.normal(size=(n, 2)) * reading
        z = _invert(coef, v, a, r)
        return np.degrees(np.percentile(np.abs(z - [a, r]), 95, axis=0))

    pitches = np.linspace(*p.usable_pitch_deg, 7)
    rolls = np.linspace(*p.usable_roll_deg, 7)
    for a in pitches:
        for r in rolls:
            assert np.all(mc_u95(a, r) <= limit * 1.10), (a, r, mc_u95(a, r))

    def det(alpha_deg, roll_deg):
        a, r, h = np.radians(alpha_deg), np.radians(roll_deg), 1e-6
        ja = (_outputs(coef, a + h, r) - _outputs(coef, a - h, r)) / (2 * h)
        jr = (_outputs(coef, a, r + h) - _outputs(coef, a, r - h)) / (2 * h)
        return ja[..., 0] * jr[..., 1] - ja[..., 1] * jr[..., 0]

    A, R = np.meshgrid(np.linspace(*p.usable_pitch_deg, 61), np.linspace(*p.usable_roll_deg, 61),
                       indexing="ij")
    inside = det(A, R)
    level = float(det(0.0, 0.0))
    assert np.all(np.sign(inside) == np.sign(level)) and np.min(np.abs(inside)) >= 0.05 * abs(level)
    across = det(0.0, np.linspace(0, 180, 1801))  # the locus crosses roll near 90° at level pitch
    crossing = np.linspace(0, 180, 1801)[np.flatnonzero(np.diff(np.sign(across)))]
    assert len(crossing) and np.all(np.abs(crossing) > p.usable_roll_deg[1])
    p_max, r_max = p.usable_pitch_deg[1], p.usable_roll_deg[1]
    beyond = max(mc_u95(p_max + 1, r_max).max(), mc_u95(p_max, r_max + 1).max(),
                 mc_u95(-p_max - 1, -r_max).max(), mc_u95(-p_max, -r_max - 1).max())
    assert beyond > limit * 0.9


# --- Tripp §9.2.1: single-axis with roll, six replications, 1 °C drift -----------------------------
NOISE = 2e-4  # V per point
B_T, S_T = 5e-5, 3e-4  # V/°C and 1/°C, as the simulated instrument's
SIGMA_R = 0.4 * DEG  # the roll measured in use


def test_u95_of_pitch_at_a_measured_roll_covers_95_percent_after_a_drifting_six_replication_calibration():
    """Tripp §9.2.1's design (pitch −30..30° by 5°, roll −180..180° by 15° with 180° repeated, six
    replications: 1950 points) of a single-axis sensor with roll whose temperature drifts 1 °C over
    the run, fitted with Table 2 footnote b's temperature terms (offset and sensitivity, centred on
    the run's mean temperature, as `labcal fit --extend temperature` does: checked on the first
    calibration). In use at that temperature, at a roll measured with σ_R = 0.4°, the inferred pitch
    (eq. 79) is within U95 = k·σ (eq. 81, σ_v from the fit's covariance and a new reading, ν_eff by
    Welch–Satterthwaite) of the truth 95 ± 2 % of 2000 calibrations, where the output noise
    dominates and where the roll's does (standard error 0.5 %)."""
    from labcal.analysis.fit import fit_readings
    from labcal.analysis.models import Model
    from labcal.analysis.readings import Readings

    pitch, roll = (x.ravel() for x in np.meshgrid(np.arange(-30, 31, 5.0), np.arange(-180, 181, 15.0),
                                                  indexing="ij"))
    pitch, roll = np.tile(pitch, 6), np.tile(roll, 6)
    assert len(pitch) == 1950
    temp = 20.0 + np.linspace(0.0, 1.0, len(pitch))  # the drift: 1 °C over the run
    t_ref = float(np.mean(temp))
    truth = Sensor("x", 0.012, 2.0, 1.0 * DEG, 20 * DEG)  # Tripp eq. 8 at 20 °C
    p, r = np.radians(pitch), np.radians(roll)
    g = np.column_stack([np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])
    # the sensor's column s (Tripp eq. 2 as v = b + s·g): s = S[cos Ω, −sin Ω cos A, −sin Ω sin A]
    s0 = truth.S * np.array([np.cos(truth.omega), -np.sin(truth.omega) * np.cos(truth.azimuth),
                             -np.sin(truth.omega) * np.sin(truth.azimuth)])
    dt = temp - 20.0
    clean = truth.b + B_T * dt + (g @ s0) * (1 + S_T * dt)
    rng = np.random.default_rng(921)
    trials = 2000
    volts = clean[:, None] + NOISE * rng.normal(size=(len(clean), trials))
    centred = (temp - t_ref)[:, None]
    design = np.column_stack([np.ones(len(g)), g, centred, centred * g])  # [1, gᵀ, ΔT, ΔT·gᵀ]
    fits = least_squares(design, volts)

    readings = Readings(replicate=np.repeat(np.arange(1, 7), 325), y_deg=np.zeros(1950), u_deg=np.zeros(1950),
                        pitch_deg=pitch, roll_deg=roll,
                        volts=np.column_stack([volts[:, 0], np.full(1950, np.nan), np.full(1950, np.nan)]),
                        temp_c=temp)
    fit = fit_readings(readings, Model(("temperature",), t_ref=t_ref))
    assert fit.sensors == ("x",)
    assert np.allclose(fit.ls.coef[:, 0], fits.coef[:, 0], rtol=1e-9, atol=1e-12)
    assert np.allclose(fit.covariance(0), fits.cov_unscaled * fits.residual_se[0] ** 2, rtol=1e-9)

    at_ref = Sensor("x", truth.b + B_T * (t_ref - 20), truth.S * (1 + S_T * (t_ref - 20)), truth.omega,
                    truth.azimuth)
    for alpha, roll_use in ((20 * DEG, 80 * DEG), (10 * DEG, -5 * DEG)):
        g_use = np.array([np.sin(alpha), np.cos(alpha) * np.sin(roll_use), np.cos(alpha) * np.cos(roll_use)])
        v_new = at_ref.b + g_use @ (s0 * at_ref.S / truth.S) + NOISE * rng.normal(size=trials)
        roll_read = roll_use + SIGMA_R * rng.normal(size=trials)
        hits = 0
        for t in range(trials):
            s_hat = from_linear(fits.coef[0, t], fits.coef[1:4, t], "x")
            a_hat = float(pitch_at_roll(v_new[t], s_hat, roll_read[t]))
            se = float(fits.residual_se[t])
            sigma_v = float(output_sd(fits.cov_unscaled[:4, :4] * se**2, se, a_hat, roll_read[t]))
            u = float(sd_pitch_at_roll([s_hat], [sigma_v], a_hat, roll_read[t], SIGMA_R))
            u_noise = float(sd_pitch_at_roll([s_hat], [sigma_v], a_hat, roll_read[t]))
            nu = welch_satterthwaite(np.array(u), [(np.array(u_noise**2), float(fits.dof)),
                                                   (np.array(u**2 - u_noise**2), np.inf)])
            hits += abs(a_hat - alpha) <= float(t_quantile(0.975, nu)) * u
        assert 0.93 <= hits / trials <= 0.97, (np.degrees([alpha, roll_use]), hits / trials)


@pytest.mark.slow
def test_u95_of_pitch_from_an_x_z_package_at_a_measured_roll_covers_95_percent():
    """An x–z package (Tripp §6.5) calibrated on a D1 design (pitch −90..90° by 15°, roll by 30°,
    two replicates) with Gaussian output noise, used at a roll measured with σ_R = 0.3°: pitch by
    least squares in α from both outputs (eq. 96) is within U95 = k·σ (eqs. 96–97 with eq. 80's roll
    term; σ_v of each sensor from its fit) of the truth 95 ± 2 % of 2000 calibrations, at an attitude
    where the x sensor carries pitch and one near pitch 80° where the z sensor does."""
    from labcal.analysis.packages import pitch_at_known_roll

    x_true = Sensor("x", 0.01, 2.0, 0.5 * DEG, 70 * DEG)
    z_true = Sensor("z", -0.02, -1.8, 0.8 * DEG, 200 * DEG)
    noise, sigma_r = (3e-4, 5e-4), 0.3 * DEG
    pitch, roll = (x.ravel() for x in np.meshgrid(np.arange(-90, 91, 15.0), np.arange(-180, 180, 30.0),
                                                  indexing="ij"))
    pitch, roll = np.radians(np.tile(pitch, 2)), np.radians(np.tile(roll, 2))
    g = np.column_stack([np.sin(pitch), np.cos(pitch) * np.sin(roll), np.cos(pitch) * np.cos(roll)])
    design = np.column_stack([np.ones(len(g)), g])
    rng = np.random.default_rng(96)
    trials = 2000

    def eq_2_and_5(alpha, r):
        """Tripp eqs. 2 and 5 typed here: the two sensors' outputs."""
        vx = x_true.b + x_true.S * (np.cos(x_true.omega) * np.sin(alpha)
                                    - np.sin(x_true.omega) * np.cos(alpha) * np.sin(r + x_true.azimuth))
        om, A = z_true.omega, z_true.azimuth
        vz = z_true.b - z_true.S * (np.cos(om) * np.cos(r) * np.cos(alpha) - np.sin(om) * (
            np.cos(A) * np.sin(alpha) - np.sin(A) * np.sin(r) * np.cos(alpha)))
        return vx, vz

    clean = eq_2_and_5(pitch, roll)
    fits = [least_squares(design, c[:, None] + s * rng.normal(size=(len(c), trials)))
            for c, s in zip(clean, noise, strict=True)]
    for alpha, roll_use in ((20 * DEG, 50 * DEG), (80 * DEG, 30 * DEG)):
        new = [v + s * rng.normal(size=trials)
               for v, s in zip(eq_2_and_5(alpha, roll_use), noise, strict=True)]
        roll_read = roll_use + sigma_r * rng.normal(size=trials)
        hits = 0
        for t in range(trials):
            sensors = [from_linear(f.coef[0, t], f.coef[1:, t], axis)
                       for f, axis in zip(fits, "xz", strict=True)]
            a_hat = float(pitch_at_known_roll(sensors, [[new[0][t], new[1][t]]], roll_read[t])[0])
            sd = [float(output_sd(f.cov_unscaled * f.residual_se[t] ** 2, f.residual_se[t], a_hat,
                                  roll_read[t])) for f in fits]
            u = float(sd_pitch_at_roll(sensors, sd, a_hat, roll_read[t], sigma_r))
            u_noise = float(sd_pitch_at_roll(sensors, sd, a_hat, roll_read[t]))
            nu = welch_satterthwaite(np.array(u), [(np.array(u_noise**2), float(fits[0].dof)),
                                                   (np.array(u**2 - u_noise**2), np.inf)])
            hits += abs(a_hat - alpha) <= float(t_quantile(0.975, nu)) * u
        assert 0.93 <= hits / trials <= 0.97, (np.degrees([alpha, roll_use]), hits / trials)

"""The GUM budget row by row against values derived without it (docs/mutation.md).

Coefficients: each bench error is applied to noise-free readings as the bench would make it (a table
off by δ at one angle, a plate seated off by δ for one mounting, a DMM reading ε too high), the
readings are refitted with numpy's lstsq on the nominal design, and the change of X per unit error is
the sensitivity (central difference, exact to δ²); GUM: u = half-width/√3 for a rectangular input,
contributions add in quadrature; a table's error in both shapes the budget states (one per table
angle, and harmonics 1–3 of the angle at u²/3 each). Pitch and roll: a hand-built calibration with
S = I, where the estimator's sensitivities are the gravity derivatives written out in the test
(∂g/∂p ⟂ ∂g/∂r ⟂ g, |∂g/∂p| = 1, |∂g/∂r| = cos p), with the |g| column and the prior on |g| in numpy
where unequal weights let it matter, ν_eff by Welch–Satterthwaite written out (GUM G.2b) and k from
scipy's Student t at ν_eff truncated to the integer below (GUM G.4.1 note 1).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy import stats

from labcal.analysis.budget import (
    Calibration,
    Component,
    Source,
    TypeBInputs,
    calibration_of,
    calibration_of_device,
    coefficient_budget,
    propagate,
    sources,
    welch_satterthwaite,
)
from labcal.analysis.device_fit import fit_device
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import ARCSEC, Misalignment, gravity
from labcal.analysis.models import Points
from labcal.analysis.readings import Readings
from labcal.config.emulation import InstrumentTruth
from labcal.config.plans import load_plan
from labcal.sim.direct import simulate_readings

SQRT3 = np.sqrt(3.0)
B = np.array([0.01, -0.02, 0.005])
S = np.array([[5.0, 0.01, 0.0], [0.0, 4.9, 0.02], [0.01, 0.0, 5.1]])
Z975 = 1.959963984540054  # the normal distribution's 97.5 % point (k for ν = ∞)

# Two mounts, the second at y = 90°, u = 180° written also as y = −270° and u = −180° (the same
# seating), pitch −45…80° and roll 0, 120, 240° (also written −120°): every table angle is visited
# several times, and no table error cancels between the two mounts.
# The second mount's pitch angles are written as a file may hold them: −45° as 315°, 0° as
# 359.9999996° (6 decimals round it to 360, which is 0), 45° as 45.0000004°; and 80.5° is its own angle.
_P = np.concatenate([np.repeat([-45.0, 0.0, 45.0, 80.5], 3),
                     np.repeat([315.0, 360 - 4e-7, 45 + 4e-7, 80.0], 3)])
_R = np.tile([0.0, 120.0, 240.0, 0.0, 120.0, -120.0], 4)
_Y = np.concatenate([np.zeros(12), np.tile([90.0 + 4e-7, -270.0], 6)])
_U = np.concatenate([np.zeros(12), np.tile([180.0, 180.0, -180.0], 4)])


def _volts(mis: Misalignment | None = None) -> np.ndarray:
    return B + gravity(*np.radians([_P, _R, _Y, _U]), mis or Misalignment()) @ S


READINGS = Readings(replicate=np.ones(24, dtype=int), y_deg=_Y, u_deg=_U, pitch_deg=_P, roll_deg=_R,
                    volts=_volts())
DESIGN = np.column_stack([np.ones(24), gravity(*np.radians([_P, _R, _Y, _U]))])


def _refit(volts: np.ndarray) -> np.ndarray:
    return np.linalg.lstsq(DESIGN, volts, rcond=None)[0]


def _sensitivity(name: str, patterns: np.ndarray) -> np.ndarray:
    """∂X/∂(error ``name`` of each input), 4×3×n_inputs, by refitting readings made with the error:
    input m moves misalignment ``name`` at point k by patterns[k, m] per unit."""
    delta, columns = 1e-6, []
    for pattern in patterns.T:
        plus = _refit(_volts(Misalignment(**{name: delta * pattern})))
        minus = _refit(_volts(Misalignment(**{name: -delta * pattern})))
        columns.append((plus - minus) / (2 * delta))
    return np.stack(columns, axis=-1)


def _per_group(groups: np.ndarray) -> np.ndarray:
    """One input per group: 1 at the group's points, 0 elsewhere (K × n_groups)."""
    return np.stack([(groups == g).astype(float) for g in np.unique(groups)], axis=1)


def _harmonics(angle_deg: np.ndarray) -> np.ndarray:
    """A smooth table's error: harmonics 1–3 of the table angle, cos and sin (K × 6)."""
    a = np.radians(angle_deg)
    return np.column_stack([f(h * a) for f in (np.cos, np.sin) for h in (1, 2, 3)])


def _u_of(half_width: float, names: tuple[str, ...], groups: np.ndarray) -> np.ndarray:
    """Each coefficient's standard uncertainty from independent rectangular errors ±half_width."""
    jac = np.concatenate([_sensitivity(n, _per_group(groups)) for n in names], axis=-1)
    return half_width / SQRT3 * np.sqrt(np.sum(jac**2, axis=-1))


def _u_of_table(half_width: float, names: tuple[str, ...], groups: np.ndarray, angle_deg: np.ndarray
                ) -> np.ndarray:
    """A table error in its two shapes: a rough table, one rectangular error ±half_width per
    table angle (u = a/√3), and a smooth one, six harmonic amplitudes of u²/3 each; independent, so
    their variances add."""
    rough = _u_of(half_width, names, groups)
    jac = np.concatenate([_sensitivity(n, _harmonics(angle_deg)) for n in names], axis=-1)
    smooth = half_width / SQRT3 / np.sqrt(3.0) * np.sqrt(np.sum(jac**2, axis=-1))
    return np.hypot(rough, smooth)


PITCH_GROUPS = np.concatenate([np.repeat([0, 1, 2, 3], 3), np.repeat([0, 1, 2, 4], 3)])
ROLL_GROUPS = np.round(np.mod(_R, 360.0) / 120.0).astype(int)
# each point's table angle as the table stood (315° is −45°, 359.9999996° is 0°)
PITCH_ANGLES = np.concatenate([np.repeat([-45.0, 0.0, 45.0, 80.5], 3),
                               np.repeat([-45.0, 0.0, 45.0, 80.0], 3)])
ROLL_ANGLES = 120.0 * ROLL_GROUPS
MOUNT_GROUPS = (_Y != 0).astype(int)

INPUTS = TypeBInputs(dmm_reading=3.5e-5, dmm_range_v=5e-5, pitch_index=2 * ARCSEC, pitch_wobble=3 * ARCSEC,
                     roll_index=4 * ARCSEC, roll_wobble=5 * ARCSEC, mount_repeatability=6 * ARCSEC,
                     temperature_half_range_k=1.5, bias_tempco_v_per_k=1e-4, sensitivity_tempco_per_k=2e-5)


@pytest.fixture(scope="module")
def cal() -> Calibration:
    return calibration_of(fit_readings(READINGS), READINGS)


def test_projection_is_the_pseudo_inverse_of_the_nominal_design(cal):
    np.testing.assert_allclose(cal.projection, np.linalg.pinv(DESIGN)[:4], atol=1e-12)
    np.testing.assert_allclose(cal.X, np.vstack([B, S]), atol=1e-12)
    assert sorted(set(cal.installation)) == [0, 1]  # (90°, 180°) and (−270°, −180°) are one seating
    np.testing.assert_array_equal(cal.installation == cal.installation[0], MOUNT_GROUPS == 0)


def _row(rows: list[Source], name: str) -> Source:
    return next(r for r in rows if r.name == name)


def test_each_type_b_row_of_the_coefficients_is_what_refitting_the_disturbed_readings_gives(cal):
    rows = sources(cal, INPUTS)
    coef = coefficient_budget(rows)
    X = np.vstack([B, S])
    expected = {
        # the DMM reads (1 + ε_j) v on channel j: the fit of channel j scales by (1 + ε_j)
        "DMM accuracy, % of reading": np.abs(X) * 3.5e-5 / SQRT3,
        # and v + o_j: only B_j moves, by o_j
        "DMM accuracy, % of range": np.vstack([np.full(3, 5e-5 / SQRT3), np.zeros((3, 3))]),
        # ΔT moves every B by c_B ΔT and every S by c_S S ΔT, one input for all
        "temperature": np.vstack([np.full(3, 1e-4), 2e-5 * np.abs(S)]) * 1.5 / SQRT3,
        # the tables' errors are functions of the table angle: a (pitch) and f (roll) add to the table
        # angles, one error per angle (rough) and harmonics 1–3 of it (smooth)
        "pitch table index accuracy": _u_of_table(2 * ARCSEC, ("a",), PITCH_GROUPS, PITCH_ANGLES),
        "pitch table wobble": _u_of_table(3 * ARCSEC, ("d", "f"), PITCH_GROUPS, PITCH_ANGLES),
        "roll table index accuracy": _u_of_table(4 * ARCSEC, ("f",), ROLL_GROUPS, ROLL_ANGLES),
        "roll table wobble": _u_of_table(5 * ARCSEC, ("e", "k"), ROLL_GROUPS, ROLL_ANGLES),
        "mount repeatability": _u_of(6 * ARCSEC, ("e", "f", "k"), MOUNT_GROUPS),
        "one new reading (instrument repeatability)": np.zeros((4, 3)),
        "local gravity": np.zeros((4, 3)),
    }
    for name, u in expected.items():
        np.testing.assert_allclose(coef.contributions[name], u, rtol=1e-6, atol=1e-13, err_msg=name)
    assert coef.contributions["calibration fit (coefficients)"].max() < 1e-12  # noise-free readings
    total = np.sqrt(sum(u**2 for u in expected.values()))
    np.testing.assert_allclose(coef.u_c, total, rtol=1e-6, atol=1e-13)
    np.testing.assert_allclose(coef.k, Z975, rtol=1e-6)  # every input Type B or noise-free: ν = ∞
    np.testing.assert_allclose(coef.U, Z975 * total, rtol=1e-6, atol=1e-12)


def test_rows_state_their_inputs_in_their_own_units(cal):
    rows = {r.name: r for r in sources(cal, INPUTS)}
    stated = {name: (r.type, r.distribution, r.unit) for name, r in rows.items()}
    assert stated == {
        "calibration fit (coefficients)": ("A", "t", "V (u of B, largest)"),
        "one new reading (instrument repeatability)": ("A", "t", "V"),
        "DMM accuracy, % of reading": ("B", "rectangular", "relative"),
        "DMM accuracy, % of range": ("B", "rectangular", "V"),
        "pitch table index accuracy": ("B", "rectangular", "arcsec"),
        "pitch table wobble": ("B", "rectangular", "arcsec"),
        "roll table index accuracy": ("B", "rectangular", "arcsec"),
        "roll table wobble": ("B", "rectangular", "arcsec"),
        "mount repeatability": ("B", "rectangular", "arcsec"),
        "temperature": ("B", "rectangular", "K"),
        "local gravity": ("B", "rectangular", "g"),
    }
    for name, half in (("pitch table index accuracy", 2), ("pitch table wobble", 3),
                       ("roll table index accuracy", 4), ("roll table wobble", 5),
                       ("mount repeatability", 6)):
        assert rows[name].u == pytest.approx(half / SQRT3, rel=1e-12), name  # arcsec, u = a/√3
        assert rows[name].dof == np.inf and rows[name].added
    assert rows["DMM accuracy, % of reading"].u == pytest.approx(3.5e-5 / SQRT3, rel=1e-12)
    assert rows["DMM accuracy, % of range"].u == pytest.approx(5e-5 / SQRT3, rel=1e-12)
    assert rows["temperature"].u == pytest.approx(1.5 / SQRT3, rel=1e-12)
    # |g| where used within ±5e-4 of the calibration's (the estimator's prior): u = 5e-4/√3, in g; it
    # reaches pitch and roll through the estimator, not the coefficients or outputs: no component
    assert rows["local gravity"].u == pytest.approx(5e-4 / SQRT3, rel=1e-12)
    assert rows["local gravity"].components == () and rows["local gravity"].added
    assert rows["local gravity"].dof == np.inf  # a stated distribution: nothing limits it
    # the Type A rows carry the fit's 24 − 4 = 20 degrees of freedom
    assert rows["calibration fit (coefficients)"].dof == 20
    assert rows["one new reading (instrument repeatability)"].dof == 20


def test_dmm_noise_is_shown_through_the_projection_and_not_added_again(cal):
    """Independent noise σ on every reading: var X̂_ij = σ² ((FᵀF)⁻¹)_ii (P Pᵀ = (FᵀF)⁻¹)."""
    without = coefficient_budget(sources(cal, INPUTS))
    rows = sources(cal, TypeBInputs(**{**vars(INPUTS), "dmm_noise_v": 2e-5}))
    noise = _row(rows, "DMM noise")
    assert (noise.type, noise.distribution, noise.u, noise.added) == ("B", "normal", 2e-5, False)
    coef = coefficient_budget(rows)
    inv = np.linalg.inv(DESIGN.T @ DESIGN)
    np.testing.assert_allclose(coef.contributions["DMM noise"],
                               2e-5 * np.sqrt(np.diag(inv))[:, None] * np.ones(3), rtol=1e-9)
    np.testing.assert_allclose(coef.u_c, without.u_c, rtol=1e-12)
    assert "DMM noise" not in [r.name for r in sources(cal, INPUTS)]


def test_mount_scatter_replaces_the_station_file_value_as_type_a(cal):
    rows = sources(cal, TypeBInputs(mount_repeatability=6 * ARCSEC, mount_repeatability_sd=2 * ARCSEC,
                                    mount_repeatability_dof=7))
    mount = _row(rows, "mount repeatability")
    assert (mount.type, mount.distribution, mount.dof) == ("A", "normal", 7.0)
    assert mount.u == pytest.approx(2.0, rel=1e-12)  # arcsec, the σ itself: normal, no √3
    coef = coefficient_budget(rows)
    # σ = 2″ normal is the u of a rectangular ±2√3″: the refitted sensitivities, scaled
    np.testing.assert_allclose(coef.contributions["mount repeatability"],
                               _u_of(2 * SQRT3 * ARCSEC, ("e", "f", "k"), MOUNT_GROUPS),
                               rtol=1e-6, atol=1e-13)
    unknown = _row(sources(cal, TypeBInputs(mount_repeatability_sd=2 * ARCSEC)), "mount repeatability")
    assert unknown.dof == np.inf  # no dof stated: taken as exactly known


def test_device_misalignments_are_one_input_each_for_the_whole_run(cal):
    rows = sources(cal, TypeBInputs(device_misalignment={"a": 3 * ARCSEC, "e": 4 * ARCSEC}))
    row = _row(rows, "device misalignment estimates")
    assert (row.type, row.distribution, row.u) == ("B", "normal", pytest.approx(4.0))
    everything = np.zeros(24, dtype=int)
    expected = np.hypot(_u_of(3 * SQRT3 * ARCSEC, ("a",), everything),
                        _u_of(4 * SQRT3 * ARCSEC, ("e",), everything))
    np.testing.assert_allclose(coefficient_budget(rows).contributions[row.name], expected,
                               rtol=1e-6, atol=1e-13)


def test_welch_satterthwaite_by_hand():
    """u_c = 2 from variances 1 (ν = 4), 3 (ν = ∞) and 0 (ν = 0, ignored): ν_eff = 2⁴ / (1²/4) = 64."""
    parts = [(np.array([1.0, 0.0]), 4.0), (np.array([3.0, 1.0]), np.inf), (np.array([0.0, 0.0]), 0.0)]
    nu = welch_satterthwaite(np.array([2.0, 1.0]), parts)
    assert nu[0] == pytest.approx(64.0, rel=1e-12)
    assert nu[1] == np.inf  # only an infinite-dof part: ν = ∞


# --- pitch and roll: a calibration built by hand -------------------------------------------------
SIGMA = 1e-3  # V, one new reading's standard deviation, every sensor
C_FIT = 2e-4**2  # V², every coefficient's variance, uncorrelated, every sensor
DOF = np.array([10.0, 20.0, 40.0])


HAND_POINTS = ([0.0, 90.0, 0.0, -90.0, 45.0, 30.0], [0.0, 0.0, 90.0, 0.0, 180.0, -60.0])


def _hand_design() -> np.ndarray:
    p, r = np.radians(HAND_POINTS)
    return np.column_stack([np.ones(6), np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)])


def _hand_cal(cov: float = 0.0) -> Calibration:
    """S = I, B = 0: the instrument reads gravity itself. The projection and points only feed the
    table and mount rows, which these tests leave at zero."""
    f = _hand_design()
    points = Points.at(*HAND_POINTS)
    return Calibration(X=np.vstack([np.zeros(3), np.eye(3)]), covariance=np.stack([cov * np.eye(4)] * 3),
                       reading_var=np.full(3, SIGMA**2), dof=DOF, projection=np.linalg.pinv(f)[:4],
                       points=points, installation=np.zeros(6, dtype=int))


def _dg(p: float, r: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """g = (sin p, cos p sin r, cos p cos r) and its derivatives, by hand."""
    sp, cp, sr, cr = np.sin(p), np.cos(p), np.sin(r), np.cos(r)
    return (np.array([sp, cp * sr, cp * cr]), np.array([cp, -sp * sr, -sp * cr]),
            np.array([0.0, cp * cr, -cp * sr]))


U_GRAVITY = 5e-4 / SQRT3  # the estimator's prior on local |g|: within ±5e-4 of the calibration's


def _estimator(p: float, r: float, w: np.ndarray) -> np.ndarray:
    """A = ∂(pitch, roll)/∂v of the sphere estimator with S = I, B = 0: parameters (p, r, m), m = |g|,
    outputs m·g(p, r), so J = [∂g/∂p, ∂g/∂r, g] (columns), and the prior m = 1 ± U_GRAVITY adds
    P = 1/U_GRAVITY² to m's normal equation: A = first two rows of (JᵀWJ + P e_m e_mᵀ)⁻¹ JᵀW."""
    g, dp, dr = _dg(p, r)
    J = np.column_stack([dp, dr, g])
    N = J.T @ np.diag(w) @ J + np.diag([0.0, 0.0, 1.0 / U_GRAVITY**2])
    return np.asarray(np.linalg.solve(N, J.T @ np.diag(w))[:2])


def _k(nu: np.ndarray) -> np.ndarray:
    """k = t₀.₉₇₅ at ν_eff truncated to the integer below (GUM G.4.1 note 1), from scipy."""
    return np.asarray(stats.t.ppf(0.975, np.floor(nu)))


def test_a_new_readings_noise_reaches_pitch_and_roll_as_the_geometry_says():
    """Equal weights and orthogonal ∂g/∂p, ∂g/∂r, g: the prior on |g| only moves m, and A = [∂g/∂p;
    ∂g/∂r / cos²p], so u_pitch = σ and u_roll = σ / cos p; ν_eff from the three sensors' shares
    σ²(∂g/∂p)_j² with their own ν; k at ν truncated."""
    p, r = np.radians(60.0), np.radians(20.0)
    cal = _hand_cal()
    out = propagate(cal, sources(cal, TypeBInputs()), p, r)
    g, dp, dr = _dg(p, r)
    np.testing.assert_allclose(_estimator(p, r, np.full(3, SIGMA**-2)), [dp, dr / np.cos(p) ** 2],
                               atol=1e-12)  # the hand form is the estimator's, prior included
    np.testing.assert_allclose(out.contributions["one new reading (instrument repeatability)"][0],
                               [SIGMA, SIGMA / np.cos(p)], rtol=1e-9)
    np.testing.assert_allclose(out.u_c[0], [SIGMA, 2 * SIGMA], rtol=1e-9)  # cos 60° = ½
    nu = np.array([1.0 / np.sum(d**4 / DOF) for d in (dp, dr / np.linalg.norm(dr))])
    np.testing.assert_allclose(out.nu_eff[0], nu, rtol=1e-9)
    assert np.all(np.floor(nu) < nu)  # ν is not whole here: the truncation shows in k
    np.testing.assert_allclose(out.k[0], _k(nu), rtol=1e-7)
    np.testing.assert_allclose(out.U[0], _k(nu) * np.array([SIGMA, 2 * SIGMA]), rtol=1e-7)
    np.testing.assert_allclose(out.pitch, [p])
    np.testing.assert_allclose(out.roll, [r])


def test_the_fits_covariance_reaches_pitch_and_roll_through_f_of_z():
    """C_j = c·I: var(fᵀδX_j) = c |f|² = 2c (|g| = 1), the same for every sensor, so the weights stay
    equal and the fit row gives √(2c) in pitch, √(2c)/cos p in roll. A sensor's fit covariance and its
    new reading's variance come from its one residual variance estimate: one Welch–Satterthwaite term
    per sensor, (2c + σ²) d_j², with that sensor's ν."""
    p, r = np.radians(30.0), np.radians(-70.0)
    cal = _hand_cal(C_FIT)
    out = propagate(cal, sources(cal, TypeBInputs()), p, r)
    _, dp, dr = _dg(p, r)
    fit_u = np.sqrt(2 * C_FIT)
    np.testing.assert_allclose(out.contributions["calibration fit (coefficients)"][0],
                               [fit_u, fit_u / np.cos(p)], rtol=1e-9)
    u_c = np.sqrt(2 * C_FIT + SIGMA**2) * np.array([1.0, 1.0 / np.cos(p)])
    np.testing.assert_allclose(out.u_c[0], u_c, rtol=1e-9)
    shares = [((2 * C_FIT + SIGMA**2) * d**2) ** 2 for d in (dp, dr / np.cos(p) ** 2)]
    nu = np.array([u**4 / np.sum(s / DOF) for u, s in zip(u_c, shares, strict=True)])
    np.testing.assert_allclose(out.nu_eff[0], nu, rtol=1e-9)
    np.testing.assert_allclose(out.k[0], _k(nu), rtol=1e-7)
    coef = coefficient_budget(sources(cal, TypeBInputs()))
    np.testing.assert_allclose(coef.u_c, np.full((4, 3), np.sqrt(C_FIT)), rtol=1e-12)
    np.testing.assert_allclose(coef.nu_eff, np.broadcast_to(DOF, (4, 3)), rtol=1e-12)


def test_dmm_and_temperature_reach_pitch_and_roll_as_the_geometry_says():
    """Offset o_j on channel j: like a reading error, u·(1, 1/cos p). Gain ε_j: δv_j = ε_j g_j, so
    pitch moves by Σ_j (∂g/∂p)_j g_j ε_j. Temperature: c_B ΔT on every channel moves pitch by
    Σ_j (∂g/∂p)_j c_B ΔT; c_S ΔT on every S scales v along g, normal to the sphere: no angle moves."""
    p, r = np.radians(35.0), np.radians(50.0)
    cal = _hand_cal()
    inputs = TypeBInputs(dmm_reading=3.5e-5, dmm_range_v=5e-5, temperature_half_range_k=2.0,
                         bias_tempco_v_per_k=1e-4, sensitivity_tempco_per_k=3e-4)
    out = propagate(cal, sources(cal, inputs), p, r)
    g, dp, dr = _dg(p, r)
    a_roll = dr / np.cos(p) ** 2
    c = out.contributions
    np.testing.assert_allclose(c["DMM accuracy, % of range"][0], 5e-5 / SQRT3 * np.array([1, 1 / np.cos(p)]),
                               rtol=1e-9)
    gain = 3.5e-5 / SQRT3 * np.array([np.linalg.norm(dp * g), np.linalg.norm(a_roll * g)])
    np.testing.assert_allclose(c["DMM accuracy, % of reading"][0], gain, rtol=1e-9)
    temp = 1e-4 * 2.0 / SQRT3 * np.abs([dp.sum(), a_roll.sum()])
    np.testing.assert_allclose(c["temperature"][0], temp, rtol=1e-9, atol=1e-15)
    # Local |g| = 1 + δ scales v along g: A·g·δ = (∂g/∂p·g, ∂g/∂r·g/cos²p)·δ = 0, the prior's m takes
    # it all. Exact zero by hand; the solver's rounding leaves ~eps·‖N⁻¹‖/u ≈ 1e-18 rad, 13 orders
    # below the other rows here, hence atol 1e-15 rad.
    np.testing.assert_allclose(_estimator(p, r, np.full(3, SIGMA**-2)) @ g, [0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(c["local gravity"][0], [0.0, 0.0], atol=1e-15)
    # A gain common to the three channels (one ADC) is the same scaling along g: no angle moves
    common = propagate(cal, sources(cal, replace(inputs, common=("dmm_reading",))), p, r)
    np.testing.assert_allclose(common.contributions["DMM accuracy, % of reading"][0], [0.0, 0.0], atol=1e-15)
    assert gain.min() > 1e-6  # while independent gains move both angles


def test_unequal_weights_let_the_prior_on_gravity_into_pitch_and_roll():
    """One new reading's σ_j different per sensor (σ, 2σ, σ/2): the weights differ, ∂g/∂p, ∂g/∂r and g
    are no longer orthogonal under W, and the prior matters. A from (JᵀWJ + P e_m e_mᵀ)⁻¹ JᵀW by numpy;
    the new-reading row is √(Σ_j A_aj² σ_j²); local |g| = 1 + δ (rectangular ±5e-4) moves the
    estimate by A·g·δ, so the local gravity row is |A·g|·5e-4/√3."""
    p, r = np.radians(40.0), np.radians(25.0)
    sd = SIGMA * np.array([1.0, 2.0, 0.5])
    cal = replace(_hand_cal(), reading_var=sd**2)
    out = propagate(cal, sources(cal, TypeBInputs()), p, r)
    g, dp, dr = _dg(p, r)
    A = _estimator(p, r, sd**-2.0)
    no_prior = np.linalg.solve(np.column_stack([dp, dr, g]).T @ np.diag(sd**-2.0)
                               @ np.column_stack([dp, dr, g]), np.column_stack([dp, dr, g]).T
                               @ np.diag(sd**-2.0))[:2]
    assert np.abs(A - no_prior).max() > 0.01 * np.abs(A).max()  # the prior changes A here
    reading = np.sqrt(np.sum(A**2 * sd**2, axis=1))
    np.testing.assert_allclose(out.contributions["one new reading (instrument repeatability)"][0], reading,
                               rtol=1e-9)
    gravity_row = np.abs(A @ g) * U_GRAVITY
    assert gravity_row.min() > 1e-6  # a real share in both angles
    np.testing.assert_allclose(out.contributions["local gravity"][0], gravity_row, rtol=1e-9)
    np.testing.assert_allclose(out.u_c[0], np.hypot(reading, gravity_row), rtol=1e-9)
    # ν_eff: the readings' shares (A_aj σ_j)² with ν_j, the prior's with ν = ∞
    nu = np.array([out.u_c[0, a] ** 4 / np.sum((A[a] * sd) ** 4 / DOF) for a in range(2)])
    np.testing.assert_allclose(out.nu_eff[0], nu, rtol=1e-9)
    np.testing.assert_allclose(out.k[0], _k(nu), rtol=1e-7)


def test_at_pitch_90_only_pitch_is_estimated():
    """Roll is undefined where cos p = 0 (NaN, never a number); pitch keeps σ since |∂g/∂p| = 1."""
    cal = _hand_cal()
    out = propagate(cal, sources(cal, TypeBInputs()), np.radians([90.0, -90.0]), np.radians([10.0, 0.0]))
    np.testing.assert_allclose(out.u_c[:, 0], SIGMA, rtol=1e-9)
    assert np.isnan(out.u_c[:, 1]).all()


def test_components_add_their_variances_and_unadded_rows_are_only_shown():
    """Two components of one row: contributions √(Σ J² u²); a second row not ``added``: shown, not in u_c."""
    jac = np.zeros((12, 1))
    jac[0, 0] = 2.0  # B_x moves by 2 per unit input
    jac2 = np.zeros((12, 1))
    jac2[0, 0] = 1.0
    rows = [Source("two", "B", "normal", 1.0, "V", (Component(jac, np.zeros((3, 1)), 3.0, np.inf, "normal"),
                                                    Component(jac2, np.zeros((3, 1)), 4.0, 5.0, "normal"))),
            Source("shown", "B", "normal", 1.0, "V", (Component(jac2, np.zeros((3, 1)), 7.0, 2.0, "normal"),),
                   added=False)]
    coef = coefficient_budget(rows)
    assert coef.contributions["two"][0, 0] == pytest.approx(np.hypot(6.0, 4.0))
    assert coef.contributions["shown"][0, 0] == pytest.approx(7.0)
    assert coef.u_c[0, 0] == pytest.approx(np.hypot(6.0, 4.0))
    assert coef.nu_eff[0, 0] == pytest.approx(52.0**2 / (16.0**2 / 5.0))  # only the ν = 5 part counts
    assert rows[0].dof == 5.0


def test_a_device_fit_gives_the_coefficients_covariance_with_the_misalignments_held():
    """The covariance of (B, S) given a…k is the Schur complement; computed here the other way, as
    the inverse of the (B, S) block of the precision matrix Σ⁻¹. Layout: θ = [a…k, vec X], X[i, j] at
    6 + 3i + j."""
    plan, _ = load_plan("four-mount-64")
    readings = simulate_readings(plan, InstrumentTruth(B=B.tolist(), S=S.tolist()),
                                 Misalignment.from_degrees(a=0.01, e=-0.02, k=0.015), noise_v=3e-5, seed=5)
    device = fit_device(readings)
    cal = calibration_of(device.linear, readings)
    dev = calibration_of_device(device, readings)
    given = np.linalg.inv(np.linalg.inv(device.covariance)[6:, 6:])
    for j in range(3):
        idx = [3 * i + j for i in range(4)]
        np.testing.assert_allclose(dev.covariance[j], given[np.ix_(idx, idx)], rtol=1e-6,
                                   atol=1e-9 * np.abs(given).max())
    np.testing.assert_array_equal(dev.X, device.theta[6:].reshape(4, 3))
    np.testing.assert_allclose(dev.reading_var, device.reading_sd() ** 2, rtol=1e-12)
    np.testing.assert_array_equal(dev.dof, np.full(3, 3 * 64 - 18, dtype=float))
    np.testing.assert_array_equal(dev.projection, cal.projection)
    np.testing.assert_array_equal(dev.installation, cal.installation)
    # four mounts decouple a…k from X almost entirely; a covariance where they are strongly coupled
    # (A Aᵀ, A random and seeded) tells the conditional from the marginal covariance
    a = np.random.default_rng(11).normal(size=(18, 18))
    coupled = a @ a.T + 0.1 * np.eye(18)
    dev = calibration_of_device(replace(device, covariance=coupled), readings)
    given = np.linalg.inv(np.linalg.inv(coupled)[6:, 6:])
    for j in range(3):
        idx = [3 * i + j for i in range(4)]
        np.testing.assert_allclose(dev.covariance[j], given[np.ix_(idx, idx)], rtol=1e-8)
        assert not np.allclose(dev.covariance[j], coupled[np.ix_([6 + i for i in idx], [6 + i for i in idx])],
                               rtol=0.1)


def test_the_estimators_weights_are_one_over_each_outputs_variance():
    """f = [1, g], C_j = c·I: fᵀC_j f = c(1 + |g|²) = 2c, plus one reading's σ²."""
    from labcal.analysis.budget import estimator_weights, regressors

    cal = _hand_cal(C_FIT)
    f = regressors(np.radians([10.0, 70.0]), np.radians([-30.0, 120.0]))
    np.testing.assert_allclose(f[:, 0], 1.0)
    np.testing.assert_allclose(f[0, 1:], _dg(np.radians(10.0), np.radians(-30.0))[0], rtol=1e-12)
    np.testing.assert_allclose(estimator_weights(cal, f), 1.0 / (2 * C_FIT + SIGMA**2), rtol=1e-12)


def test_type_a_rows_state_the_largest_standard_uncertainty():
    rows = {r.name: r for r in sources(_hand_cal(C_FIT), TypeBInputs())}
    assert rows["calibration fit (coefficients)"].u == pytest.approx(np.sqrt(C_FIT), rel=1e-12)
    assert rows["one new reading (instrument repeatability)"].u == pytest.approx(SIGMA, rel=1e-12)


def test_perfectly_correlated_coefficients_give_the_root_of_their_variance():
    """C = c·11ᵀ (rank one: eigenvalues 4c, 0, 0, 0, the zeros rounded to ±1e-20): each coefficient's u
    is √c, never NaN from the root of a rounding-negative eigenvalue."""
    cal = _hand_cal()
    cal = Calibration(**{**vars(cal), "covariance": np.stack([C_FIT * np.ones((4, 4))] * 3)})
    coef = coefficient_budget(sources(cal, TypeBInputs()))
    np.testing.assert_allclose(coef.u_c, np.sqrt(C_FIT), rtol=1e-9)


def test_dmm_noise_reaches_pitch_through_the_fits_covariance():
    """Noise σ on every reading of the calibration (6 points × 3 channels: 18 inputs, compressed to
    15 columns) moves X̂_j by P·δv_j, so v̂ = fᵀX̂ has variance σ² fᵀ(FᵀF)⁻¹f per sensor; with S = I
    and equal weights that is pitch's variance (|∂g/∂p| = 1) and roll's times 1/cos²p."""
    p, r = np.radians(40.0), np.radians(-10.0)
    cal = _hand_cal()
    out = propagate(cal, sources(cal, TypeBInputs(dmm_noise_v=2e-5)), p, r)
    F = _hand_design()
    f = np.concatenate([[1.0], _dg(p, r)[0]])
    u = 2e-5 * np.sqrt(f @ np.linalg.inv(F.T @ F) @ f)
    np.testing.assert_allclose(out.contributions["DMM noise"][0], [u, u / np.cos(p)], rtol=1e-9)
    np.testing.assert_allclose(out.u_c[0], [SIGMA, SIGMA / np.cos(p)], rtol=1e-9)  # shown, not added


def test_an_error_common_to_calibration_and_use_cancels():
    """An offset δ on channel 0 both when calibrating (B_0 fitted δ too high) and in use (the reading
    δ too high): the corrected output v − B does not move, so neither does the attitude."""
    jac_x = np.zeros((12, 1))
    jac_x[0, 0] = 1.0  # X[0, 0] = B_x
    jac_v = np.zeros((3, 1))
    jac_v[0, 0] = 1.0
    both = Source("both", "B", "normal", 1.0, "V", (Component(jac_x, jac_v, 1e-4, np.inf, "normal"),))
    use = Source("use", "B", "normal", 1.0, "V",
                 (Component(np.zeros((12, 1)), jac_v, 1e-4, np.inf, "normal"),))
    p, r = np.radians(20.0), np.radians(30.0)
    out = propagate(_hand_cal(), [both, use], p, r)
    np.testing.assert_allclose(out.contributions["both"][0], [0.0, 0.0], atol=1e-18)
    _, dp, dr = _dg(p, r)  # use alone: A·δv with δv = (1e-4, 0, 0)
    np.testing.assert_allclose(out.contributions["use"][0], 1e-4 * np.abs([dp[0], dr[0] / np.cos(p) ** 2]),
                               rtol=1e-9, atol=1e-18)


def test_mount_scatter_as_type_a_reaches_pitch_like_its_rectangular_equivalent():
    """A normal σ is the u of a rectangular ±σ√3: the same contribution to pitch and roll."""
    cal = calibration_of(fit_readings(READINGS), READINGS)
    at = (np.radians([25.0]), np.radians([40.0]))
    scatter = TypeBInputs(mount_repeatability_sd=2 * ARCSEC, mount_repeatability_dof=9)
    a = propagate(cal, sources(cal, scatter), *at)
    b = propagate(cal, sources(cal, TypeBInputs(mount_repeatability=2 * SQRT3 * ARCSEC)), *at)
    np.testing.assert_allclose(a.contributions["mount repeatability"], b.contributions["mount repeatability"],
                               rtol=1e-9)
    assert a.contributions["mount repeatability"].max() > 0.01 * ARCSEC


def test_welch_satterthwaite_counts_one_degree_of_freedom_and_stays_quiet():
    """Variances 1 (ν = 4), 2 (ν = 1), 1 (ν = ∞), u_c = 2: ν = 16 / (1/4 + 4/1) = 16/4.25. No part with
    finite ν: ∞, also for u_c = 0, and without a floating-point warning."""
    import warnings

    nu = welch_satterthwaite(np.array([2.0]), [(np.array([1.0]), 4.0), (np.array([2.0]), 1.0),
                                                (np.array([1.0]), np.inf)])
    assert nu[0] == pytest.approx(16 / 4.25, rel=1e-12)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert welch_satterthwaite(np.array([0.0, 1.0]), [(np.array([0.0, 1.0]), np.inf)]).tolist() == [
            np.inf, np.inf]
        assert welch_satterthwaite(np.array([0.0]), []).tolist() == [np.inf]


WORDING = {
    "calibration fit (coefficients)": "residual standard error, or the lack-of-fit mean square where "
                                      "replication shows bias (Tripp & Tcheng §8)",
    "DMM accuracy, % of reading": "independent between the channels; 10 V range at 10 PLC",
    "DMM accuracy, % of range": "independent between the channels; 10 V range at 10 PLC",
    "DMM noise": "included in the fit's Type A (the residuals contain it); not added again",
    "pitch table index accuracy": "a function of the table angle, repeated wherever the table returns to it: "
                                  "one error per angle, and harmonics 1–3 of the angle, each with the "
                                  "stated u (a rough and a smooth table)",
    "mount repeatability": "pitch, roll and yaw of the plate, one error per mounting; from the station "
                           "file (no mount was seated twice)",
    "temperature": "temperature coefficients × half the range observed during the run",
    "device misalignment estimates": "the device model's estimates of a…k, applied as corrections: each "
                                     "one's standard uncertainty from the joint fit, through the fit's "
                                     "projection (their correlations are not carried)",
    "local gravity": "where the instrument is used |g| may differ from the calibration's by up to ±0.0005 "
                     "(latitude, height): the sphere estimator takes |g| as unknown within that (a prior), "
                     "so it follows the direction; its share is what the prior leaves in pitch and roll",
}


def test_each_row_says_on_the_certificate_what_it_computed(cal):
    """The notes are statements the certificate makes; each is checked above against what the row
    does (not added, one input per table angle or mounting, the station file's value, …)."""
    inputs = TypeBInputs(dmm_noise_v=1e-5, dmm_conditions="10 V range at 10 PLC",
                         device_misalignment={"a": ARCSEC})
    rows = {r.name: r for r in sources(cal, inputs)}
    for name, note in WORDING.items():
        assert rows[name].note == note, name
    for name in ("pitch table wobble", "roll table index accuracy", "roll table wobble"):
        assert rows[name].note == WORDING["pitch table index accuracy"]
    # a scanning DMM's gain declared common (what it does to pitch and roll is checked above)
    common = {r.name: r for r in sources(cal, replace(inputs, common=("dmm_reading",)))}
    assert common["DMM accuracy, % of reading"].note == ("one error common to the three channels (one ADC "
                                                         "scans them); 10 V range at 10 PLC")
    assert common["DMM accuracy, % of range"].note == WORDING["DMM accuracy, % of range"]
    assert _row(sources(cal, TypeBInputs()), "DMM accuracy, % of reading").note == \
        "independent between the channels"  # no conditions stated: no dangling "; "
    # readings without their windows' scatter: the row is the fit's residual, and says so
    assert rows["one new reading (instrument repeatability)"].note.startswith(
        "the fit's residual standard error: the readings do not carry the scatter inside their windows")
    assert (rows["DMM noise"].unit, rows["device misalignment estimates"].unit) == ("V", "arcsec")
    assert rows["local gravity"].added is True
    scattered = _row(sources(cal, TypeBInputs(mount_repeatability_sd=ARCSEC)), "mount repeatability")
    assert scattered.unit == "arcsec"
    assert scattered.note == ("pitch, roll and yaw of the plate, one error per mounting; from the "
                              "replicates' scatter of the mount groups (Tripp & Tcheng, marginal drift "
                              "component), not the station file")
    # the distribution each input is drawn from (Monte Carlo): Student t for the fit's Type A, normal
    # for a standard deviation, rectangular for a half-width
    kinds = {name: {c.distribution for c in r.components} for name, r in rows.items()}
    assert kinds["calibration fit (coefficients)"] == {"t"}
    assert kinds["one new reading (instrument repeatability)"] == {"t"}
    assert kinds["DMM noise"] == {"normal"} and kinds["device misalignment estimates"] == {"normal"}
    assert kinds["DMM accuracy, % of reading"] == kinds["mount repeatability"] == {"rectangular"}
    assert {c.distribution for c in scattered.components} == {"normal"}


def test_a_fit_with_temperature_terms_gives_the_budget_its_first_four_coefficients():
    """The base coefficients' covariance and projection are the leading 4×4 block and rows of the
    extended fit's (FᵀF)⁻¹ and (FᵀF)⁻¹Fᵀ, computed here with numpy from the design written out."""
    from labcal.analysis.models import Model

    temp = 20.0 + np.linspace(-2.0, 2.0, 24)
    noise = np.random.default_rng(3).normal(0.0, 1e-4, (24, 3))
    readings = Readings(replicate=np.ones(24, dtype=int), y_deg=_Y, u_deg=_U, pitch_deg=_P, roll_deg=_R,
                        volts=_volts() + noise, temp_c=temp)
    fit = fit_readings(readings, Model(extensions=("temperature",), t_ref=20.0))
    cal_t = calibration_of(fit, readings)
    g = DESIGN[:, 1:]
    F = np.column_stack([DESIGN, (temp - 20.0)[:, None], (temp - 20.0)[:, None] * g])
    inv = np.linalg.inv(F.T @ F)
    residuals = readings.volts - F @ np.linalg.lstsq(F, readings.volts, rcond=None)[0]
    s2 = np.sum(residuals**2, axis=0) / (24 - 8)
    assert cal_t.covariance.shape == (3, 4, 4) and cal_t.projection.shape == (4, 24)
    for j in range(3):
        np.testing.assert_allclose(cal_t.covariance[j], s2[j] * inv[:4, :4], rtol=1e-6)
    np.testing.assert_allclose(cal_t.projection, (inv @ F.T)[:4], rtol=1e-6, atol=1e-12)

"""σ_bias: labcal's convention against Tripp & Tcheng's Table 2, and noise-free
replicated readings accepted with a note.

The two conventions (labcal.analysis.replication's docstring derives them): labcal's σ̂_bias² =
(MS_LOF − MS_PE)/R is unbiased for the variance of a point bias; Table 2's is σ_E² − σ_prec², low by
(N − p)/(R(m − p)) — 1.056 for 64 points × 6 replicates. Expected values here come from the
published table, from sums of squares computed with numpy's own least squares in the test, and from
a Monte Carlo with a known σ_bias.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from labcal.analysis.replication import analyse, tripp_sigma_bias
from labcal.cli import main

# Tripp & Tcheng 1999, Table 2 (×10⁴, degrees): figure → (σ_E, σ_bias, σ_prec). Rows where σ_E
# carries no drift: 34 and 42 (sensor 2, strong drift), 28(a) (no temperature correction), the
# tumble rows of fig. 50 and fig. 35 are left out (their σ_E is not σ_bias² + σ_prec² to the
# table's digits, or only with drift in it).
TABLE_2 = {"22": (1.60, 0.431, 1.54), "24": (3.17, 2.62, 1.79), "26": (2.84, 2.20, 1.79),
           "28(b)": (3.87, 3.54, 1.56), "37": (4.89, 4.71, 1.31), "44(a)": (4.34, 4.10, 1.42),
           "44(b)": (4.44, 4.17, 1.54), "44(c)": (3.55, 3.11, 1.71), "47(a)": (4.09, 3.72, 1.71),
           "47(b)": (5.23, 5.08, 1.23), "47(c)": (4.79, 4.28, 2.15), "53 x": (4.12, 3.78, 1.65),
           "53 y": (5.64, 5.51, 1.23), "53 z": (4.79, 4.23, 2.24)}


def _half_digit(x: float) -> float:
    """Half a unit in the last of three significant digits: the table's rounding."""
    return 0.5 * 10 ** (math.floor(math.log10(x)) - 2)


@pytest.mark.parametrize("figure", sorted(TABLE_2))
def test_table_2_states_sigma_bias_as_the_residual_variance_less_precision(figure):
    """Tripp's convention, read off the published numbers: σ_E² = σ_bias² + σ_prec² to rounding."""
    e, b, p = TABLE_2[figure]
    rounding = sum(2 * x * _half_digit(x) for x in (e, b, p))
    assert abs(e**2 - b**2 - p**2) <= rounding


def _balanced(m: int, r: int, sigma_e: float, sigma_prec: float, seed: int = 0):
    """Readings of m points × r replicates, p = 4 coefficients, whose residual mean square is exactly
    σ_E² and pure-error mean square exactly σ_prec² (the biases orthogonal to the model)."""
    rng = np.random.default_rng(seed)
    j_m = np.column_stack([np.ones(m), rng.normal(size=(m, 3))])
    q, _ = np.linalg.qr(j_m)
    beta = rng.normal(size=m)
    beta -= q @ (q.T @ beta)  # orthogonal to the model: all of it is lack of fit
    n, p = m * r, j_m.shape[1]
    beta *= math.sqrt(((n - p) * sigma_e**2 - (n - m) * sigma_prec**2) / r) / np.linalg.norm(beta)
    eps = rng.normal(size=(r, m))
    eps -= eps.mean(axis=0)  # pure error: zero mean at every point
    eps *= math.sqrt((n - m) * sigma_prec**2) / np.linalg.norm(eps)
    theta = np.array([0.01, 1.0, 0.02, -0.01])
    y = (j_m @ theta + beta)[None, :] + eps
    design = np.tile(j_m, (r, 1))
    groups = np.tile(np.arange(m), r)
    replicate = np.repeat(np.arange(1, r + 1), m)
    return design, y.reshape(-1, 1), groups, replicate


def test_labcals_sigma_bias_on_a_table_2_design_and_the_conversion_to_tripps():
    """Fig. 44(a): 247 points × 6 replicates, p = 4 (b, S, Ω, A), σ_E = 4.34e-4, σ_prec = 1.42e-4.
    Data with exactly those mean squares: numpy's least squares gives σ_E back, Table 2's convention
    σ_E² − σ_prec² gives its σ_bias = 4.10e-4, labcal's is (MS_LOF − MS_PE)/R by hand, and
    `tripp_sigma_bias` maps labcal's onto the table's."""
    m, r, p = 247, 6, 4
    sigma_e, table_bias, sigma_prec = (x * 1e-4 for x in TABLE_2["44(a)"])
    design, y, groups, replicate = _balanced(m, r, sigma_e, sigma_prec)
    _, ss_res, *_ = np.linalg.lstsq(design, y, rcond=None)
    n = m * r
    assert math.sqrt(ss_res[0] / (n - p)) == pytest.approx(sigma_e, rel=1e-9)
    rep = analyse(design, y, groups, replicate)
    assert rep.sigma_prec[0] == pytest.approx(sigma_prec, rel=1e-9)
    tripp = math.sqrt(sigma_e**2 - rep.sigma_prec[0] ** 2)
    assert abs(tripp - table_bias) <= 2 * _half_digit(4.10) * 1e-4  # the published 4.10
    ms_lof = (ss_res[0] - (n - m) * sigma_prec**2) / (m - p)
    assert rep.sigma_bias[0] == pytest.approx(math.sqrt((ms_lof - sigma_prec**2) / r), rel=1e-9)
    assert rep.sigma_bias[0] ** 2 / tripp**2 == pytest.approx((n - p) / (r * (m - p)), rel=1e-9)
    assert float(tripp_sigma_bias(rep.sigma_bias[0], m, r, p)) == pytest.approx(tripp, rel=1e-9)


def test_the_unbiased_convention_by_monte_carlo_and_the_1_056_factor_for_64_by_6():
    """y = f + β + ε with known σ_bias = σ_prec: labcal's σ̂_bias² averages to σ_bias² (unbiased),
    Table 2's to σ_bias²·R(m − p)/(N − p) = σ_bias²/1.0556 for 64 × 6. 4000 trials at once (the
    analysis is vectorised over columns): the mean's standard error is about 0.4 %."""
    m, r, p, trials = 64, 6, 4, 4000
    rng = np.random.default_rng(23)
    j_m = np.column_stack([np.ones(m), rng.normal(size=(m, 3))])
    sigma_bias = sigma_prec = 1e-4
    y = (j_m @ np.array([0.0, 1.0, 0.0, 0.0]))[None, :, None] \
        + rng.normal(0, sigma_bias, (1, m, trials)) + rng.normal(0, sigma_prec, (r, m, trials))
    y = y.reshape(m * r, trials)
    rep = analyse(np.tile(j_m, (r, 1)), y, np.tile(np.arange(m), r), np.repeat(np.arange(1, r + 1), m))
    ours = np.mean(rep.sigma_bias**2) / sigma_bias**2
    theirs = np.mean(tripp_sigma_bias(rep.sigma_bias, m, r, p) ** 2) / sigma_bias**2
    factor = (m * r - p) / (r * (m - p))
    assert factor == pytest.approx(1.0556, abs=1e-4)
    se = np.std(rep.sigma_bias**2) / sigma_bias**2 / math.sqrt(trials)
    assert abs(ours - 1.0) < 4 * se
    assert abs(theirs - 1 / factor) < 4 * se and 1.0 - theirs > 8 * se


def test_a_noise_free_replicated_file_is_accepted_with_a_note(tmp_path, capsys):
    """`labcal simulate --noise 0 --replicates 2` then `labcal fit`: the replicates repeat exactly, so
    pure error is zero; before, every F test divided by it and every reading was flagged (exit 2)."""
    readings = tmp_path / "exact.csv"
    assert main(["simulate", "--noise", "0", "--replicates", "2", "--out", str(readings)]) == 0
    capsys.readouterr()
    for model in ("linear", "device"):
        assert main(["fit", str(readings), "--model", model, "--json"]) == 0
        captured = capsys.readouterr()
        assert captured.err == ""  # no division warnings
        doc = json.loads(captured.out)
        assert doc["gross_errors"] == []
        assert any(n.startswith("noise-free readings for sensor(s) x, y, z") for n in doc["notes"])
    linear = main(["fit", str(readings), "--model", "linear", "--json"])
    doc = json.loads(capsys.readouterr().out)
    assert linear == 0
    for r in doc["replication"].values():
        assert r["lack_of_fit"]["F"] is None and r["lack_of_fit"]["significant"] is False
    # with noise, nothing changes: the tests are made
    noisy = tmp_path / "noisy.csv"
    assert main(["simulate", "--noise", "1e-5", "--replicates", "2", "--out", str(noisy)]) == 0
    capsys.readouterr()
    assert main(["fit", str(noisy), "--model", "linear", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert all(r["lack_of_fit"]["F"] is not None for r in doc["replication"].values())
    assert not any(n.startswith("noise-free") for n in doc.get("notes", []))

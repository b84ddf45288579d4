"""Gross-error checks: good data is flagged at no more than the stated rate (Monte Carlo),
and the blunders a technician makes are flagged, by row."""

from __future__ import annotations

import pytest

from labcal.analysis.fit import fit_readings
from labcal.analysis.gross_errors import FAMILY_ALPHA, fit_flags
from labcal.analysis.readings import Readings
from labcal.config.emulation import InstrumentTruth
from labcal.config.plans import load_plan
from labcal.sim.direct import simulate_readings

TRUTH = InstrumentTruth(B=[0.01, -0.02, 0.005],
                        S=[[5.0, 0.01, -0.02], [0.015, 4.9, 0.01], [-0.01, 0.02, 5.1]])
NOISE_V = 1e-4


def good_readings(seed: int, plan: str = "four-mount-64") -> Readings:
    return simulate_readings(load_plan(plan)[0], TRUTH, noise_v=NOISE_V, seed=seed)


@pytest.mark.parametrize("alpha,trials", [(0.05, 150), (FAMILY_ALPHA, 50)])
def test_good_data_is_flagged_at_no_more_than_the_stated_rate(alpha, trials):
    """Each check's family-wise false-alarm rate ≤ alpha: the count of flagged files in `trials`
    files of good readings stays below the binomial 99.9 % upper bound of Bin(trials, alpha)."""
    from scipy.stats import binom

    flagged = {"gravity": 0, "mount": 0, "residual": 0}
    for seed in range(trials):
        readings = good_readings(seed)
        for check in {f.check for f in fit_flags(readings, fit_readings(readings), alpha)}:
            flagged[check] += 1
    bound = binom.ppf(0.999, trials, alpha)
    assert all(n <= bound for n in flagged.values()), (flagged, bound)
    if alpha == 0.05:  # and the residual test is not vacuous: it does flag at about its rate
        assert flagged["residual"] >= binom.ppf(0.001, trials, alpha / 2), flagged


def _with(readings: Readings, **arrays) -> Readings:
    from dataclasses import replace

    return replace(readings, **arrays)


def test_a_missed_remount_is_named_by_its_rows():
    readings = good_readings(1)
    volts = readings.volts.copy()
    volts[16:32] = volts[0:16]  # mount 2 (y=180) read while the instrument still sat as mount 1
    flags = fit_flags(bad := _with(readings, volts=volts), fit_readings(bad))
    assert {f.row for f in flags} == set(range(17, 33)) and {f.check for f in flags} == {"mount"}
    assert "readings 17–32 (replicate 1) are labelled mount y=180 u=0 but read like mount y=0 u=0" \
        in flags[0].message


@pytest.mark.parametrize("row,volts", [
    (10, [0.0, 0.0, 0.0]),  # a dead input
    (40, [2.5, 2.5, 2.5]),  # |g| ≈ 0.87 g, inflating S_E: its residuals stand out instead
])
def test_a_reading_that_is_not_1_g_is_flagged_with_its_row(row, volts):
    readings = good_readings(2)
    v = readings.volts.copy()
    v[row - 1] = volts
    flags = fit_flags(bad := _with(readings, volts=v), fit_readings(bad))
    assert {f.row for f in flags} == {row}


def test_a_small_blunder_shows_as_a_residual_beyond_the_limit():
    readings = good_readings(3)
    v = readings.volts.copy()
    v[20, 1] += 30 * NOISE_V  # 30 σ on one sensor: |g| changes by 6e-4 g, too little for the 1 g test
    flags = fit_flags(bad := _with(readings, volts=v), fit_readings(bad))
    assert [(f.row, f.check) for f in flags] == [(21, "residual")]
    assert "sensor y: residual" in flags[0].message


def test_each_group_left_out_by_downdating_is_the_qr_fit_of_the_other_groups():
    """The mount check's fit of every other group (downdated from one fit of all the rows) against
    a QR fit of those rows themselves: the same coefficients, covariance and S_E to 1e-8 relative
    (the downdate works at the residuals' scale; double rounding leaves ~1e-12 here)."""
    import numpy as np

    from labcal.analysis.fit import readings_points
    from labcal.analysis.gross_errors import _batches_of_equal_groups, _leave_group_out
    from labcal.analysis.models import Model
    from labcal.analysis.regression import least_squares

    readings = simulate_readings(load_plan("four-mount-64")[0].model_copy(update={"replicates": 2}),
                                 TRUTH, noise_v=NOISE_V, seed=5)
    _, design = Model().design(readings_points(readings))
    index = np.unique(np.column_stack([readings.replicate, readings.y_deg, readings.u_deg]), axis=0,
                      return_inverse=True)[1].ravel()
    n_groups = int(index.max()) + 1
    coefs, covs, ses, determined = _leave_group_out(design, readings.volts,
                                                    least_squares(design, readings.volts), index, n_groups,
                                                    _batches_of_equal_groups(index, n_groups))
    assert determined.all()
    for k, (coef, cov, se) in enumerate(zip(coefs, covs, ses, strict=True)):
        ls = least_squares(design[index != k], readings.volts[index != k])
        for mine, qr in ((coef, ls.coef), (cov, ls.cov_unscaled), (se, ls.residual_se)):
            assert np.allclose(mine, qr, rtol=1e-8, atol=1e-8 * np.max(np.abs(qr)))

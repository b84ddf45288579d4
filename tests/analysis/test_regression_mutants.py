"""The least-squares core at its edges, each expected value worked by hand in the test.

Written against the mutants that survived the regression tests (docs/mutation.md): a square design,
the covariance of one column, float32 input, badly scaled columns, a column of rounding noise, and the
rank threshold on either side of it.
"""

from __future__ import annotations

import numpy as np
import pytest

from labcal.analysis.regression import least_squares, least_squares_of_means
from labcal.errors import LabcalError

# A straight line through (0, 0), (1, 1), (2, 3), by hand:
#   FᵀF = [[3, 3], [3, 5]], det 6, (FᵀF)⁻¹ = [[5/6, −1/2], [−1/2, 1/2]], FᵀY = [4, 7]
#   coef = (FᵀF)⁻¹ FᵀY = [−1/6, 3/2]; residuals [1/6, −1/3, 1/6]; eᵀe = 1/6 on 3 − 2 = 1 dof.
LINE_F = np.array([[1.0, 0.0], [1.0, 1.0], [1.0, 2.0]])
LINE_Y = np.array([0.0, 1.0, 3.0])
LINE_INV = np.array([[5 / 6, -1 / 2], [-1 / 2, 1 / 2]])


def test_covariance_of_each_column_is_its_own_residual_variance_times_the_inverse():
    """Second sensor = 2 × the first: same (FᵀF)⁻¹, S_E² four times as large (4/6)."""
    ls = least_squares(LINE_F, np.column_stack([LINE_Y, 2 * LINE_Y]))
    assert np.allclose(ls.coef[:, 0], [-1 / 6, 3 / 2], rtol=1e-13)
    assert np.allclose(ls.residuals[:, 0], [1 / 6, -1 / 3, 1 / 6], atol=1e-14)
    assert np.allclose(ls.covariance(0), LINE_INV / 6, rtol=1e-12)
    assert np.allclose(ls.covariance(1), 4 * LINE_INV / 6, rtol=1e-12)
    assert np.allclose(ls.stderr[:, 1], np.sqrt(np.diag(LINE_INV) * 4 / 6), rtol=1e-12)


def test_float32_input_is_solved_in_double_precision():
    """The values are exact in float32; a float32 QR would leave errors of ~1e-7, double ~1e-16."""
    ls = least_squares(LINE_F.astype(np.float32), LINE_Y.astype(np.float32))
    assert ls.coef.dtype == np.float64
    assert np.allclose(ls.coef[:, 0], [-1 / 6, 3 / 2], rtol=1e-14, atol=1e-15)


def test_a_square_design_is_solved_exactly_with_no_degree_of_freedom():
    """As many points as coefficients: the line through (0, 1) and (2, 5) is 1 + 2x, no S_E."""
    ls = least_squares(np.array([[1.0, 0.0], [1.0, 2.0]]), np.array([1.0, 5.0]))
    assert np.allclose(ls.coef[:, 0], [1.0, 2.0], rtol=1e-14)
    assert ls.dof == 0
    assert np.isnan(ls.residual_se).all()


def test_too_few_points_says_how_many_and_what_to_do():
    with pytest.raises(LabcalError) as err:
        least_squares(np.ones((2, 3)), np.ones(2))
    assert str(err.value) == ("2 points cannot determine 3 coefficients per sensor; "
                              "add points or mounts to the plan")


def test_columns_far_apart_in_scale_are_fitted_to_full_precision():
    """Columns of size 1e5 and 1e-6 (norms 2e5 and 3.7e-6, a ratio of 2e-11: well above the 1e-12 of a
    zero column): unscaled, σ_min/σ_max ≈ 1e-11 would look singular (RANK_TOLERANCE 1e-10); scaled to unit
    columns the design is well posed: y = 1 + x is 1e-5 of the first column plus 1e6 of the second."""
    x = np.array([0.0, 1.0, 2.0, 3.0])
    F = np.column_stack([1e5 * np.ones(4), 1e-6 * x])
    ls = least_squares(F, 1.0 + x)
    assert np.allclose(ls.coef[:, 0], [1e-5, 1e6], rtol=1e-12)


def _angle_design(theta: float) -> np.ndarray:
    """Two unit columns at angle θ: FᵀF = [[1, cos θ], [cos θ, 1]], singular values √(1 ± cos θ),
    so σ_min/σ_max = tan(θ/2) ≈ θ/2 (here cos θ rounds to 1, the second row carries sin θ = θ)."""
    return np.array([[1.0, 1.0], [0.0, theta], [0.0, 0.0]])


def test_rank_threshold_is_relative_to_the_largest_singular_value():
    """RANK_TOLERANCE = 1e-10 of σ_max: θ = 1.5e-10 gives σ_min/σ_max = 0.75e-10 (refused),
    θ = 3e-10 gives 1.5e-10 (fitted, coefficients by back substitution: y = (2, θ, 0) → (1, 1))."""
    with pytest.raises(LabcalError) as err:
        least_squares(_angle_design(1.5e-10), np.array([2.0, 1.5e-10, 0.0]))
    assert str(err.value) == ("the points do not determine all 2 coefficients (the design is singular); "
                              "spread the points over more pitch and roll angles")
    ls = least_squares(_angle_design(3e-10), np.array([2.0, 3e-10, 0.0]))
    assert np.allclose(ls.coef[:, 0], [1.0, 1.0], rtol=1e-5)


def test_a_column_of_rounding_noise_is_refused_at_any_scale():
    """A column 1e-13 the size of the largest (norm 2.7e-7 beside 3.7e6: the rounding of quantities of
    size 1e6) is zero to rounding (ZERO_COLUMN = 1e-12 of the largest column), and the design singular,
    though column scaling alone would have blown it up to a column like any other."""
    x = np.array([0.0, 1.0, 2.0, 3.0])
    noise = 1e-7 * np.array([1.0, -2.0, 1.5, 0.5])  # norm 2.7e-7; 1e6·x has norm 1e6·√14 = 3.7e6
    F = np.column_stack([1e6 * np.ones(4), 1e6 * x, noise])
    with pytest.raises(LabcalError, match="do not determine all 3 coefficients"):
        least_squares(F, x)


def test_an_all_zero_design_is_refused_not_divided_by_zero():
    with pytest.raises(LabcalError, match="do not determine all 2 coefficients"):
        least_squares(np.zeros((4, 2)), np.ones(4))


def test_fit_of_means_matches_the_fit_of_every_reading_by_hand():
    """Points x = 0 (readings 1, 3) and x = 1 (reading 5): the line through the means is 2 + 3x.
    F of the readings has rows (1,0), (1,0), (1,1): FᵀF = [[3, 1], [1, 1]], inverse ½[[1, −1], [−1, 3]];
    residuals (−1, 1, 0), eᵀe = 2 on 3 − 2 = 1 dof."""
    ls = least_squares_of_means(np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([[2.0], [5.0]]),
                                np.array([2.0, 1.0]), np.array([[1.0], [3.0], [5.0]]), np.array([0, 0, 1]))
    assert np.allclose(ls.coef[:, 0], [2.0, 3.0], rtol=1e-14)
    assert np.allclose(ls.cov_unscaled, [[0.5, -0.5], [-0.5, 1.5]], rtol=1e-13)
    assert np.allclose(ls.residuals[:, 0], [-1.0, 1.0, 0.0], atol=1e-14)
    assert ls.dof == 1


def test_fit_of_means_with_as_many_readings_as_coefficients():
    ls = least_squares_of_means(np.array([[1.0, 0.0], [1.0, 1.0]]), np.array([[2.0], [5.0]]),
                                np.array([1.0, 1.0]), np.array([[2.0], [5.0]]), np.array([0, 1]))
    assert np.allclose(ls.coef[:, 0], [2.0, 3.0], rtol=1e-14)
    assert ls.dof == 0


def test_fit_of_means_refuses_too_few_readings_and_too_few_points():
    with pytest.raises(LabcalError) as err:
        least_squares_of_means(np.array([[1.0, 0.0]]), np.array([[2.0]]), np.array([1.0]),
                               np.array([[2.0]]), np.array([0]))
    assert str(err.value).startswith("1 points cannot determine 2 coefficients per sensor")
    with pytest.raises(LabcalError) as err:  # three readings, all at one point
        least_squares_of_means(np.array([[1.0, 0.0]]), np.array([[2.0]]), np.array([3.0]),
                               np.array([[1.0], [2.0], [3.0]]), np.array([0, 0, 0]))
    assert str(err.value).startswith("the points do not determine all 2 coefficients")

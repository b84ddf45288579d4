"""The closed forms and groupings that make a million-row fit fast, against the general code."""

from __future__ import annotations

import numpy as np

from labcal.analysis.kinematics import gravity, nominal_gravity
from labcal.analysis.replication import point_groups


def test_nominal_gravity_in_closed_form_is_the_chain_with_no_misalignment():
    rng = np.random.default_rng(2)
    angles = rng.uniform(-2 * np.pi, 2 * np.pi, (4, 500))
    assert np.max(np.abs(nominal_gravity(*angles) - gravity(*angles))) < 1e-15
    mounts = np.radians([[0, 0], [180, 0], [0, 180], [180, 180]])
    for y, u in mounts:
        assert np.max(np.abs(nominal_gravity(*angles[:2], y, u) - gravity(*angles[:2], y, u))) < 1e-15


def test_point_groups_number_the_distinct_rows_as_numpy_unique_does():
    rng = np.random.default_rng(3)
    keys = rng.integers(-3, 3, (2000, 4)).astype(float) * 30.0
    inverse, n = point_groups(keys)
    expected_unique, expected_inverse = np.unique(keys, axis=0, return_inverse=True)
    assert n == len(expected_unique) and np.array_equal(inverse, expected_inverse.ravel())

"""Rotation signs, the nominal gravity formula, the mounts and the index/wobble model."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from labcal.analysis.kinematics import (
    ARCSEC,
    MOUNTS,
    IndexWobble,
    Misalignment,
    Mount,
    device_matrix,
    gravity,
    prot,
    rrot,
    yrot,
)

deg = st.floats(min_value=-360, max_value=360, allow_nan=False)


@given(deg, deg)
def test_nominal_gravity_is_design_formula(p_deg, r_deg):
    p, r = np.radians([p_deg, r_deg])
    expected = [np.sin(p), np.cos(p) * np.sin(r), np.cos(p) * np.cos(r)]
    assert np.allclose(gravity(p, r, 0, 0), expected, atol=1e-15)


def test_level_instrument_reads_plus_one_g_on_z():
    assert np.allclose(gravity(0, 0, 0, 0), [0, 0, 1], atol=0)


def test_aeronautical_signs():
    """prot = Ry(-x), rrot = Rx(x), yrot = Rz(-x): nose-up pitch puts +g on x."""
    q = np.radians(90)
    assert np.allclose(prot(q), [[0, 0, -1], [0, 1, 0], [1, 0, 0]], atol=1e-15)
    assert np.allclose(rrot(q), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-15)
    assert np.allclose(yrot(q), [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    assert np.allclose(gravity(q, 0, 0, 0), [1, 0, 0], atol=1e-15)


@given(deg, deg)
def test_mounts_flip_the_expected_axes(p_deg, r_deg):
    p, r = np.radians([p_deg, r_deg])
    gx, gy, gz = gravity(p, r, 0, 0)
    assert np.allclose(gravity(p, r, np.pi, 0), [-gx, -gy, gz], atol=1e-15)  # backward: x, y reversed
    assert np.allclose(gravity(p, r, 0, np.pi), [gx, -gy, -gz], atol=1e-15)  # bottom: y, z reversed
    assert np.allclose(gravity(p, r, np.pi, np.pi), [-gx, gy, -gz], atol=1e-15)


@given(*(st.floats(-0.01, 0.01) for _ in range(6)), deg, deg)
def test_device_matrix_is_a_rotation(a, b, d, e, f, k, p_deg, r_deg):
    km = device_matrix(*np.radians([p_deg, r_deg]), 0, 0, Misalignment(a, b, d, e, f, k))
    assert np.allclose(km @ km.T, np.eye(3), atol=1e-14)
    assert np.isclose(np.linalg.det(km), 1.0, atol=1e-14)


def test_vectorised_over_points_with_per_point_misalignment():
    p = np.radians([0, 30, 60])
    r = np.radians([10, 20, 30])
    mis = Misalignment(a=np.array([1e-5, 2e-5, 3e-5]))
    batch = gravity(p, r, 0, 0, mis)
    one_by_one = [gravity(p[i], r[i], 0, 0, Misalignment(a=mis.a[i])) for i in range(3)]
    assert np.allclose(batch, one_by_one, atol=0)


def test_mount_words():
    words = [m.describe() for m in MOUNTS]
    assert words == [
        "top side of the plate, x sensor pointing forward",
        "top side of the plate, x sensor pointing backward",
        "bottom side of the plate, x sensor pointing forward",
        "bottom side of the plate, x sensor pointing backward",
    ]
    assert str(Mount(180, 0)) == "y=180°, u=0°"


@pytest.mark.parametrize("index,wobble", [(2.0, 5.0), (1.0, 0.0)])
def test_index_wobble_bounded_and_zero_mean_over_soto_points(index, wobble):
    iw = IndexWobble(index, wobble, seed=3)
    circle = np.radians(np.arange(360))
    mis = iw.misalignment(circle, circle)
    for name, amp in (("a", index), ("d", wobble), ("e", wobble), ("k", wobble)):
        values = getattr(mis, name)
        assert np.max(np.abs(values)) <= amp * ARCSEC * (1 + 1e-12)
        assert abs(np.mean(values)) < 1e-15
        quarter = getattr(iw.misalignment(np.radians([17, 107, 197, 287]), 0), name) if name in "ad" else None
        if quarter is not None:
            assert abs(np.mean(quarter)) < 1e-18
    # a table returns to the same error at the same angle
    again = IndexWobble(index, wobble, seed=3).misalignment(circle, circle)
    assert np.array_equal(again.f, mis.f)
    if wobble:
        assert np.max(np.abs(mis.d)) > 0.3 * wobble * ARCSEC  # not trivially zero

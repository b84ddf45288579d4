"""Soto (2020) §7: the closed-form coefficients an ideal instrument gets on a misaligned CD.

Every case goes through the product's own path (plan → simulated readings → fit) and must
match the paper's symbolic result to 1e-12 for any misalignments up to 0.5°. X rows are
[B; Sxx Syx Szx; Sxy Syy Szy; Sxz Syz Szz] (Soto eq. 15).
"""

from __future__ import annotations

import numpy as np
from conftest import FOUR_MOUNTS, ideal_fit
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy import cos, sin

from labcal.analysis.kinematics import Misalignment

TOL = 1e-12
angle = st.floats(min_value=-0.5, max_value=0.5, allow_nan=False)  # degrees
misalignments = st.fixed_dictionaries({n: angle for n in "abdefk"})
ONE_MOUNT = [(0, 0)]
Y_PAIR = [(0, 0), (180, 0)]  # §6.2 / §7.4.2: add the backward mount
U_PAIR = [(0, 0), (180, 180)]  # §6.3: bottom side, backward (preferred)


def diag(sxx, syy, szz) -> np.ndarray:
    return np.array([[0, 0, 0], [sxx, 0, 0], [0, syy, 0], [0, 0, szz]], dtype=float)


def rad(m: dict[str, float], names: str) -> Misalignment:
    return Misalignment.from_degrees(**{n: m[n] for n in names})


@settings(max_examples=40, deadline=None)
@given(misalignments)
def test_single_misalignments_eqs_23_to_27(m):
    a, b, d, e, f, k = np.radians([m[n] for n in "abdefk"])
    assert np.allclose(ideal_fit(ONE_MOUNT, rad(m, "a")), diag(cos(a), cos(a), cos(a)), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit(ONE_MOUNT, rad(m, "b")), diag(cos(b), cos(b), cos(b)), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit(ONE_MOUNT, rad(m, "d")), diag(cos(d), 1, 1), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit(Y_PAIR, rad(m, "e")), diag(cos(e), 1, cos(e)), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit(Y_PAIR, rad(m, "f")), diag(1, cos(f), cos(f)), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit(U_PAIR, rad(m, "k")), diag(cos(k), cos(k), 1), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit([(0, 0), (0, 180)], rad(m, "k")), diag(cos(k), cos(k), 1), atol=TOL, rtol=0)


@settings(max_examples=40, deadline=None)
@given(misalignments)
def test_combinations_eqs_28_29_and_table_4(m):
    a, b, d, e, f, k = np.radians([m[n] for n in "abdefk"])
    cab = cos(a) * cos(b)
    assert np.allclose(ideal_fit(ONE_MOUNT, rad(m, "ab")), diag(cab, cab, cab), atol=TOL, rtol=0)
    assert np.allclose(ideal_fit(Y_PAIR, rad(m, "abd")), diag(cab * cos(d), cab, cab), atol=TOL, rtol=0)
    syy = cab * cos(f) - cos(b) * sin(a) * sin(d) * sin(f)  # Table 4: S_yy = S_zz
    assert np.allclose(ideal_fit(Y_PAIR, rad(m, "abdf")), diag(cab * cos(d), syy, syy), atol=TOL, rtol=0)


def table_5_to_7(a, b, d, e, f, k) -> np.ndarray:
    """Soto Tables 5–7: one mount, every misalignment (eq. 31)."""
    ca, cb, cd, ce, cf, ck = cos([a, b, d, e, f, k])
    sa, sb, sd, se, sf, sk = sin([a, b, d, e, f, k])
    bx, by, bz = -ce * ck * sb * sd, -ce * sb * sd * sk, sb * sd * se
    sxx = ca * cb * cd * ce * ck
    sxy = -cb * cf * ck * sa * sd * se - ca * cb * ck * se * sf - ca * cb * cf * sk + cb * sa * sd * sf * sk
    sxz = ca * cb * cf * ck * se - cb * ck * sa * sd * se * sf - cb * cf * sa * sd * sk - ca * cb * sf * sk
    syx = ca * cb * cd * ce * sk
    syy = ca * cb * cf * ck - cb * ck * sa * sd * sf - cb * cf * sa * sd * se * sk - ca * cb * se * sf * sk
    syz = cb * cf * ck * sa * sd + ca * cb * ck * sf + ca * cb * cf * se * sk - cb * sa * sd * se * sf * sk
    szx = -ca * cb * cd * se
    szy = -cb * ce * cf * sa * sd - ca * cb * ce * sf
    szz = ca * cb * ce * cf - cb * ce * sa * sd * sf
    return np.array([[bx, by, bz], [sxx, syx, szx], [sxy, syy, szy], [sxz, syz, szz]])


@settings(max_examples=60, deadline=None)
@given(misalignments)
def test_one_mount_tables_5_to_7(m):
    angles = np.radians([m[n] for n in "abdefk"])
    assert np.allclose(ideal_fit(ONE_MOUNT, rad(m, "abdefk")), table_5_to_7(*angles), atol=TOL, rtol=0)


@settings(max_examples=60, deadline=None)
@given(misalignments)
def test_four_mounts_table_8_zero_bias_and_off_diagonals(m):
    a, b, d, e, f, k = np.radians([m[n] for n in "abdefk"])
    X = ideal_fit(FOUR_MOUNTS, rad(m, "abdefk"))
    sxx = cos(a) * cos(b) * cos(d) * cos(e) * cos(k)
    syy = (cos(a) * cos(b) * cos(f) * cos(k) - cos(b) * cos(k) * sin(a) * sin(d) * sin(f)
           - cos(b) * cos(f) * sin(a) * sin(d) * sin(e) * sin(k) - cos(a) * cos(b) * sin(e) * sin(f) * sin(k))
    szz = cos(a) * cos(b) * cos(e) * cos(f) - cos(b) * cos(e) * sin(a) * sin(d) * sin(f)
    assert np.allclose(X, diag(sxx, syy, szz), atol=TOL, rtol=0)


def test_one_mount_leaks_e_f_k_to_first_order_eq_33():
    """Eq. 33: to first order one mount gives S = [[1, k, -e], [-k, 1, -f], [e, f, 1]] (rows of X)."""
    m = {"a": 0.01, "b": -0.02, "d": 0.015, "e": 0.3, "f": -0.2, "k": 0.25}
    e, f, k = np.radians([m["e"], m["f"], m["k"]])
    expected = np.array([[0, 0, 0], [1, k, -e], [-k, 1, -f], [e, f, 1]])
    X = ideal_fit(ONE_MOUNT, rad(m, "abdefk"))
    # second-order terms: products of two misalignments ≤ (0.3°)² ≈ 3e-5 rad²
    assert np.allclose(X, expected, atol=5e-5, rtol=0)
    assert abs(X[2, 0] + k) < 5e-5 and abs(X[3, 0] - e) < 5e-5 and abs(X[3, 1] - f) < 5e-5


def test_table_8_simplified_syy_is_third_order_not_exact():
    """Soto Table 8 also writes S_yy = cos a cos b cos f cos k. The fit matches the full
    expression (tested above); the short form drops the third-order products, so it differs
    from the fit by sin a sin d sin f + sin e sin f sin k (to leading order)."""
    m = {"a": 0.5, "b": 0.1, "d": 0.5, "e": 0.5, "f": 0.5, "k": 0.5}
    a, b, d, e, f, k = np.radians([m[n] for n in "abdefk"])
    syy = ideal_fit(FOUR_MOUNTS, rad(m, "abdefk"))[2, 1]
    short = cos(a) * cos(b) * cos(f) * cos(k)
    dropped = sin(a) * sin(d) * sin(f) + sin(e) * sin(f) * sin(k)  # ≈ 1.3e-6
    assert abs((short - syy) - dropped) < 0.01 * dropped  # the rest is fifth order

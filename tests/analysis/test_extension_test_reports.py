"""Defects a type checker (mypy, pyproject.toml) found: each test fails on the code before its fix."""

from __future__ import annotations

import numpy as np

from labcal.analysis.fit import ExtensionTest


def test_extension_test_without_a_statistic_reports_untested_instead_of_crashing():
    # reason None but no F statistic: to_json called .tolist() on None
    assert ExtensionTest("harmonics", None).to_json() == {
        "tested": False, "reason": "no F statistic was computed"}
    assert ExtensionTest("harmonics", None).p_value is None


def test_extension_test_with_a_statistic_but_no_degrees_of_freedom_has_no_p_value():
    # p_value splatted *None into f_sf
    test = ExtensionTest("harmonics", None, f=np.array([1.0, 2.0, 3.0]))
    assert test.p_value is None
    assert test.to_json()["tested"] is False


def test_tested_extension_reports_its_statistics():
    doc = ExtensionTest("harmonics", None, np.array([0.5, 50.0, 1.0]), (4, 20), ("cos 2R",)).to_json()
    assert doc["tested"] is True and doc["df"] == [4, 20] and doc["aliased_terms"] == ["cos 2R"]
    assert doc["warranted"] == [False, True, False]
    assert np.allclose(doc["p_value"][1], 0.0, atol=1e-9)

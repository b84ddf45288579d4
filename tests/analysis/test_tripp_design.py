"""Tripp & Tcheng's experimental-design results: Table 1, eqs. 66, 69 and 109; and the plan audit."""

from __future__ import annotations

import numpy as np
import pytest

from labcal.analysis.design import (
    audit,
    audit_summary,
    d1,
    figure_of_merit,
    fractional,
    fractional_size,
    make_plan,
    normalised_variance,
    tripp_table_1,
    tumble,
)
from labcal.config.plans import load_plan, parse_plan, plan_toml

# Tripp Table 1, columns 2–5: design D1, M = 64, N = 33; V^½ over the calibration range and
# V_R^½ over the usage range −30°..30°.
TABLE_1 = [(30, 1.989, None), (45, 1.993, 1.927), (90, 2.008, 2.222), (180, 1.993, 2.174)]


@pytest.mark.parametrize("pitch_max,v_sqrt,v_r_sqrt", TABLE_1)
def test_table_1_figure_of_merit(pitch_max, v_sqrt, v_r_sqrt):
    plan = make_plan("d1", "", d1(pitch_max, 33, 64), four_mounts=False)
    assert round(figure_of_merit(plan, (-pitch_max, pitch_max)) ** 0.5, 3) == v_sqrt
    if v_r_sqrt is not None:
        assert round(figure_of_merit(plan, (-30, 30)) ** 0.5, 3) == v_r_sqrt


# Tripp Table 1, all eight columns (M = 64, N = 33; column 9: M = 65), as printed:
# column, V^½ over the calibration range, V_R^½ over the usage range and that range.
TABLE_1_ALL = [(2, 1.989, None, None), (3, 1.993, 1.927, (-30, 30)), (4, 2.008, 2.222, (-30, 30)),
               (5, 1.993, 2.174, (-30, 30)), (6, 2.127, 1.811, (-10, 10)), (7, 1.937, 1.834, (-10, 10)),
               (8, 1.941, 1.912, (-10, 10)), (9, 1.989, None, None)]


@pytest.mark.parametrize("column,v_sqrt,v_r_sqrt,usage", TABLE_1_ALL)
def test_plan_generate_makes_each_design_of_table_1_and_merit_gives_its_printed_values(
        tmp_path, capsys, column, v_sqrt, v_r_sqrt, usage):
    import json

    from labcal.cli import main

    path = tmp_path / f"column-{column}.toml"
    assert main(["plan", "generate", "tripp-table-1", "--column", str(column), "--out", str(path),
                 "--json"]) == 0
    written = json.loads(capsys.readouterr().out)
    assert written["points_per_mount"] == (33 * 65 if column == 9 else 33 * 64)
    assert written["usage_pitch"] == (None if usage is None else list(usage))
    merit = ["plan", "merit", str(path), "--json"]
    assert main(merit + ([] if usage is None else ["--usage-pitch", *map(str, usage)])) == 0
    doc = json.loads(capsys.readouterr().out)
    assert round(doc["V_sqrt"], 3) == v_sqrt
    assert (doc["V_R_sqrt"] is None) if v_r_sqrt is None else round(doc["V_R_sqrt"], 3) == v_r_sqrt


def test_table_1_d0_designs_are_spaced_as_section_5_3_2_describes():
    """§5.3.2: Fig. 3 top has 1° steps within ±10° and 4° steps beyond ±14°; Fig. 3 bottom 1° steps
    beyond ±20° and 4° steps within ±16°; Fig. 4 every point at ±30° but one at 0°; Fig. 5 rolls
    uniform over −180..180° with 180° repeated."""
    def pitches(column):
        return sorted({p for p, _ in tripp_table_1(column).points()})

    top = pitches(6)
    assert [a for a in top if abs(a) <= 10] == list(range(-10, 11))
    assert [a for a in top if a >= 14] == [14, 18, 22, 26, 30]
    bottom = pitches(7)
    assert [a for a in bottom if a >= 20] == list(range(20, 31))
    assert [a for a in bottom if 0 <= a <= 16] == [0, 4, 8, 12, 16]
    ends = [p for p, _ in tripp_table_1(8).points()]
    assert ends.count(-30) == ends.count(30) == 16 * 64 and ends.count(0) == 64
    rolls = sorted({r for _, r in tripp_table_1(9).points()})
    assert len(rolls) == 65 and rolls[0] == -180 and rolls[-1] == 180 and np.allclose(np.diff(rolls), 5.625)


def test_six_point_tumble_normalised_sd_is_2_everywhere_eq_69():
    plan = make_plan("t", "", tumble(), four_mounts=False)
    rng = np.random.default_rng(0)
    pitch, roll = rng.uniform(-180, 180, 50), rng.uniform(-180, 180, 50)
    assert np.allclose(np.sqrt(normalised_variance(plan, pitch, roll)), 2.0, rtol=1e-12)


@pytest.mark.parametrize("pitch_max,n,m", [(30, 33, 64), (45, 17, 8), (90, 9, 16), (180, 65, 32)])
def test_eq_66_matches_the_numeric_variance_function(pitch_max, n, m):
    plan = make_plan("d1", "", d1(pitch_max, n, m), four_mounts=False)
    pitches = np.radians(np.linspace(-pitch_max, pitch_max, n))
    c2 = np.sum(np.cos(2 * pitches))  # Tripp eq. 166
    alpha = np.linspace(-pitch_max, pitch_max, 37)
    cos2 = np.cos(np.radians(alpha)) ** 2
    expected = 1 / (m * n) + 2 * (n + c2 + (n - 3 * c2) * cos2) / (m * (n**2 - c2**2))
    for roll in (0.0, 33.0, 135.0):  # Theorem IV: independent of roll
        numeric = normalised_variance(plan, alpha, np.full_like(alpha, roll)) / (m * n)
        assert np.allclose(numeric, expected, rtol=1e-10)


def test_eq_109_counts_the_fractional_design():
    """Tripp Fig. 21: N = 19, M = 13, K_α = 3, K_R = 4 keeps 139 of 247 points."""
    points = fractional(30, 19, -180, 180, 13, k_pitch=3, k_roll=4)
    assert len(points) == fractional_size(19, 13, 3, 4) == 139
    assert len(set(points)) == 139


def test_generated_plan_round_trips_through_toml():
    plan = make_plan("d1", "Tripp D1", d1(30, 33, 64), four_mounts=True, replicates=2)
    back = parse_plan(plan_toml(plan), "generated")
    assert back == plan and back.angle_step_deg == 0  # 1.875° steps: continuous tables only
    on_grid = make_plan("g", "", d1(90, 3, 4), four_mounts=False)
    assert on_grid.angle_step_deg == 1


def test_audit_four_mounts_cancel_everything_one_mount_leaks_e_f_k():
    four = audit(load_plan("four-mount-64")[0])
    for leak in four.values():
        off_diagonal = leak[1:][~np.eye(3, dtype=bool)]
        assert np.max(np.abs(leak[0])) < 1e-9 and np.max(np.abs(off_diagonal)) < 1e-9
    one = audit(load_plan("one-mount-16")[0])
    summary = audit_summary(one)
    assert [n for n, s in summary.items() if not s["cancelled"]] == ["e", "f", "k"]
    # Soto eq. 33 to first order: Syx = k, Sxy = −k, Szx = −e, Sxz = e, Szy = −f, Syz = f
    assert one["k"][1, 1] == pytest.approx(1, abs=1e-12) and one["k"][2, 0] == pytest.approx(-1, abs=1e-12)
    assert one["e"][3, 0] == pytest.approx(1, abs=1e-12) and one["e"][1, 2] == pytest.approx(-1, abs=1e-12)
    assert one["f"][3, 1] == pytest.approx(1, abs=1e-12) and one["f"][2, 2] == pytest.approx(-1, abs=1e-12)


def test_audit_agrees_with_finite_misalignments():
    """The first-order audit predicts the exact fit of a slightly misaligned device."""
    from conftest import ideal_fit

    from labcal.analysis.kinematics import Misalignment

    leaks = audit(load_plan("one-mount-16")[0])
    h = 1e-6
    for name, leak in leaks.items():
        X = ideal_fit([(0, 0)], Misalignment(**{name: h}))
        change = X - np.vstack([np.zeros(3), np.eye(3)])
        assert np.allclose(change, h * leak, atol=1e-11)

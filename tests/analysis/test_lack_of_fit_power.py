"""The lack-of-fit test can pass and can fail (Monte Carlo on the simulated bench, fixed seeds): on a
clean bench stated truly it flags at most 1 % of calibrations; each effect the model or the station's
statement leaves out — the tables at 3× their stated error, an unstated 3″ seating scatter, a 60 µg/h
bias drift, a 50 µg/g² nonlinearity — it flags in at least 80 %. Four-mount-64 in a single pass: the
scatter inside the windows is the pure error. The figures are printed beside their targets
(`pytest -s`; benchmarks/attitude_coverage.py prints them too)."""

from __future__ import annotations

import pytest

from labcal.config.plans import load_plan
from labcal.sim.coverage import EFFECTS, flagged, with_effect


@pytest.fixture(scope="module")
def plan():
    return load_plan("four-mount-64")[0]


@pytest.mark.slow(seconds=32)
def test_a_clean_bench_stated_truly_is_flagged_in_at_most_one_calibration_in_a_hundred(plan):
    """500 calibrations: the test's nominal size is 1 %; a true rate of 1 % gives 5 ± 2.2 flags."""
    false_alarms, drifts = flagged(plan, with_effect("clean"), 500, first_seed=7000)
    print(f"clean bench: lack of fit flagged in {false_alarms:.1%} (target ≤ 1 %); drift test "
          f"{drifts:.1%} (the simulator's own 2 µV/h drift)")
    assert false_alarms <= 0.01


@pytest.mark.slow
@pytest.mark.parametrize("effect", EFFECTS)
def test_each_effect_outside_the_model_is_flagged_in_at_least_four_calibrations_in_five(plan, effect):
    """60 calibrations per effect: at a true power of 90 % the count flagged is 54 ± 2.3."""
    power, drifts = flagged(plan, with_effect(effect), 60, first_seed=9000)
    print(f"{effect}: lack of fit flagged in {power:.0%} (target ≥ 80 %); drift test {drifts:.0%}")
    assert power >= 0.8

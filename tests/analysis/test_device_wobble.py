"""The device model when the tables wobble: the tables' stated index and wobble
errors are per-point angle errors, one per table angle, and enter the misalignments' and coefficients'
covariance. Checked three ways: the covariance against refitting perturbed readings (the GUM formula
u² = Σ cᵢ²uᵢ² with each cᵢ found by a refit, not by the code's projection), coverage by Monte Carlo
on the simulator's own index and wobble errors, and the budget's table rows of a device-model
certificate against the same refits."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labcal.analysis.budget import TypeBInputs, calibration_of_device, coefficient_budget, sources
from labcal.analysis.design import make_plan
from labcal.analysis.device_fit import AngleErrors, fit_device
from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble, Misalignment, gravity
from labcal.analysis.plan import Plan
from labcal.analysis.readings import Readings
from labcal.config.emulation import DeviceTruth, default_instrument
from labcal.config.plans import load_plan
from labcal.sim.direct import simulate_readings

TRUTH = default_instrument()
MIS = DeviceTruth().misalignment()
INDEX, WOBBLE, NOISE = 1.0, 2.0, 5e-6  # arcsec, arcsec, V: the case


def _plan(replicates: int) -> Plan:
    base, _ = load_plan("four-mount-64")
    return Plan(**{**base.model_dump(), "replicates": replicates})


def _stated(index: float = INDEX, wobble: float = WOBBLE) -> AngleErrors:
    return AngleErrors(index * ARCSEC, wobble * ARCSEC, index * ARCSEC, wobble * ARCSEC)


def _perturbed(readings: Readings, pattern: np.ndarray, name: str, delta: float,
               base: Misalignment = MIS) -> Readings:
    """The readings the instrument gives when a table errs by δ·pattern in misalignment ``name`` (the
    pattern: 1 at one table angle, or a harmonic of the table angle, at every mount and replicate),
    the rest exactly as read: V + (g(δ) − g)·S."""
    degrees = (readings.pitch_deg, readings.roll_deg, readings.y_deg, readings.u_deg)
    p, r, y, u = (np.radians(a) for a in degrees)
    g0 = gravity(p, r, y, u, base)
    g1 = gravity(p, r, y, u, base + Misalignment(**{name: delta * pattern}))
    volts = readings.volts + (g1 - g0) @ TRUTH.X[1:]
    return Readings(readings.replicate, readings.y_deg, readings.u_deg, readings.pitch_deg, readings.roll_deg,
                    volts)


def _patterns(readings: Readings, table: str) -> list[tuple[np.ndarray, float]]:
    """The table's error shapes with their share of u²: one per distinct angle (a rough table, u²
    each) and harmonics 1–3 of the angle, cos and sin (a smooth table, u²/3 each)."""
    table_deg = np.mod(readings.pitch_deg if table == "pitch" else readings.roll_deg, 360)
    rough = [(np.isclose(table_deg, angle).astype(float), 1.0) for angle in np.unique(table_deg)]
    smooth = [(f(h * np.radians(table_deg)), 1 / 3) for h in (1, 2, 3) for f in (np.cos, np.sin)]
    return rough + smooth


def _refit_covariance(readings: Readings, stated: AngleErrors, base: Misalignment = MIS) -> np.ndarray:
    """Σ over inputs of c·cᵀ·u², c = ∂θ̂/∂δ by central differences of full refits, u² = half-width²/3
    times the shape's share."""
    cov = np.zeros((18, 18))
    h = 0.05 * ARCSEC
    for table, names, half in stated.inputs():
        if half == 0:
            continue
        for pattern, share in _patterns(readings, table):
            for name in names:
                up = fit_device(_perturbed(readings, pattern, name, h, base)).theta
                down = fit_device(_perturbed(readings, pattern, name, -h, base)).theta
                c = (up - down) / (2 * h)
                cov += np.outer(c, c) * share * half**2 / 3
    return cov


def test_angle_error_covariance_is_what_refitting_predicts():
    readings = simulate_readings(_plan(1), TRUTH, MIS, None, NOISE, seed=4)
    stated = _stated()
    fit = fit_device(readings, angle_errors=stated)
    expected = _refit_covariance(readings, stated)
    assert fit.angle_covariance is not None
    # to 1 %, or to 0.1 % of the noise's u where the angle errors' share is nil (four mounts cancel
    # them in B): a refit weights each sensor by its own residual scatter, which the perturbation moves
    # (the code linearises at fixed weights), and the solver stops at 1e-10 of the cost
    got, want = np.sqrt(np.diag(fit.angle_covariance)), np.sqrt(np.diag(expected))
    noise = np.sqrt(np.diag(fit.noise_covariance))
    assert np.all(np.abs(got - want) <= 1e-2 * want + 1e-3 * noise), (got, want)
    assert np.all(want[:6] > 2 * noise[:6])  # the wobble dominates the misalignments' u here
    # the noise share is the fit without stated errors, exactly
    np.testing.assert_allclose(fit.noise_covariance, fit_device(readings).covariance, rtol=1e-9, atol=1e-30)
    doc = fit.to_json()
    assert doc["angle_errors_stated"] == {"pitch_index_arcsec": pytest.approx(INDEX),
                                          "pitch_wobble_arcsec": pytest.approx(WOBBLE),
                                          "roll_index_arcsec": pytest.approx(INDEX),
                                          "roll_wobble_arcsec": pytest.approx(WOBBLE)}
    assert any("index and wobble" in n for n in doc["notes"])


def test_budget_table_rows_of_a_device_certificate_are_what_refitting_predicts():
    """Each table row's contribution to the coefficients: u(X) = √(Σ c² u²), c by refitting (the device
    model re-estimates a…k, which takes up part of a table error). On a device without misalignments,
    where the budget linearises the kinematics (its second-order terms are below 1e-3 of the noise's u
    on a 40″ device, but not below the refits' agreement)."""
    readings = simulate_readings(_plan(1), TRUTH, Misalignment(), None, NOISE, seed=4)
    fit = fit_device(readings, angle_errors=_stated())
    cal = calibration_of_device(fit, readings)
    inputs = TypeBInputs(pitch_index=INDEX * ARCSEC, pitch_wobble=WOBBLE * ARCSEC, roll_index=INDEX * ARCSEC,
                         roll_wobble=WOBBLE * ARCSEC)
    rows = {s.name: s for s in sources(cal, inputs)}
    for label, stated in (("pitch table index accuracy", AngleErrors(pitch_index=INDEX * ARCSEC)),
                          ("roll table wobble", AngleErrors(roll_wobble=WOBBLE * ARCSEC))):
        expected = np.sqrt(np.diag(_refit_covariance(readings, stated, Misalignment()))[6:]).reshape(4, 3)
        got = coefficient_budget([rows[label]]).contributions[label]
        noise = np.sqrt(np.diag(fit.noise_covariance)[6:]).reshape(4, 3)
        assert np.all(np.abs(got - expected) <= 1e-2 * expected + 1e-3 * noise), (label, got, expected)


def _scattered_plan() -> Plan:
    """Twenty scattered articulations in four mounts: many distinct table angles, close together, where
    a smooth table's errors do not average out as independent ones would."""
    rng = np.random.default_rng(3)
    points = [(float(p), float(r)) for p, r in zip(rng.integers(-80, 80, 20), rng.integers(0, 359, 20),
                                                    strict=True)]
    return make_plan("scattered-20", "20 scattered points × 4 mounts", points, four_mounts=True)


def _coverage(trials: int, replicates: int, stated: bool, plan: Plan | None = None) -> np.ndarray:
    """Per parameter, the fraction of trials (each a new rig: new index and wobble harmonics, new
    noise) whose U = k·u covers the truth, with or without the stated errors given to the fit."""
    plan = plan or _plan(replicates)
    true = np.concatenate([[getattr(MIS, n) for n in MISALIGNMENT_NAMES], TRUTH.X.ravel()])
    hits = []
    for seed in range(trials):
        readings = simulate_readings(plan, TRUTH, MIS, IndexWobble(INDEX, WOBBLE, seed), NOISE, seed)
        fit = fit_device(readings, angle_errors=_stated() if stated else None)
        hits.append(np.abs(fit.theta - true) <= fit.k95 * fit.stderr)
    return np.mean(hits, axis=0)


def _lowest_acceptable(trials: int) -> float:
    """A 95 % coverage observed in N trials falls below 0.95 − 3.1·√(0.95·0.05/N) with probability
    0.1 % (normal approximation to the binomial): below that, the stated U does not cover."""
    return 0.95 - 3.1 * np.sqrt(0.95 * 0.05 / trials)


@pytest.mark.parametrize("replicates", [1, 2])
def test_misalignments_and_coefficients_cover_with_wobble(replicates):
    trials = 100
    after = _coverage(trials, replicates, stated=True)
    floor = _lowest_acceptable(trials)  # 0.882 for 100 trials
    assert np.all(after >= floor), dict(zip(MISALIGNMENT_NAMES, after[:6], strict=False))
    # without the stated errors the misalignments' U does not cover (the issue: 0.23–0.66): 30 trials
    # tell 0.95 from below 0.7 (binomial SE 0.04)
    assert np.min(_coverage(30, replicates, stated=False)[:6]) < 0.7


def test_a_scattered_plan_covers_too():
    """Many distinct, nearby table angles: the smooth shape of the errors is what covers here."""
    trials = 100
    after = _coverage(trials, 1, stated=True, plan=_scattered_plan())
    assert np.all(after >= _lowest_acceptable(trials)), after


@pytest.mark.slow
@pytest.mark.parametrize("replicates", [1, 3])
def test_coverage_of_a_thousand_rigs(replicates):
    """The issue's criterion: ≥ 93 % for each misalignment and each coefficient in 1 000 trials."""
    after = _coverage(1000, replicates, stated=True)
    assert np.all(after >= 0.93), after


def test_fit_command_takes_the_tables_stated_errors(tmp_path, capsys):
    from labcal.cli import main

    csv = tmp_path / "readings.csv"
    assert main(["simulate", "--plan", "four-mount-64", "--misalign", "a=30arcsec,e=20arcsec",
                 "--index-error", "1", "--wobble", "2", "--noise", "5e-6", "--seed", "3",
                 "--out", str(csv)]) == 0
    capsys.readouterr()
    assert main(["fit", str(csv), "--model", "device", "--json"]) == 0
    bare = json.loads(capsys.readouterr().out)
    assert main(["fit", str(csv), "--model", "device", "--table-index", "1", "--table-wobble", "2",
                 "--json"]) == 0
    stated = json.loads(capsys.readouterr().out)
    assert stated["angle_errors_stated"]["roll_wobble_arcsec"] == pytest.approx(2.0)
    assert "angle_errors_stated" not in bare
    for name in MISALIGNMENT_NAMES:  # the same estimate, a wider U (the wobble dominates at 5 µV)
        assert stated["misalignments"][name]["value_arcsec"] == bare["misalignments"][name]["value_arcsec"]
        assert stated["misalignments"][name]["U_arcsec"] > 2 * bare["misalignments"][name]["U_arcsec"]
    assert main(["fit", str(csv), "--model", "linear", "--table-wobble", "2"]) == 2
    err = capsys.readouterr().err
    assert "--table-index and --table-wobble are the device model's" in err and err.count("\n") == 1


def test_a_run_s_station_states_the_tables_errors():
    from labcal.config.snapshot import parse_snapshot, stated_angle_errors

    rig = {"kind": "simulated rig", "seed": 1,
           "rig": {"device": {"index_arcsec": 1.5, "wobble_arcsec": 0.5}}}
    errors = stated_angle_errors(parse_snapshot(json.dumps(rig)))
    assert errors == AngleErrors(1.5 * ARCSEC, 0.5 * ARCSEC, 1.5 * ARCSEC, 0.5 * ARCSEC)
    table = {"pitch_index": "2 arcsec", "roll_wobble": "1 arcsec"}
    station = parse_snapshot(json.dumps({"kind": "station", "station": {"uncertainty": table}}))
    assert stated_angle_errors(station) == AngleErrors(pitch_index=2 * ARCSEC, roll_wobble=ARCSEC)
    assert stated_angle_errors(parse_snapshot(json.dumps({"kind": "station", "station": {}}))) is None
    assert stated_angle_errors(parse_snapshot("")) is None  # states none, and no snapshot

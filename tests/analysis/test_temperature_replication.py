"""Temperature-corrected replicated calibration as Tripp & Tcheng do it (§9.2.1, Table 2 footnote b):
a sensor calibrated with roll over ±30° in six replications while the temperature drifts 1 °C."""

from __future__ import annotations

import json

import numpy as np
import pytest

from labcal.analysis.distributions import t_quantile
from labcal.analysis.fit import fit_readings
from labcal.analysis.kinematics import nominal_gravity
from labcal.analysis.models import Model
from labcal.analysis.packages import Sensor, output
from labcal.analysis.readings import Readings
from labcal.analysis.replication import analyse_with_covariates, point_groups

DEG = np.pi / 180
NOISE = 2e-5  # V rms per reading
B_T = 5e-5  # V/°C: offset temperature coefficient
S_T = 3e-4  # 1/°C: relative sensitivity temperature coefficient
SENSORS = (Sensor("x", 0.012, 2.0, 0.5 * DEG, 30 * DEG), Sensor("y", -0.008, -2.1, 0.3 * DEG, 100 * DEG),
           Sensor("z", 0.005, -1.9, 0.2 * DEG, -60 * DEG))


def design_9_2_1(replicates: int = 6) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """§9.2.1: pitch −30..30° by 5°, roll −180..180° by 15° (180° repeated, as Fig. 5): 325 points
    per replication, in run order; and the temperature, rising 1 °C over the whole run."""
    pitch, roll = (a.ravel() for a in np.meshgrid(np.arange(-30, 31, 5.0), np.arange(-180, 181, 15.0),
                                                  indexing="ij"))
    assert len(pitch) == 325
    rep = np.repeat(np.arange(1, replicates + 1), len(pitch))
    pitch, roll = np.tile(pitch, replicates), np.tile(roll, replicates)
    run = np.linspace(0.0, 1.0, len(rep))
    temp = 21.0 + 0.5 * (1 - np.cos(np.pi * run))  # 21 → 22 °C
    return rep, pitch, roll, temp


def volts(pitch, roll, temp, rng, columns: int | None = None) -> np.ndarray:
    """Each sensor's eq. 14–16 output with b(T) = b + b_T·ΔT and S(T) = S·(1 + S_T·ΔT) about the run's
    mean temperature, plus white noise."""
    dt = temp - temp.mean()
    clean = np.column_stack([s.b + B_T * dt + (output(s, pitch * DEG, roll * DEG) - s.b) * (1 + S_T * dt)
                             for s in SENSORS])
    if columns is None:
        return clean + NOISE * rng.normal(size=clean.shape)
    return clean[:, :1] + NOISE * rng.normal(size=(len(clean), columns))


def readings(rep, pitch, roll, temp, v) -> Readings:
    zero = np.zeros(len(rep))
    return Readings(replicate=rep, y_deg=zero, u_deg=zero, pitch_deg=pitch, roll_deg=roll, volts=v,
                    temp_c=temp)


def truth_x() -> tuple[np.ndarray, np.ndarray]:
    """The x sensor's linear coefficients [B, s] at the mean temperature, and their temperature
    derivatives: eq. 14 expanded on g = [sin α, cos α sin R, cos α cos R] is
    b + S·[cos Ω·g_x − sin Ω cos A·g_y − sin Ω sin A·g_z]."""
    s = SENSORS[0]
    column = s.S * np.array([np.cos(s.omega), -np.sin(s.omega) * np.cos(s.azimuth),
                             -np.sin(s.omega) * np.sin(s.azimuth)])
    return np.array([s.b, *column]), np.array([B_T, *(S_T * column)])


def test_temperature_corrected_fit_of_a_drifting_calibration():
    """Without the temperature terms the residual SD is several times the noise and the sensitivity
    drift test between replications (Table 2's T_S) is significant, as in Fig. 28(a); with them the
    coefficients are within 3 SE of the truth, the sensitivity's temperature term is significant,
    the residual SD is within 10 % of the noise, and the drift is gone, as in Fig. 28(b)."""
    rep, pitch, roll, temp = design_9_2_1()
    r = readings(rep, pitch, roll, temp, volts(pitch, roll, temp, np.random.default_rng(921)))
    plain = fit_readings(r, Model(t_ref=float(temp.mean())))
    assert plain.ls.residual_se[0] > 3 * NOISE and plain.replication is not None
    drift = {d.name: d for d in plain.replication.drift}
    assert drift["sensitivity"].test.significant[0]

    corrected = fit_readings(r, Model(("temperature",), t_ref=float(temp.mean())))
    names = corrected.names
    assert names[4:] == ("dB/dT", "dS_x/dT", "dS_y/dT", "dS_z/dT")
    base, per_kelvin = truth_x()
    coef, se = corrected.ls.coef[:, 0], corrected.stderr[:, 0]
    assert np.all(np.abs(coef - np.concatenate([base, per_kelvin])) <= 3 * se)
    t_s = coef[5] / se[5]  # dS_x/dT, the main component of the sensitivity's temperature term
    assert abs(t_s) > float(t_quantile(0.975, corrected.variance_dof[0]))
    assert corrected.ls.residual_se[0] == pytest.approx(NOISE, rel=0.10)
    rep_analysis = corrected.replication
    assert rep_analysis is not None  # no longer skipped for temperature terms
    assert rep_analysis.sigma_prec[0] == pytest.approx(NOISE, rel=0.10)
    drift = {d.name: d for d in rep_analysis.drift}
    assert not drift["sensitivity"].test.significant[0] and not drift["offset"].test.significant[0]
    assert not rep_analysis.lack_of_fit.significant[0]


def test_temperature_corrected_tests_hold_their_size():
    """1000 noise draws of the right model, the temperature rising through the run: the lack-of-fit
    test and the offset and sensitivity drift tests of the temperature-corrected analysis each reject
    5 % of the time (3 % to 7 %: 3 standard errors of a proportion over 1000 draws). (Readings
    corrected by a γ fitted within points first, then tested as without temperature, gave the drift
    tests 3 %.)"""
    rep, pitch, roll, temp = design_9_2_1()
    y = volts(pitch, roll, temp, np.random.default_rng(37), columns=1000)
    dt = (temp - temp.mean())[:, None]
    g = nominal_gravity(pitch * DEG, roll * DEG, 0.0, 0.0)
    design = np.hstack([np.ones((len(g), 1)), g, dt, dt * g])
    groups, _ = point_groups([pitch, roll % 360])
    per_point = np.array([True] * 4 + [False] * 4)
    result = analyse_with_covariates(design, y, groups, rep, per_point)
    assert result is not None
    rates = {"lack of fit": result.classical.significant.mean(),
             **{d.name: d.test.significant.mean() for d in result.drift}}
    assert all(0.03 <= rate <= 0.07 for rate in rates.values()), rates


def test_a_temperature_read_once_per_replicate_is_an_offset_drift_it_takes_a_degree_of_freedom_from():
    """Temperature constant within each replicate: the offset's temperature term is a combination of
    per-replicate offsets, so the offset drift test has R − 2 degrees of freedom left, not R − 1."""
    rep, pitch, roll, _ = design_9_2_1()
    temp = 21.0 + 0.2 * rep
    r = readings(rep, pitch, roll, temp, volts(pitch, roll, temp, np.random.default_rng(3)))
    result = fit_readings(r, Model(("temperature",), t_ref=float(temp.mean()))).replication
    assert result is not None
    drift = {d.name: d for d in result.drift}
    assert drift["offset"].test.df_num == 4 and drift["sensitivity"].test.df_num == 4
    assert np.all(np.isfinite(drift["offset"].test.statistic))


def test_labcal_fit_reports_table_2_with_the_temperature_terms(tmp_path, capsys):
    """`labcal fit --extend temperature` on the drifting calibration: Table 2's columns, per sensor,
    and the sensitivity drift of the uncorrected fit gone. (--allow-outliers: the gross-error check
    holds |(V − B)S⁻¹| to 1 g without the temperature terms, and a 3e-4/°C sensitivity over 1 °C
    moves it 1.7e-4, beyond its 5e-5.)"""
    from rich.console import Console

    from labcal.cli import main
    from labcal.commands.fit import replication_table
    from labcal.config.readings_csv import write_readings

    rep, pitch, roll, temp = design_9_2_1()
    path = tmp_path / "readings.csv"
    write_readings(path, readings(rep, pitch, roll, temp, volts(pitch, roll, temp, np.random.default_rng(5))))
    fit = ["fit", str(path), "--model", "linear", "--extend", "temperature", "--allow-outliers", "--json"]
    assert main(fit) == 0
    doc = json.loads(capsys.readouterr().out)
    x = doc["replication"]["x"]
    assert not x["drift"]["sensitivity"]["significant"] and x["drift"]["sensitivity"]["sigma_drift"] >= 0
    table = Console(width=250, record=True)
    table.print(replication_table(doc["replication"], "V", doc["residual_standard_error"]))
    text = table.export_text()
    for column in ("σ_E", "σ_bias", "σ_prec", "T_bias", "(F_bias)95", "σ_b", "σ_S", "T_b", "T_S", "(F_bS)95"):
        assert column in text
    x_row = next(line for line in text.splitlines() if line.strip("│ ").startswith("x "))
    assert f"{doc['residual_standard_error'][0]:.3g}" in x_row
    # the 95 % limits Tripp Table 2 prints for the design of §9.2.1 (row 28(b)): 1.15 and 2.22
    assert round(x["lack_of_fit"]["critical_95"], 2) == 1.15
    assert round(x["drift"]["sensitivity"]["critical_95"], 2) == 2.22

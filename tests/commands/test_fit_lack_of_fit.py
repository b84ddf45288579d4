"""`labcal fit` reports the lack-of-fit and drift tests: from a readings CSV that carries each point's
window (the audit columns labcal writes), against the windows' noise and the tables' stated errors.
The flag is a finding about the readings, not bad input: the command still prints the coefficients and
exits 0, with one clear line (and the JSON says it)."""

from __future__ import annotations

import json

from labcal.analysis.kinematics import IndexWobble
from labcal.cli import main
from labcal.config.emulation import DeviceTruth, default_instrument
from labcal.config.plans import load_plan
from labcal.config.readings_csv import ReadingsWriter, read_readings
from labcal.sim.direct import BenchEffects, simulate_readings


def _csv(path, quadratic=(0.0, 0.0, 0.0), audit=True):
    """Four-mount-64 on ±2″ tables, 20 µV per sample over windows of 10, optionally a nonlinearity."""
    plan, _ = load_plan("four-mount-64")
    truth = default_instrument()
    table = IndexWobble(2.0, 2.0, 4)
    r = simulate_readings(plan, truth, DeviceTruth().misalignment(), table, truth.noise_v, 4,
                          BenchEffects(samples=10, quadratic_v_per_g2=quadratic))
    with ReadingsWriter(path, temperature=False, audit=audit) as w:
        for i in range(len(r)):
            w.append(replicate=int(r.replicate[i]), y_deg=r.y_deg[i], u_deg=r.u_deg[i],
                     pitch_deg=r.pitch_deg[i], roll_deg=r.roll_deg[i], volts=r.volts[i], sd=r.window_sd[i],
                     n_samples=10, time_s=30.0 * i)
    return path


def _fit(path, capsys, *extra):
    capsys.readouterr()
    code = main(["fit", str(path), "--table-index", "2", "--table-wobble", "2", *extra])
    return code, capsys.readouterr()


def test_the_audit_columns_give_the_readings_their_windows(tmp_path):
    readings = read_readings(_csv(tmp_path / "r.csv"))
    assert readings.window_n is not None and set(readings.window_n) == {10.0}
    assert readings.window_sd.shape == (64, 3) and (readings.window_sd > 0).all()
    # an incomplete audit (an empty sd) is read without the windows, not refused
    text = (tmp_path / "r.csv").read_text().splitlines()
    cells = text[1].split(",")
    cells[9] = ""
    (tmp_path / "gap.csv").write_text("\n".join([text[0], ",".join(cells), *text[2:]]) + "\n")
    assert read_readings(tmp_path / "gap.csv").window_sd is None


def test_a_clean_calibration_passes_and_a_nonlinear_instrument_is_flagged(tmp_path, capsys):
    code, out = _fit(_csv(tmp_path / "clean.csv"), capsys)
    assert code == 0 and "lack of fit: none against the windows' noise and the tables' stated" in out.out
    assert "drift: none" in out.out
    # 50 µg/g² on a 5 V/g sensor: 250 µV at 1 g, forty times the noise of a reading
    code, out = _fit(_csv(tmp_path / "bent.csv", quadratic=(2.5e-4, 2.5e-4, 2.5e-4)), capsys)
    assert code == 0 and "LACK OF FIT against the windows' noise" in out.out
    code, out = _fit(tmp_path / "bent.csv", capsys, "--json")
    doc = json.loads(out.out)["lack_of_fit"]
    assert doc["tested"] and doc["significant"] and doc["p_value"] < 1e-6 and doc["bench_errors_stated"]


def test_readings_without_their_windows_are_not_tested_and_say_why(tmp_path, capsys):
    code, out = _fit(_csv(tmp_path / "plain.csv", audit=False), capsys)
    assert code == 0
    assert "lack of fit: not tested — the readings do not carry their windows' scatter" in out.out

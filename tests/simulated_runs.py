"""Dry runs on the simulated rig for the certificate, report and history tests.

Through the command line (`labcal run --sim`), in-process: the interface the lab uses, and the one
that stays put while the run's internals move to the journal. One run takes about a second.
"""

from __future__ import annotations

import json
import time
from datetime import UTC, datetime
from pathlib import Path

from labcal.cli import main
from labcal.config.emulation import RigConfig, default_instrument

SAMPLES_OF_A_RUN = 10  # SettleSettings.samples: a dry run's points average this many samples


def rig_with_bias_shift(path: Path, shift_v: tuple[float, float, float]) -> Path:
    """A rig file whose instrument is the default one with its bias B shifted by ``shift_v``."""
    truth = default_instrument().model_dump()
    truth["B"] = [b + d for b, d in zip(truth["B"], shift_v, strict=True)]
    path.write_text("[instrument]\n" + "".join(f"{k} = {json.dumps(v)}\n" for k, v in truth.items()),
                    encoding="utf-8")
    return path


def simulated_run(run_dir: Path, db: Path, seed: int, *, rig: Path | None = None, plan: str | None = None,
                  serial: str | None = None, report: bool = True) -> Path:
    """A complete dry run into ``run_dir`` journaled in ``db``; it starts in a new UTC second, so
    consecutive runs have distinct calibration times (run.json keeps whole seconds). ``report=False``:
    without its documents (--no-report), for a test that issues them itself — the certificate, report
    and DCC are most of a dry run's time."""
    start = datetime.now(UTC).replace(microsecond=0)
    while datetime.now(UTC).replace(microsecond=0) == start:
        time.sleep(0.02)
    args = ["run", "--sim", "--yes", "--seed", str(seed), "--out", str(run_dir), "--db", str(db)]
    args += ["--rig", str(rig)] * (rig is not None) + ["--plan", plan] * (plan is not None)
    args += ["--serial", serial] * (serial is not None) + ["--no-report"] * (not report)
    assert main(args) == 0
    return run_dir


def bench_run(run_dir: Path, db: Path, serial: str, plan: str = "one-mount-16", *,
              report: bool = True) -> Path:
    """A complete calibration through the real drivers against `labcal sim serve` in another process,
    as against a bench (`tests/run/test_emulated_runs.py::test_a_run_on_hardware_served_by_another_process`):
    labcal does not know the devices are emulated, so its journal holds no simulated truth — a run
    that may be approved. One mount (nobody remounts the served instrument), a fixed dwell (the
    system clock is not scaled). ``report=False``: without its documents, as `simulated_run`."""
    import signal
    import subprocess
    import sys

    from emulators import private_file

    station = private_file("smc100-tcp", run_dir.parent)
    labcal = str(Path(sys.executable).with_name("labcal"))
    serve = subprocess.Popen([labcal, "sim", "serve", str(station), "--time-scale", "500", "--json"],
                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert json.loads("".join(iter(serve.stdout.readline, "}\n")) + "}")["time_scale"] == 500
        code = main(["run", "--station", str(station), "--plan", plan, "--yes", "--serial", serial,
                     "--fixed-dwell", "0.05", "--out", str(run_dir), "--db", str(db),
                     *["--no-report"] * (not report)])
    finally:
        serve.send_signal(signal.SIGINT)
        serve.communicate(timeout=20)
    assert code == 0
    return run_dir


def days_ago(days: float) -> str:
    """An ISO 8601 UTC time this many days before now, to the second: a device history's estimates must
    be recent enough to be used and on distinct days to count as distinct sittings."""
    from datetime import timedelta

    return (datetime.now(UTC).replace(microsecond=0) - timedelta(days=days)).isoformat()


def characterised_device(db: Path, seeds: tuple[int, ...]) -> None:
    """Earlier four-mount-64 runs of the simulated rig's device, one per seed (the simulator's
    readings, fitted as a run fits them: the device model told the tables' stated index and wobble),
    stored in ``db``'s device history as `labcal run` stores them (device "SIMULATED"), ten days apart,
    the last ten days ago: distinct sittings, well within a correction's age limit."""
    import math

    import numpy as np

    from labcal.analysis.device_fit import AngleErrors, fit_device
    from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble
    from labcal.config.plans import load_plan
    from labcal.documents import device_history
    from labcal.documents.device_history import DeviceEstimate
    from labcal.sim.direct import simulate_readings

    plan, _ = load_plan("four-mount-64")
    rig = RigConfig()
    truth, device = rig.instrument, rig.device
    stated = AngleErrors(*(np.array([device.index_arcsec, device.wobble_arcsec] * 2) * ARCSEC))
    for n, seed in enumerate(seeds, start=1):
        readings = simulate_readings(plan, truth, device.misalignment(),
                                     IndexWobble(device.index_arcsec, device.wobble_arcsec, seed),
                                     truth.noise_v / math.sqrt(SAMPLES_OF_A_RUN), seed)
        doc = fit_device(readings, angle_errors=stated).to_json()["misalignments"]
        device_history.store(DeviceEstimate("SIMULATED", days_ago(10 * (len(seeds) - n + 1)), f"run-{n}",
                                            {m: doc[m]["value_arcsec"] for m in MISALIGNMENT_NAMES},
                                            {m: doc[m]["U_arcsec"] for m in MISALIGNMENT_NAMES}), db)


def corrected_runs_under_a_step(text: str, step_arcsec: dict[str, float], runs: int, seed: int,
                                new_readings: int = 200, checked: bool = True) -> list[tuple[bool, float]]:
    """``runs`` simulated runs of the corrected plan ``text`` on a device whose misalignments moved by
    ``step_arcsec`` since the correction's estimate (its truth also drawn about the estimate with the
    correction's own u): each run's readings from the simulator (a new table of index errors and
    wobble per run, the instrument's noise over the plan's window), fitted as `labcal run` fits them,
    its check made as the run makes it (`correction_check.check`, the window noise and the rig's
    stated tables). Per run: (refused, coverage), the coverage being the smaller of pitch's and roll's
    share of ``new_readings`` new readings at random attitudes in the envelope (pitch ±60°, any roll)
    whose attitude error lies within the certificate's U95 (its budget: the simulator's Type B inputs,
    the plan's u). ``checked`` False: no check (what a run did before it made one)."""
    import math
    import tomllib

    import numpy as np

    from labcal.analysis.attitude import LOCAL_GRAVITY_U, sphere_least_squares
    from labcal.analysis.attitude import Calibration as AttitudeCalibration
    from labcal.analysis.budget import calibration_of, propagate, sources
    from labcal.analysis.correction_check import check
    from labcal.analysis.device_fit import AngleErrors, PointMeans
    from labcal.analysis.kinematics import ARCSEC, MISALIGNMENT_NAMES, IndexWobble, Misalignment, gravity
    from labcal.analysis.plan import Plan
    from labcal.app.planning import planning_bench
    from labcal.config.plans import plan_correction
    from labcal.sim.direct import simulate_readings
    from labcal.store.exports import run_fits

    correction = plan_correction(text, "the plan")
    assert correction is not None
    plan = Plan.model_validate({k: v for k, v in tomllib.loads(text).items() if k != "device_correction"})
    samples = int(text.split("Run it with --samples ")[1].split()[0])
    bench, _, _ = planning_bench(None)
    inputs = bench.type_b.__class__(**{**vars(bench.type_b), "device_misalignment": correction.u_rad(),
                                      "device_misalignment_source": correction.describe()})
    rig = RigConfig()
    truth, device = rig.instrument, rig.device
    stated = AngleErrors(*(np.array([device.index_arcsec, device.wobble_arcsec] * 2) * ARCSEC))
    noise = truth.noise_v / math.sqrt(samples)
    held = np.array([correction.value_arcsec[n] for n in MISALIGNMENT_NAMES]) * ARCSEC
    own = np.array([correction.u_history_rad()[n] for n in MISALIGNMENT_NAMES])
    budget = np.array([correction.u_rad()[n] for n in MISALIGNMENT_NAMES])
    step = np.array([step_arcsec.get(n, 0.0) for n in MISALIGNMENT_NAMES]) * ARCSEC
    rng = np.random.default_rng(seed)
    out = []
    for trial in range(runs):
        drawn = held + rng.normal(0.0, own) + step
        readings = simulate_readings(plan, truth, Misalignment(*drawn),
                                     IndexWobble(device.index_arcsec, device.wobble_arcsec, seed + trial),
                                     noise, seed + trial)
        fit, _, _ = run_fits(readings, text, None)
        verdicts = check(PointMeans.of(readings), fit.ls.residuals, fit.coefficients, np.full(3, noise), held,
                         own, budget, stated)
        if checked and any(v.detected for v in verdicts):
            out.append((True, float("nan")))
            continue
        cal = calibration_of(fit, readings)
        pitch = np.radians(rng.uniform(-60, 60, new_readings))
        roll = np.radians(rng.uniform(-180, 180, new_readings))
        U = propagate(cal, sources(cal, inputs), pitch, roll).U
        volts = truth.static_volts(gravity(pitch, roll, 0.0, 0.0)) + rng.normal(0.0, noise, (new_readings, 3))
        att = sphere_least_squares(AttitudeCalibration(fit.coefficients, cal.covariance,
                                                       np.sqrt(cal.reading_var), int(cal.dof[0])),
                                   volts, LOCAL_GRAVITY_U)
        error = np.column_stack([att.pitch - pitch, np.angle(np.exp(1j * (att.roll - roll)))])
        out.append((False, float(np.min(np.mean(np.abs(error) <= U, axis=0)))))
    return out

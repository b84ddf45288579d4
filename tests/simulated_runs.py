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
                  serial: str | None = None) -> Path:
    """A complete dry run into ``run_dir`` journaled in ``db``; it starts in a new UTC second, so
    consecutive runs have distinct calibration times (run.json keeps whole seconds)."""
    start = datetime.now(UTC).replace(microsecond=0)
    while datetime.now(UTC).replace(microsecond=0) == start:
        time.sleep(0.02)
    args = ["run", "--sim", "--yes", "--seed", str(seed), "--out", str(run_dir), "--db", str(db)]
    args += ["--rig", str(rig)] * (rig is not None) + ["--plan", plan] * (plan is not None)
    args += ["--serial", serial] * (serial is not None)
    assert main(args) == 0
    return run_dir


def bench_run(run_dir: Path, db: Path, serial: str, plan: str = "one-mount-16") -> Path:
    """A complete calibration through the real drivers against `labcal sim serve` in another process,
    as against a bench (`tests/test_emulated_runs.py::test_a_run_on_hardware_served_by_another_process`):
    labcal does not know the devices are emulated, so its journal holds no simulated truth — a run
    that may be approved. One mount (nobody remounts the served instrument), a fixed dwell (the
    system clock is not scaled)."""
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
                     "--fixed-dwell", "0.05", "--out", str(run_dir), "--db", str(db)])
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

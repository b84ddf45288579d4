"""The duration estimate against the run.

Each example station, emulated through the real drivers, runs one mount's plan (`one-mount-16`)
and the simulated rig the default plan; each line prints the estimate `labcal run` printed at the
start (`estimated_rig_time_s`, the same as `--dry-run`'s) against the rig time the run took on the
rig's own clock (`simulated_rig_time_s`). An emulated station's rig clock runs --time-scale times
faster than the wall's, so the host's own scheduling counts that many times over: on a busy host
the runs take longer and the figures drift low. That is why this is a benchmark and not a test; the
simulated rig's figure (no host time in it) is asserted by tests/run/test_run_estimate.py.

Usage: python benchmarks/estimate_accuracy.py [--time-scale 10] [--stations NAME ...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

LABCAL = str(Path(sys.executable).with_name("labcal"))
STATIONS = ["az-modbus-rtu", "az-modbus-tcp", "mixed-rtu-socket", "smc100-serial", "smc100-tcp"]


def measured(where: list[str], folder: str) -> tuple[float, float]:
    done = subprocess.run([LABCAL, "run", *where, "--seed", "0", "--yes", "--no-report", "--json",
                           "--out", f"{folder}/run", "--db", f"{folder}/lab.sqlite"],
                          capture_output=True, text=True, check=True)
    run = json.loads(done.stdout)
    return run["estimated_rig_time_s"], run["simulated_rig_time_s"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--time-scale", type=float, default=10.0)
    parser.add_argument("--stations", nargs="*", default=STATIONS)
    args = parser.parse_args()
    cases = [("simulated rig (four-mount-64)", ["--sim"])] + [
        (f"{name} (one-mount-16, ×{args.time_scale:g})",
         ["--station", name, "--emulate", "--time-scale", str(args.time_scale), "--plan", "one-mount-16"])
        for name in args.stations]
    print(f"{'station':44} {'estimate':>9} {'actual':>9} {'error':>7}")
    for label, where in cases:
        with tempfile.TemporaryDirectory() as folder:
            estimate, actual = measured(where, folder)
        print(f"{label:44} {estimate:8.0f}s {actual:8.0f}s {(estimate - actual) / actual:+7.1%}")


if __name__ == "__main__":
    main()

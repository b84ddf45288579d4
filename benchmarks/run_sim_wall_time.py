"""Wall time of `labcal run --sim --yes` for a plan, and the rig time it reports.

Usage: python benchmarks/run_sim_wall_time.py [--plan four-mount-64] [--repeat 5]

Prints, for each repetition, the command's wall time (process start to exit, what a user
waits for) and the in-run wall time labcal measures itself, then the medians.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LABCAL = str(Path(sys.executable).with_name("labcal"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--plan", default="four-mount-64")
    parser.add_argument("--repeat", type=int, default=5)
    args = parser.parse_args()
    command_s, run_s = [], []
    for i in range(args.repeat):
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            proc = subprocess.run([LABCAL, "run", "--sim", "--yes", "--json", "--seed", str(i),
                                   "--plan", args.plan, "--out", f"{tmp}/run", "--db", f"{tmp}/j.sqlite"],
                                  capture_output=True, text=True, check=True)
            command_s.append(time.perf_counter() - t0)
        summary = json.loads(proc.stdout)
        run_s.append(summary["wall_time_s"])
        print(f"run {i + 1}: command {command_s[-1]:.2f} s, in-run {run_s[-1]:.2f} s, "
              f"rig time {summary['simulated_rig_time_s'] / 60:.1f} min, {summary['points']} points")
    print(f"median: command {statistics.median(command_s):.2f} s, in-run {statistics.median(run_s):.2f} s; "
          f"a real rig would need {summary['simulated_rig_time_s'] / 60:.1f} min")


if __name__ == "__main__":
    main()

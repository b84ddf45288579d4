"""Round trips through the real drivers to the protocol emulators, and whole runs on them.

Usage: python benchmarks/drivers_round_trip.py [--repeat 3] [--time-scale 1000] [--no-runs]

Prints, per transport: the round trip of one Modbus register read (AZ feedback position), one
SMC100 query (1TP), and one DMM scan exchange (TRIG:COUN, INIT, *OPC?, FETC?, SYST:ERR?) both
with a negligible integration (1 sweep at NPLC 0.02: the protocol's own cost) and as a run
reads it (10 sweeps of the scan list at NPLC 10, the integration shrunk by the time scale);
then the wall time of `labcal run --station NAME --emulate --no-report` (the four-mount plan,
64 points; the certificate and report are left out) for every example station. Uses the
example stations' ports: stop `labcal sim serve` first.
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

from labcal.bench.hardware import Bench
from labcal.config.station import load_station, shipped_stations
from labcal.sim.emulation import Emulation

LABCAL = str(Path(sys.executable).with_name("labcal"))


def per_call_ms(call, n: int) -> float:
    call()  # connect, warm up
    t0 = time.perf_counter()
    for _ in range(n):
        call()
    return (time.perf_counter() - t0) / n * 1e3


def round_trips(station: str, time_scale: float, repeat: int) -> None:
    config, _ = load_station(station)
    with Emulation(config, time_scale=time_scale) as emulation, \
            Bench(emulation.station_config, emulation.rig.clock) as bench:
        links = {e["devices"][0]: e["address"] for e in emulation.endpoints()}
        n = 30 if "socket://" in links["pitch"] else 300
        table = "Modbus read" if bench.pitch.model.startswith("Oriental") else "SMC100 query (TP)"
        ms = statistics.median(per_call_ms(bench.pitch.angle, n) for _ in range(repeat))
        print(f"  {table:<28} {ms:7.3f} ms   ({links['pitch']})")
        dmm = bench.dmm
        for nplc, sweeps, what in ((0.02, 1, "1 sweep, NPLC 0.02"), (10.0, 10, "10 sweeps, NPLC 10")):
            dmm.nplc = nplc
            dmm.configure()
            ms = statistics.median(per_call_ms(lambda s=sweeps: dmm.read(s), 20) for _ in range(repeat))
            integration = sweeps * dmm.scan_time_s(1) / time_scale * 1e3
            print(f"  SCPI scan, {what:<17} {ms:7.3f} ms   ({links['dmm']}; {len(dmm.scan_list)} channels, "
                  f"of which {integration:.2f} ms integration at ×{time_scale:g})")


def runs(time_scale: float, repeat: int) -> None:
    for station in (s for s in shipped_stations() if s != "lab-example"):
        walls, in_run = [], []
        for _ in range(repeat):
            with tempfile.TemporaryDirectory() as tmp:
                t0 = time.perf_counter()
                command = [LABCAL, "run", "--station", station, "--emulate", "--time-scale", str(time_scale),
                           "--yes", "--json", "--no-report", "--out", f"{tmp}/run",
                           "--db", f"{tmp}/journal.sqlite"]
                proc = subprocess.run(command, capture_output=True, text=True)
                walls.append(time.perf_counter() - t0)
            if proc.returncode:
                sys.exit(f"{station}: {proc.stderr.strip().splitlines()[-1]}")
            summary = json.loads(proc.stdout)
            in_run.append(summary["wall_time_s"])
        rig_min = summary["simulated_rig_time_s"] / 60
        print(f"  {station:<18} {summary['points']} points: in-run {statistics.median(in_run):5.2f} s, "
              f"command {statistics.median(walls):5.2f} s (rig time {rig_min:.0f} min)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--time-scale", type=float, default=1000.0, help="the test suite's default: 1000")
    parser.add_argument("--no-runs", action="store_true", help="round trips only")
    args = parser.parse_args()
    for station in ("az-modbus-tcp", "az-modbus-rtu", "mixed-rtu-socket", "smc100-serial", "smc100-tcp"):
        print(f"{station}: medians of {args.repeat}")
        round_trips(station, args.time_scale, args.repeat)
    if not args.no_runs:
        print(f"four-mount calibration (64 points) through the drivers, emulators at ×{args.time_scale:g}: "
              f"medians of {args.repeat}")
        runs(args.time_scale, args.repeat)


if __name__ == "__main__":
    main()

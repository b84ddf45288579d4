"""A simulated calibration through labcal's Python API, and its certificate read back
(python docs/examples/calibrate.py [FOLDER])."""

import sys
from pathlib import Path

import labcal.api as labcal

folder = Path(sys.argv[1] if len(sys.argv) > 1 else "runs")
finished = labcal.run(sim=True, plan="one-mount-16", seed=7, out=str(folder), say=print)
assert isinstance(finished, labcal.Finished), finished  # an unattended simulated run ends complete
certificate = labcal.read_certificate(finished.run_dir / "certificate.json")
largest = certificate.attitude.pitch_U95_max_deg
print(f"certificate {certificate.certificate_id}: largest pitch U95 {largest:.5f}°")
print(f"the run's {labcal.open_run(finished.run_dir).points_ok} points are in {finished.journal}")

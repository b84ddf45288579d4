"""False change flags of the device history: N dry runs of the same simulated rig
(`labcal run --sim`, which reports and stores the estimate; seeds 1…N: the same misalignments, new
index and wobble harmonics and noise each run), then `labcal device history SIMULATED`: how many of
the 6·(N − 1) consecutive pairs are flagged. With U that covers at 95 % a pair of independent
estimates is flagged about 5 % of the time (fewer where U is conservative).

Usage: python benchmarks/device_history_flags.py [--runs 8] [--unstated]

--unstated fits the device model without the rig's index and wobble, as labcal once did.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
from pathlib import Path

from labcal.cli import main as labcal


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--unstated", action="store_true")
    args = parser.parse_args()
    if args.unstated:
        from labcal.store import exports
        exports.stated_angle_errors = lambda text: None  # type: ignore[assignment]
    with tempfile.TemporaryDirectory() as tmp:
        db = Path(tmp) / "lab.sqlite"
        for seed in range(1, args.runs + 1):
            with contextlib.redirect_stdout(io.StringIO()):
                assert labcal(["run", "--sim", "--yes", "--seed", str(seed), "--db", str(db),
                               "--out", str(Path(tmp) / f"run-{seed}")]) == 0
        out = io.StringIO()
        with contextlib.redirect_stdout(out):
            assert labcal(["device", "history", "SIMULATED", "--db", str(db), "--json"]) == 0
    doc = json.loads(out.getvalue())
    pairs = len(doc["changes"])
    flagged = doc["flagged"]
    by_name: dict[str, int] = {}
    for f in flagged:
        by_name[f["misalignment"]] = by_name.get(f["misalignment"], 0) + 1
    print(f"{args.runs} dry runs: {len(flagged)} of {pairs} consecutive pairs flagged "
          f"({len(flagged) / pairs:.1%}); by misalignment {by_name or 'none'}")
    u = {n: [e["misalignments"][n]["U_arcsec"] for e in doc["estimates"]] for n in "abdefk"}
    print("U95 (″) of the first run: " + ", ".join(f"{n} {v[0]:.2f}" for n, v in u.items()))


if __name__ == "__main__":
    main()

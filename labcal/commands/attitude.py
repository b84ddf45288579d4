"""`labcal attitude`: pitch and roll with uncertainty from measured voltages."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

METHODS = {"closed": "closed_form", "sphere": "sphere_least_squares"}
PREFIX = {"closed": "cf_", "sphere": "ls_"}
ROLL_UNDEFINED = "pitch is ±90° within its uncertainty: gravity lies along x and roll is undefined"


def _columns(att, prefix: str) -> dict[str, np.ndarray]:
    import numpy as np

    deg = np.degrees
    return {f"{prefix}pitch_deg": deg(att.pitch), f"{prefix}roll_deg": deg(att.roll),
            f"{prefix}u_pitch_deg": deg(att.u_pitch), f"{prefix}u_roll_deg": deg(att.u_roll),
            f"{prefix}U95_pitch_deg": att.k95 * deg(att.u_pitch),
            f"{prefix}U95_roll_deg": att.k95 * deg(att.u_roll)}


def cmd_attitude(args: argparse.Namespace) -> int:
    import csv
    import tempfile
    from pathlib import Path

    import numpy as np

    from labcal.analysis import attitude
    from labcal.commands.common import print_json
    from labcal.config.readings_csv import read_numeric_csv
    from labcal.documents.certificate import load_calibration

    cal = load_calibration(args.cert)
    source = args.csv
    if source is None:  # voltages on standard input
        with tempfile.NamedTemporaryFile("w", suffix=".csv", delete=False) as tmp:
            tmp.write(sys.stdin.read())
        source = tmp.name
    try:
        cols = read_numeric_csv(source, "voltages", ("vx", "vy", "vz"))
    finally:
        if args.csv is None:
            Path(source).unlink()
    volts = np.column_stack([cols["vx"], cols["vy"], cols["vz"]])
    methods = list(METHODS) if args.method == "both" else [args.method]
    results = {m: getattr(attitude, METHODS[m])(cal, volts) for m in methods}
    table = {k: v for m in methods for k, v in _columns(results[m], PREFIX[m]).items()}
    k95 = next(iter(results.values())).k95
    if args.json:
        rows = []
        for i in range(len(volts)):
            row = {}
            for m in methods:
                values = {k.removeprefix(PREFIX[m]): table[k][i] for k in table if k.startswith(PREFIX[m])}
                values = {k: (None if not np.isfinite(v) else float(v)) for k, v in values.items()}
                if values["roll_deg"] is None:
                    values["roll_note"] = ROLL_UNDEFINED
                row[METHODS[m]] = values
            rows.append(row)
        print_json({"coverage_factor_95": k95, "degrees_of_freedom": cal.dof, "rows": rows})
        return 0
    writer = csv.writer(sys.stdout)
    writer.writerow(["row", *table])
    for i in range(len(volts)):
        cells = ("" if not np.isfinite(column[i]) else f"{column[i]:.9g}" for column in table.values())
        writer.writerow([i + 1, *cells])
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("attitude", help="pitch and roll with uncertainty from voltages",
                       description="Convert voltages (CSV columns vx,vy,vz) to pitch and roll using a "
                                   "calibration: Soto's closed form (eqs. 5–7) and weighted least squares "
                                   "on the unit sphere (Tripp eqs. 99–104), each with standard "
                                   "uncertainties and 95 % expanded uncertainties (U95 = k·u, k from "
                                   "Student t). Roll is empty where pitch is ±90°.")
    p.add_argument("--cert", required=True, help="fit.json or certificate.json of the instrument")
    p.add_argument("--csv", help="voltages CSV (default: standard input)")
    p.add_argument("--method", choices=["closed", "sphere", "both"], default="both",
                   help="estimator(s) to report (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_attitude)

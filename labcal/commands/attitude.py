"""`labcal attitude`: pitch and roll with uncertainty from measured voltages."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from labcal.lazy import lazy

if TYPE_CHECKING:
    import numpy
    import numpy as np
    from rich import markup
else:
    markup = lazy("rich.markup")  # start-up without rich
    numpy = lazy("numpy")  # start-up without numpy

import json
import math
import tempfile
from pathlib import Path

from labcal.analysis import attitude
from labcal.analysis.gross_errors import gravity_flags, methods_disagree
from labcal.analysis.packages import package_attitude
from labcal.commands import summary
from labcal.commands.common import add_db_option, err, keep_freed_memory, outcome_of_checks
from labcal.config.readings_csv import read_numeric_csv
from labcal.config.streams import read_stream
from labcal.documents.approvers import calibration_in_use
from labcal.errors import LabcalError

CHUNK_ROWS = 10_000  # rows formatted and written at a time: output memory stays flat
METHODS = {"closed": "closed_form", "sphere": "sphere_least_squares"}
PREFIX = {"closed": "cf_", "sphere": "ls_"}
ROLL_UNDEFINED = "pitch is ±90° within its uncertainty: gravity lies along x and roll is undefined"


def _columns(att, prefix: str) -> dict[str, np.ndarray]:
    deg = numpy.degrees
    return {f"{prefix}pitch_deg": deg(att.pitch), f"{prefix}roll_deg": deg(att.roll),
            f"{prefix}u_pitch_deg": deg(att.u_pitch), f"{prefix}u_roll_deg": deg(att.u_roll),
            f"{prefix}U95_pitch_deg": deg(att.U_pitch), f"{prefix}U95_roll_deg": deg(att.U_roll),
            f"{prefix}k_pitch": att.k_pitch, f"{prefix}k_roll": att.k_roll}


def cmd_attitude(args: argparse.Namespace) -> int:
    keep_freed_memory()
    cal, standing = calibration_in_use(args.cert, args.db, args.unverified)
    if not isinstance(cal, attitude.Calibration):  # a sensor package's certificate (Tripp & Tcheng §6)
        return package_attitude_command(args, cal, standing)
    if args.roll_deg is not None or args.roll_sd_deg is not None:
        raise LabcalError("--roll-deg and --roll-sd-deg are for a package that infers pitch at a measured "
                          f"roll; {args.cert} is a three-axis instrument's, which infers roll itself")
    unverified = standing is not None and standing["approved"] and not standing["verified"]
    if standing is not None:  # a draft or an unverified one: a warning; a verified one: who and through what
        prefix = "certificate:" if standing["verified"] else "[yellow]note:[/]"
        err.print(f"{prefix} {markup.escape(str(args.cert))}: {markup.escape(standing['note'])}")
    source = args.csv
    if source is None:  # voltages on standard input (never a device: /dev/zero would fill memory)
        text = read_stream(sys.stdin, "standard input", "voltages")
        with tempfile.NamedTemporaryFile("w", suffix=".csv", delete=False) as tmp:
            tmp.write(text)
        source = tmp.name
    try:
        cols = read_numeric_csv(source, "voltages", ("vx", "vy", "vz"))
    finally:
        if args.csv is None:
            Path(source).unlink()
    volts = numpy.column_stack([cols["vx"], cols["vy"], cols["vz"]])
    methods = list(METHODS) if args.method == "both" else [args.method]
    # local gravity may differ from the calibration's: the sphere estimator takes |g| as 1 ± its
    # uncertainty, the gravity check tests only what lies beyond the tolerance
    estimate = {"closed": lambda: attitude.closed_form(cal, volts),
                "sphere": lambda: attitude.sphere_least_squares(cal, volts, attitude.LOCAL_GRAVITY_U)}
    with numpy.errstate(all="ignore"):  # a row of 1e308 V is flagged below, not a page of warnings
        results = {m: estimate[m]() for m in methods}
        flags = gravity_flags(cal, volts, tolerance=attitude.LOCAL_GRAVITY_TOLERANCE)
        if len(methods) == 2:
            flags += methods_disagree(results["closed"], results["sphere"])
    table = {k: v for m in methods for k, v in _columns(results[m], PREFIX[m]).items()}
    if args.json:
        write_json_rows(table, methods, cal.dof, flags, standing)
    else:
        if unverified and standing is not None:  # stated with the numbers, not only on the terminal
            sys.stdout.write(f"# UNVERIFIED certificate {args.cert}: {standing['note']}\n")
        write_csv_rows(table)
    return outcome_of_checks(flags, args.allow_outliers, args.csv or "standard input")


def package_attitude_command(args: argparse.Namespace, cal, standing: dict | None) -> int:
    """`labcal attitude` with a sensor package's certificate: the outputs of the sensors it has (vx, and
    vy or vz), pitch as it states (without roll, at a roll measured in use: --roll-deg or a roll_deg
    column, with --roll-sd-deg or its σ_R; or pitch and roll together within its usable range)."""
    if standing is not None:
        prefix = "certificate:" if standing["verified"] else "[yellow]note:[/]"
        err.print(f"{prefix} {markup.escape(str(args.cert))}: {markup.escape(standing['note'])}")
    if args.method != "both":
        raise LabcalError(f"--method chooses a three-axis estimator; the {cal.package} package's angles are "
                          "inferred as its certificate states")
    columns = tuple(f"v{s.axis}" for s in cal.sensors)
    source = args.csv
    if source is None:
        text = read_stream(sys.stdin, "standard input", "voltages")
        with tempfile.NamedTemporaryFile("w", suffix=".csv", delete=False) as tmp:
            tmp.write(text)
        source = tmp.name
    try:
        cols = read_numeric_csv(source, "voltages", columns, ("roll_deg",))
    finally:
        if args.csv is None:
            Path(source).unlink()
    if "roll_deg" in cols and args.roll_deg is not None:
        raise LabcalError("the roll is given twice: a roll_deg column and --roll-deg; give one")
    roll = cols.get("roll_deg", None if args.roll_deg is None else numpy.array(args.roll_deg))
    att = package_attitude(cal, numpy.column_stack([cols[c] for c in columns]),
                           None if roll is None else numpy.radians(roll),
                           None if args.roll_sd_deg is None else numpy.radians(args.roll_sd_deg))
    deg = numpy.degrees
    table = {"pitch_deg": deg(att.pitch), "roll_deg": deg(att.roll), "U95_pitch_deg": deg(att.U_pitch),
             "U95_roll_deg": deg(att.U_roll), "k": numpy.full(len(att.pitch), att.k)}
    if args.json:
        rows = [{k: (float(v[i]) if numpy.isfinite(v[i]) else None) for k, v in table.items()}
                for i in range(len(att.pitch))]
        sys.stdout.write(json.dumps({"package": cal.package, "roll_in_use": cal.roll_in_use,
                                     "coverage": "U95 = k·σ (Tripp & Tcheng §6), k = t₀.₉₇₅ of the fit's "
                                                 "degrees of freedom; U95_roll null where roll is not "
                                                 "inferred",
                                     "certificate": standing, "rows": rows}) + "\n")
    else:
        write_csv_rows(table)
    return 0


def write_csv_rows(table: dict[str, np.ndarray]) -> None:
    """The columns as CSV, a chunk of rows per write; a non-finite value is an empty cell."""
    sys.stdout.write(",".join(["row", *table]) + "\n")
    values = numpy.column_stack(list(table.values()))
    line = "%d" + ",%.9g" * values.shape[1] + "\n"
    for start in range(0, len(values), CHUNK_ROWS):
        chunk = values[start:start + CHUNK_ROWS]
        finite = numpy.isfinite(chunk).all(axis=1)
        if finite.all():  # one format operation for the whole chunk: a sixth faster than one per row
            numbered = numpy.column_stack([numpy.arange(start + 1, start + len(chunk) + 1), chunk])
            sys.stdout.write((line * len(chunk)) % tuple(numbered.ravel().tolist()))
            continue
        sys.stdout.write(
            "".join(
                line % (start + i + 1, *row)
                if finite[i]
                else ",".join([str(start + i + 1), *(f"{v:.9g}" if numpy.isfinite(v) else "" for v in row)])
                + "\n"
                for i, row in enumerate(chunk.tolist())
            )
        )


def write_json_rows(table: dict[str, np.ndarray], methods: list[str], dof: int, flags: list,
                    standing: dict | None = None) -> None:
    """One JSON document, streamed: the rows are formatted a chunk at a time, never all held as
    Python objects (a hundred thousand rows of dicts took 700 MiB)."""
    names = {m: [k for k in table if k.startswith(PREFIX[m])] for m in methods}
    header = {"coverage": "U95 = k·u_c per row, u_c from the calibration's complete covariance (a "
                          "certificate's uncertainty budget: Type A and B with their correlations), "
                          "k = t₀.₉₇₅(ν_eff) per row and angle (k_pitch, k_roll)",
              "degrees_of_freedom": dof, "certificate": standing}
    sys.stdout.write(json.dumps(header)[:-1] + ', "rows": [')
    n = len(next(iter(table.values())))
    for start in range(0, n, CHUNK_ROWS):
        chunk = {k: v[start:start + CHUNK_ROWS].tolist() for k, v in table.items()}
        rows = []
        for i in range(len(chunk[next(iter(chunk))])):
            row = {}
            for m in methods:
                values = {k.removeprefix(PREFIX[m]): chunk[k][i] for k in names[m]}
                values = {k: (v if math.isfinite(v) else None) for k, v in values.items()}
                if values["roll_deg"] is None:
                    values["roll_note"] = ROLL_UNDEFINED
                row[METHODS[m]] = values
            rows.append(json.dumps(row))
        sys.stdout.write(("\n" if start == 0 else ",\n") + ",\n".join(rows))
    sys.stdout.write("\n], \"gross_errors\": " + json.dumps([f.to_json() for f in flags]) + "}\n")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("attitude", help=summary("attitude"),
                       description="Convert voltages (CSV columns vx,vy,vz) to pitch and roll using a "
                                   "calibration: Soto's closed form (eqs. 5–7) and weighted least squares "
                                   "on the unit sphere (Tripp eqs. 99–104), each with standard "
                                   "uncertainties and 95 % expanded uncertainties (U95 = k·u_c from the "
                                   "certificate's complete uncertainty budget, k = t₀.₉₇₅(ν_eff)). "
                                   "Roll is empty where pitch is ±90°.")
    p.add_argument("--cert", required=True, help="fit.json or certificate.json of the instrument")
    p.add_argument("--csv", help="voltages CSV (default: standard input)")
    p.add_argument("--method", choices=["closed", "sphere", "both"], default="both",
                   help="estimator(s) to report (default %(default)s)")
    p.add_argument("--roll-deg", type=float, metavar="DEG",
                   help="a sensor package used at a measured roll (its certificate says the table or a roll "
                        "sensor): the roll, for every row (or a roll_deg column in the CSV)")
    p.add_argument("--roll-sd-deg", type=float, metavar="DEG",
                   help="that roll's standard deviation σ_R (default: the one the certificate states)")
    p.add_argument("--allow-outliers", action="store_true",
                   help="exit 0 even when rows fail the gross-error checks (|g| ≠ 1 g; the two methods "
                        "disagree); they are listed on stderr either way")
    p.add_argument("--unverified", action="store_true",
                   help="use an approved certificate whose signature is not by a key registered in the lab "
                        "database (forged, unknown or revoked key); every output then says UNVERIFIED")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_attitude)

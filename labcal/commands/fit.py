"""`labcal fit`."""

from __future__ import annotations

import argparse

from labcal.commands.common import out, print_json
from labcal.readings import read_readings


def cmd_fit(args: argparse.Namespace) -> int:
    from labcal.console import coefficient_table
    from labcal.fit import fit_linear

    fit = fit_linear(read_readings(args.readings))
    if args.json:
        print_json(fit.to_json())
    else:
        out.print(coefficient_table(fit))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("fit", help="fit calibration coefficients to a readings CSV",
                       description="Least-squares fit of V = B + gᵀS on the nominal gravity "
                                   "(Soto eqs. 13–21), with standard errors.")
    p.add_argument("readings", help="readings CSV (replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz)")
    p.add_argument("--model", choices=["linear"], default="linear", help="instrument model")
    p.add_argument("--json", action="store_true", help="print the fit as JSON on stdout")
    p.set_defaults(func=cmd_fit)

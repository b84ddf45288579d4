"""`labcal history`: an instrument's coefficients over its calibrations, with drift flagged."""

from __future__ import annotations

import argparse

from labcal.commands.common import add_db_option, out, print_changes, print_json


def cmd_history(args: argparse.Namespace) -> int:
    from rich.table import Table

    from labcal.analysis.fit import ROW_NAMES, SENSORS
    from labcal.documents.certificate import format_result
    from labcal.documents.history import RULE, certificates_for, changes, history_json, plot_history

    certs = certificates_for(args.serial, args.db, args.include_simulated)
    found = changes(certs)
    if args.plot:
        plot_history(args.serial, certs, found, args.plot)
    if args.json:
        print_json(history_json(args.serial, certs, found))
        return 0
    flagged = {(c.after, c.row, c.sensor) for c in found if c.flagged}
    out.print(f"Instrument {args.serial}: {len(certs)} calibration(s)")
    for n, c in enumerate(certs, start=1):
        simulated = "  (simulated: a dry run)" if c.station.simulated else ""
        out.print(f"  {n}  {c.calibrated_utc:%Y-%m-%d %H:%M} UTC  {c.certificate_id}{simulated}")
    for j, sensor in enumerate(SENSORS):
        table = Table(title=f"sensor {sensor}: coefficients ± U (95 %)")
        table.add_column("#", justify="right")
        for i, row in enumerate(ROW_NAMES):
            table.add_column(f"{row} ({'V' if i == 0 else 'V/g'})", justify="right")
        for n, c in enumerate(certs, start=1):
            cells = [format_result(c.coefficients[i, j], c.U[i, j]) for i in range(len(ROW_NAMES))]
            table.add_row(str(n), *(f"[bold red]{v} ▲[/]" if (c.certificate_id, i, j) in flagged else v
                                    for i, v in enumerate(cells)))
        out.print(table)
    print_changes([f"{ch.name} from {ch.before} to {ch.after}: Δ = {ch.delta:+.3g}, "
                   f"limit k·√(u₁²+u₂²) = {ch.limit:.2g} (k = {ch.k:.2f})" for ch in found if ch.flagged],
                  f"{len(certs)} calibration(s)", RULE, args.plot)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("history", help="an instrument's coefficients over time, drift flagged",
                       description="Every certificate of an instrument from the lab's database, "
                                   "oldest first: each coefficient with its expanded uncertainty, and a flag "
                                   "wherever it changed between consecutive calibrations by more than the "
                                   "combined expanded uncertainty, |Δ| > k·√(u₁² + u₂²).")
    p.add_argument("serial", metavar="SERIAL", help="instrument serial number (dry runs: SIMULATED)")
    p.add_argument("--plot", metavar="FILE", help="also plot each coefficient over time (PNG, PDF or SVG)")
    p.add_argument("--include-simulated", action="store_true",
                   help="also show dry runs made under this serial (left out by default: never mistaken for "
                        "a real calibration)")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_history)

"""`labcal history`: an instrument's coefficients over its calibrations, with drift flagged."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, err, out, print_history, print_json
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import histories
else:
    histories = lazy("labcal.app.histories")  # not for --help: SQLAlchemy, scipy, matplotlib


def cmd_history(args: argparse.Namespace) -> int:
    history = histories.instrument_history(
        histories.InstrumentHistory(args.serial, args.db, args.include_simulated, args.plot))
    if history.stale:
        err.print(history.stale, markup=False)
    if args.json:
        print_json(history.document)
        return 0
    out.print(f"Instrument {args.serial}: {len(history.entries)} calibration(s)")
    print_history(history)
    return 0
def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("history", help=summary("history"),
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

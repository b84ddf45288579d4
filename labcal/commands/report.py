"""`labcal report`: certificate, report (HTML + PDF) and history entry of a finished run."""

from __future__ import annotations

import argparse
from datetime import date
from typing import TYPE_CHECKING

from rich.markup import escape

from labcal.commands import summary
from labcal.commands.common import (
    add_db_option,
    angle_deg,
    bounded,
    command_line,
    err,
    literal,
    out,
    print_json,
)
from labcal.lazy import lazy

if TYPE_CHECKING:
    from rich import table as _rich_table
    from rich.table import Table as RichTable

    from labcal.app import certificates
else:
    certificates = lazy("labcal.app.certificates")  # not for --help: SQLAlchemy, scipy, matplotlib
    _rich_table = lazy("rich.table")  # start-up without rich


def rich_table(t) -> RichTable:
    """A report table (`labcal.documents.report_tables.Table`) for the terminal. Its text is the
    report's, not rich markup: escaped, so that "[certificate]" (a station file's section) is printed,
    not eaten."""
    table = _rich_table.Table(title=escape(t.title), caption=escape(t.caption) if t.caption else None)
    for h in t.header:
        table.add_column(escape(h), justify="right")
    for i, row in enumerate(t.rows):
        table.add_row(*(f"[bold red]{escape(c)}[/]" if (i, j) in t.emphasis else escape(c)
                        for j, c in enumerate(row)))
    return table


def cmd_report(args: argparse.Namespace) -> int:
    issued = certificates.issue_certificate(certificates.IssueCertificate(
        args.run_dir, args.db, args.station, args.tolerance_deg, args.bias_max_v,
        tuple(args.usage_pitch) if args.usage_pitch else None,
        tuple(args.usage_roll) if args.usage_roll else None,
        args.monte_carlo, args.serial, args.operator, args.customer, args.manufacturer, args.model,
        args.received, args.in_use_samples))
    for note in issued.notes:
        err.print(f"[yellow]note:[/] {note}")
    if args.json:
        print_json(issued.to_json())
        return 0
    result, cert = issued.outputs, issued.outputs.certificate
    for table in issued.tables:
        out.print(rich_table(table))
    out.print(f"Certificate {literal(cert.number)}: {literal(result.certificate_path)}")
    if issued.changed is not None:
        out.print(escape(issued.changed[0].upper() + issued.changed[1:]))
    out.print(f"Report: {literal(result.html_path)}, {literal(result.pdf_path)}")
    out.print(f"Digital Calibration Certificate: {literal(result.dcc_path)}")
    history = command_line("labcal", "history", cert.instrument.serial)
    out.print(f"Stored in {literal(result.database)} (see `{history}`)")
    return 0


def _day(text: str):
    """A receipt date: a real day, and not after today (an item is received before it is calibrated)."""
    try:
        day = date.fromisoformat(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a date (YYYY-MM-DD)") from None
    if day > date.today():
        raise argparse.ArgumentTypeError(f"{text} is in the future (today is {date.today().isoformat()}); "
                                         "give the date the item was received")
    return day


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("report", help=summary("report"),
                       description="Regenerate certificate.json, report.html (self-contained) and report.pdf "
                                   "in a run directory from its readings, plan and run record, and store the "
                                   "certificate in the lab's database. Tolerances come from the command line "
                                   "or a station file's [certificate] section (the command line wins).")
    p.add_argument("run_dir", metavar="RUN_DIR", help="a complete run directory (readings.csv, plan.toml, "
                                                      "run.json)")
    p.add_argument("--tolerance-deg", type=angle_deg(180), metavar="X",
                   help="pass when the largest U95 of pitch and of roll over the usage envelope is ≤ X: "
                        "degrees, or with its unit (7.5arcsec)")
    p.add_argument("--bias-max-v", type=bounded(float, 0, 1000, lo_open=True), metavar="V",
                   help="pass a sensor's bias when |B| + U(B) ≤ V")
    p.add_argument("--usage-pitch", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="usage envelope pitch range in ° (default -60 60)")
    p.add_argument("--usage-roll", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="usage envelope roll range in ° (default -180 180)")
    p.add_argument("--in-use-samples", type=bounded(int, 1, 1_000_000), metavar="N",
                   help="samples a reading of the instrument in use averages (default: as many as the "
                        "calibration's windows); the certificate states it, and its U95 applies to it")
    p.add_argument("--station", metavar="FILE",
                   help="station TOML whose [certificate] section sets laboratory, tolerances and usage "
                        "envelope, and whose [uncertainty] and [[traceability]] give the Type B inputs "
                        "(default: the station the run was journaled with)")
    p.add_argument("--monte-carlo", type=int, default=0, metavar="N",
                   help="check the uncertainty budget by JCGM 101 Monte Carlo with N trials (e.g. 10000)")
    p.add_argument("--serial", help="instrument serial, if the run did not record it (dry runs: SIMULATED)")
    p.add_argument("--operator", help="operator's name, if the run did not record it")
    p.add_argument("--customer", metavar="NAME", help="the customer, as the certificate names them")
    p.add_argument("--manufacturer", metavar="NAME", help="the instrument's manufacturer")
    p.add_argument("--model", metavar="MODEL", help="the instrument's model")
    p.add_argument("--received", type=_day, metavar="YYYY-MM-DD", help="the date the item was received")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print a summary as JSON on stdout")
    p.set_defaults(func=cmd_report)

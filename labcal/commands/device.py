"""`labcal device history`: the calibration device's misalignments over time, changes flagged."""

from __future__ import annotations

import argparse

from labcal.commands.common import add_db_option, out, print_changes, print_json


def cmd_history(args: argparse.Namespace) -> int:
    from labcal.analysis.kinematics import MISALIGNMENT_NAMES
    from labcal.documents.device_history import RULE, changes, estimates_for, history_json, plot_history

    estimates = estimates_for(args.device_id, args.db)
    found = changes(estimates)
    if args.plot:
        plot_history(args.device_id, estimates, found, args.plot)
    if args.json:
        print_json(history_json(args.device_id, estimates, found))
        return 0
    from rich.table import Table

    flagged = {(c.after, c.name) for c in found if c.flagged}
    table = Table(title=f"Calibration device {args.device_id}: misalignments (″) ± U (95 %)")
    for col in ("#", "calibrated (UTC)", "run", *MISALIGNMENT_NAMES):
        table.add_column(col, justify="right")
    for n, e in enumerate(estimates, start=1):
        cells = [f"{e.value_arcsec[m]:+.2f} ± {e.U_arcsec[m]:.2f}" for m in MISALIGNMENT_NAMES]
        table.add_row(str(n), e.calibrated_utc[:16].replace("T", " "), e.source,
                      *(f"[bold red]{c} ▲[/]" if (e.source, m) in flagged else c
                        for c, m in zip(cells, MISALIGNMENT_NAMES, strict=True)))
    out.print(table)
    print_changes([f"{ch.name} from {ch.before} to {ch.after}: Δ = {ch.delta_arcsec:+.2f}″, "
                   f"limit √(U₁²+U₂²) = {ch.limit_arcsec:.2f}″" for ch in found if ch.flagged],
                  f"{len(estimates)} estimate(s)", RULE, args.plot)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    device = sub.add_parser("device", help="the calibration device's own history",
                            description="What every calibration has measured of the calibration device "
                                        "itself: its misalignments a, b, d, e, f, k (Soto Table 1).")
    actions = device.add_subparsers(dest="device_command", required=True, metavar="ACTION")
    p = actions.add_parser("history", help="the device's misalignments over time, changes flagged",
                           description="Every device-model estimate of a calibration device's misalignments "
                                       "from the lab's database, oldest first, each ± U (95 %), with a flag "
                                       "wherever one changed between consecutive calibrations by more than "
                                       "the combined expanded uncertainty √(U₁² + U₂²).")
    p.add_argument("device_id", metavar="DEVICE_ID", help="calibration-device id (dry runs: SIMULATED)")
    p.add_argument("--plot", metavar="FILE", help="also plot each misalignment over time (PNG, PDF or SVG)")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_history)

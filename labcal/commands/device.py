"""`labcal device history`: the calibration device's misalignments over time, changes flagged."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, err, print_history, print_json
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import histories
else:
    histories = lazy("labcal.app.histories")  # not for --help: SQLAlchemy, scipy, matplotlib


def cmd_history(args: argparse.Namespace) -> int:
    history = histories.device_history(histories.DeviceHistory(args.device_id, args.db, args.plot))
    if history.stale:
        err.print(history.stale, markup=False)
    if args.json:
        print_json(history.document)
        return 0
    print_history(history)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    device = sub.add_parser("device", help=summary("device"),
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

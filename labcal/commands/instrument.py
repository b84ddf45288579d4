"""`labcal instrument` (the lab's instrument register) and `labcal due` (what falls due, the recall):
`labcal.app.instruments`."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, day_given, err, lab_of, out, print_json, register_write
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import instruments
else:
    instruments = lazy("labcal.app.instruments")  # not for --help: SQLAlchemy, scipy, matplotlib

STATUSES = ("active", "retired", "out-for-repair")  # as labcal.app.instruments.STATUSES, for --help
SIMULATED_HELP = "count dry runs' certificates as calibrations too (as labcal history --include-simulated)"


def _fields(args: argparse.Namespace):
    return instruments.InstrumentFields(args.model, args.manufacturer, args.customer, args.owner,
                                        args.location, args.interval, args.status, args.notes)


def _interval(days: int | None) -> str:
    return "not set" if days is None else f"{days} days"


def _print_row(i) -> None:
    out.print(f"{i.serial}\t{i.model or '-'}\t{i.customer or '-'}\t{i.status}\t"
              f"interval {_interval(i.interval_days)}", markup=False)


def cmd_add(args: argparse.Namespace) -> int:
    fields = _fields(args)
    fields.values()  # checked before the database is opened (or created)
    return register_write(args, instruments.add, fields, create=True,
                          said=lambda i, lab: f"{i.serial} registered in {lab.shown}")


def cmd_edit(args: argparse.Namespace) -> int:
    return register_write(args, instruments.edit, _fields(args), create=False,
                          said=lambda i, lab: f"{i.serial} updated")


def cmd_list(args: argparse.Namespace) -> int:
    lab = lab_of(args.db, create=False)
    try:
        found = instruments.listed(lab, args.search)
    finally:
        lab.close()
    if args.json:
        print_json({"instruments": [i.to_json() for i in found]})
        return 0
    if not found:
        out.print("no instruments" + (f" matching {args.search!r}" if args.search else
                                      " (`labcal instrument add SERIAL --interval 12m`)"), markup=False)
    for i in found:
        _print_row(i)
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    today = day_given(args.on)
    lab = lab_of(args.db, create=False)
    try:
        card = instruments.card(lab, args.serial, args.db, today, args.include_simulated)
    finally:
        lab.close()
    if args.json:
        print_json(card.to_json())
        return 0
    i = card.instrument
    for label, value in (("serial", i.serial), ("model", i.model), ("manufacturer", i.manufacturer),
                         ("customer", i.customer), ("owner", i.owner), ("location", i.location),
                         ("status", i.status), ("interval", _interval(i.interval_days)), ("notes", i.notes)):
        if value:
            out.print(f"{label:<18}{value}", markup=False)
    last = card.last
    if last is None:
        out.print(f"{'last calibration':<18}none (no certificate in the history)", markup=False)
    else:
        verdict = {True: "in tolerance", False: "OUT OF TOLERANCE", None: "not judged"}[last.in_tolerance]
        out.print(f"{'last calibration':<18}{last.on.isoformat()}, certificate {last.certificate_id} "
                  f"({verdict}; {len(card.history)} calibration(s) in all)", markup=False)
    if card.next_due is not None:
        left = (card.next_due - today).days
        when = (f"overdue by {-left} day(s)" if left < 0 else "due now" if left == 0 else f"in {left} day(s)")
        out.print(f"{'next due':<18}{card.next_due.isoformat()} ({when})", markup=False)
    else:
        out.print(f"{'next due':<18}no interval set (`labcal instrument edit {i.serial} --interval 12m`)",
                  markup=False)
    if card.suggested_days is not None:
        result = "an in-tolerance" if last and last.in_tolerance else "an out-of-tolerance"
        out.print(f"{'suggested':<18}{card.suggested_days} days (ILAC-G24:2007 method 1, staircase: "
                  f"from {i.interval_days} days after {result} result)", markup=False)
    return 0


def cmd_due(args: argparse.Namespace) -> int:
    today = day_given(args.on)
    lab = lab_of(args.db, create=False)
    try:
        found = instruments.due(lab, args.db, args.within, today, args.include_simulated)
    finally:
        lab.close()
    sent = failed = 0
    if args.notify and found:
        sent, failed = instruments.notify_due(found, lambda line: err.print(line, markup=False))
    if args.json:
        doc: dict = {"on": today.isoformat(), "within": args.within, "due": [d.to_json() for d in found]}
        if args.notify:
            doc["notifications"] = {"sent": sent, "failed": failed}
        print_json(doc)
    else:
        if not found:
            out.print(f"nothing due within {args.within} of {today.isoformat()}", markup=False)
        for d in found:
            i, last = d.card.instrument, d.card.last
            state = f"OVERDUE {-d.days_left} d" if d.overdue else f"due in {d.days_left} d"
            out.print(f"{i.serial}\t{d.due.isoformat()}\t{state}\t"
                      f"last {'never' if last is None else last.on.isoformat()}\t{i.customer or '-'}\t"
                      f"{i.location or '-'}", markup=False)
        if args.notify:
            err.print(f"{sent} notification(s) sent" + (f", {failed} not sent" if failed else ""),
                      markup=False)
    return 1 if failed else 0


def _fields_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", metavar="TEXT", help="the instrument's model")
    p.add_argument("--manufacturer", metavar="TEXT", help="its manufacturer")
    p.add_argument("--customer", metavar="TEXT", help="whose it is (the certificate's customer)")
    p.add_argument("--owner", metavar="TEXT", help="who looks after it")
    p.add_argument("--location", metavar="TEXT", help="where it is kept")
    p.add_argument("--interval", metavar="N{d,m,y}",
                   help="its calibration interval: 365d, 12m or 1y (a month is 365.25/12 days)")
    p.add_argument("--status", choices=STATUSES, help="active (default), retired or out-for-repair")
    p.add_argument("--notes", metavar="TEXT", help="a line of notes")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("instrument", help=summary("instrument"),
                       description="The lab's instrument register: each instrument by serial (the same "
                                   "instrument whatever the case), with its model, customer, location and "
                                   "calibration interval. Once it holds any instrument, `labcal run` asks "
                                   "before certifying a serial it does not hold (and refuses with --yes, "
                                   "unless the lab file sets [instruments] allow_adhoc = true).")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    add = verbs.add_parser("add", help="register an instrument", description="Register an instrument.")
    add.add_argument("serial", metavar="SERIAL")
    _fields_options(add)
    add_db_option(add)
    add.add_argument("--json", action="store_true", help="print as JSON on stdout")
    add.set_defaults(func=cmd_add)
    edit = verbs.add_parser("edit", help="change a registered instrument's details",
                            description="Change what is given of a registered instrument (any case of "
                                        "its serial finds it).")
    edit.add_argument("serial", metavar="SERIAL")
    _fields_options(edit)
    add_db_option(edit)
    edit.add_argument("--json", action="store_true", help="print as JSON on stdout")
    edit.set_defaults(func=cmd_edit)
    listing = verbs.add_parser("list", help="the registered instruments, by serial",
                               description="The registered instruments, by serial.")
    listing.add_argument("--search", metavar="TEXT", help="only those whose serial, customer or model holds "
                                                          "TEXT (any case)")
    add_db_option(listing)
    listing.add_argument("--json", action="store_true", help="print as JSON on stdout")
    listing.set_defaults(func=cmd_list)
    show = verbs.add_parser("show", help="an instrument, its last calibration and next due date",
                            description="An instrument's details, its last calibration (the newest "
                                        "certificate that is not a dry run's), when it is next due (last "
                                        "calibration + interval; never calibrated: due now) and a suggested "
                                        "interval (ILAC-G24:2007 method 1, staircase).")
    show.add_argument("serial", metavar="SERIAL")
    show.add_argument("--on", metavar="YYYY-MM-DD", help="as of this date (default: today)")
    show.add_argument("--include-simulated", action="store_true", help=SIMULATED_HELP)
    add_db_option(show)
    show.add_argument("--json", action="store_true", help="print as JSON on stdout")
    show.set_defaults(func=cmd_show)

    p = sub.add_parser("due", help=summary("due"),
                       description="Active registered instruments with an interval that are overdue or fall "
                                   "due within --within, soonest first (never calibrated: due now). With "
                                   "--notify, one notification per instrument through the lab's apprise URLs "
                                   "(run it daily from cron).")
    p.add_argument("--within", default="30d", metavar="N{d,m,y}", help="how far ahead (default 30d)")
    p.add_argument("--on", metavar="YYYY-MM-DD", help="as of this date (default: today)")
    p.add_argument("--include-simulated", action="store_true", help=SIMULATED_HELP)
    p.add_argument("--notify", action="store_true",
                   help="send one notification per instrument listed (exit 1 if any was not sent)")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_due)

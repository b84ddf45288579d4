"""`labcal standard` (the lab's reference standards, and an approver's override for an overdue one):
`labcal.app.standards`."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, day_given, lab_of, out, print_json, register_write
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import standards
else:
    standards = lazy("labcal.app.standards")  # SQLAlchemy and pydantic: not for --help

KINDS = ("dmm", "pitch-table", "roll-table", "reference-level", "other")  # as labcal.app.standards.KINDS


def _fields(args: argparse.Namespace):
    return standards.StandardFields(args.kind, args.model, args.manufacturer, args.certificate,
                                    args.issued_by, args.calibrated, args.due, args.bench, args.status,
                                    args.notes)


def _row(s) -> str:
    return (f"{s.serial}\t{s.kind}\t{s.model or '-'}\tcertificate {s.certificate}\t"
            f"due {s.due_on.isoformat()}\tbench {s.bench or '-'}\t{s.status}")


def cmd_add(args: argparse.Namespace) -> int:
    fields = _fields(args)
    fields.values()  # checked before the database is opened (or created)
    return register_write(args, standards.add, fields, create=True,
                          said=lambda s, lab: f"{s.serial} registered in {lab.shown}: due "
                                              f"{s.due_on.isoformat()}")


def cmd_edit(args: argparse.Namespace) -> int:
    return register_write(args, standards.edit, _fields(args), create=False,
                          said=lambda s, lab: f"{s.serial} updated: due {s.due_on.isoformat()}")


def cmd_list(args: argparse.Namespace) -> int:
    today = day_given(args.on)
    lab = lab_of(args.db, create=False)
    try:
        found = standards.listed(lab, args.bench)
    finally:
        lab.close()
    if args.json:
        print_json({"on": today.isoformat(),
                    "standards": [{**s.to_json(), "overdue": s.due_on < today} for s in found]})
        return 0
    if not found:
        out.print("no reference standards" + (f" on bench {args.bench!r}" if args.bench else
                                              " (`labcal standard add SERIAL --kind dmm …`)"), markup=False)
    for s in found:
        out.print(_row(s) + ("\tOVERDUE" if s.due_on < today else ""), markup=False)
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    today = day_given(args.on)
    lab = lab_of(args.db, create=False)
    try:
        card = standards.card(lab, args.serial, today, args.db)
    finally:
        lab.close()
    if args.json:
        print_json(card.to_json())
        return 0
    s = card.standard
    for label, value in (("serial", s.serial), ("kind", s.kind), ("model", s.model),
                         ("manufacturer", s.manufacturer), ("certificate", s.certificate),
                         ("issued by", s.issued_by), ("calibrated", s.calibrated_on.isoformat()),
                         ("bench", s.bench), ("status", s.status), ("notes", s.notes)):
        if value:
            out.print(f"{label:<14}{value}", markup=False)
    left = (s.due_on - today).days
    state = f"OVERDUE by {-left} day(s)" if left < 0 else f"in {left} day(s)"
    out.print(f"{'due':<14}{s.due_on.isoformat()} ({state})", markup=False)
    for row, problem in card.overrides:
        verdict = "holds" if problem is None else f"does not hold: {problem}"
        out.print(f"{'override':<14}by {row.approver} ({row.role}) {row.recorded_utc}, until "
                  f"{row.valid_until.isoformat()}: {row.reason} — {verdict}", markup=False)
    return 0


def cmd_override(args: argparse.Namespace) -> int:
    request = standards.RecordOverride(args.serial, args.reason, args.by, args.role, args.key, args.until,
                                       args.db)
    standard, row = standards.record_override(request, day_given(None))
    if args.json:
        print_json({"serial": standard.serial, **standards.override_json(row)})
    else:
        out.print(f"override recorded: runs may use {standard.serial} (due {standard.due_on.isoformat()}) "
                  f"until {row.valid_until.isoformat()}, by {row.approver} ({row.role}): {row.reason}",
                  markup=False)
    return 0


def _fields_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--kind", choices=KINDS, help="what it is (a certificate's traceability names it so)")
    p.add_argument("--model", metavar="TEXT", help="its model")
    p.add_argument("--manufacturer", metavar="TEXT", help="its manufacturer")
    p.add_argument("--certificate", metavar="NUMBER", help="the number of its calibration certificate")
    p.add_argument("--issued-by", metavar="TEXT", help="the laboratory that calibrated it")
    p.add_argument("--calibrated", metavar="YYYY-MM-DD", help="when it was calibrated")
    p.add_argument("--due", metavar="YYYY-MM-DD", help="when its calibration falls due")
    p.add_argument("--bench", metavar="STATION",
                   help="the station that uses it, by its name in the lab database (its LABCAL_STATION)")
    p.add_argument("--status", choices=("active", "retired"), help="active (default) or retired")
    p.add_argument("--notes", metavar="TEXT", help="a line of notes")


def _common(p: argparse.ArgumentParser) -> None:
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("standard", help=summary("standard"),
                       description="The lab's reference standards: the DMM and the tables, each with its "
                                   "calibration certificate and due date, and the bench that uses it. A run "
                                   "uses the standards registered to its bench and those its station file "
                                   "names (standards = [\"SERIAL\", …]); an overdue one stops the run before "
                                   "anything moves unless an approver has recorded an override.")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    add = verbs.add_parser("add", help="register a standard",
                           description="Register a reference standard with its calibration (--kind, "
                                       "--certificate, --calibrated and --due are required).")
    add.add_argument("serial", metavar="SERIAL")
    _fields_options(add)
    _common(add)
    add.set_defaults(func=cmd_add)
    edit = verbs.add_parser("edit", help="change a standard's details (a recalibration: new --certificate, "
                                         "--calibrated, --due)",
                            description="Change what is given of a registered standard (any case of its "
                                        "serial finds it).")
    edit.add_argument("serial", metavar="SERIAL")
    _fields_options(edit)
    _common(edit)
    edit.set_defaults(func=cmd_edit)
    listing = verbs.add_parser("list", help="the registered standards, by serial",
                               description="The registered standards, by serial; overdue ones marked.")
    listing.add_argument("--bench", metavar="STATION", help="only those the station uses")
    listing.add_argument("--on", metavar="YYYY-MM-DD", help="as of this date (default: today)")
    _common(listing)
    listing.set_defaults(func=cmd_list)
    show = verbs.add_parser("show", help="a standard, when it is due, and its overrides",
                            description="A standard's details, when it is due, and every override recorded "
                                        "for it, each with whether it holds.")
    show.add_argument("serial", metavar="SERIAL")
    show.add_argument("--on", metavar="YYYY-MM-DD", help="as of this date (default: today)")
    _common(show)
    show.set_defaults(func=cmd_show)
    override = verbs.add_parser(
        "override", help="an approver lets runs use an overdue standard, with a reason",
        description="Record an approver's override: runs may use the standard although it is overdue, "
                    "until --until (default 7 days, at most 31), while its due date stays the one it has "
                    "now. Signed with the approver's registered key (`labcal certificate approvers add`); "
                    "the certificate of every run under it states it.")
    override.add_argument("serial", metavar="SERIAL")
    override.add_argument("--reason", required=True, metavar="TEXT", help="why (stated on the certificate)")
    override.add_argument("--by", required=True, metavar="NAME", help="the approver's registered name")
    override.add_argument("--role", required=True, metavar="ROLE", help="the approver's registered role")
    override.add_argument("--key", required=True, metavar="KEYFILE", help="the approver's private key (PEM)")
    override.add_argument("--until", metavar="YYYY-MM-DD", help="the last day it holds (default: 7 days on)")
    _common(override)
    override.set_defaults(func=cmd_override)

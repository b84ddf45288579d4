"""`labcal user`: the lab server's users (`labcal.app.users`)."""

from __future__ import annotations

import argparse
import sys

from labcal.commands import summary
from labcal.commands.common import out, print_json
from labcal.errors import LabcalError

# as labcal.app.users.ROLES, without importing argon2 for --help
ROLES = ("technician", "approver", "viewer")


def _lab(option: str | None, create: bool):
    try:
        from labcal.app.labdatabase import OpenLab, open_lab
    except ImportError as exc:
        raise LabcalError(f"labcal user needs the lab server's packages ({exc.name} is missing): "
                          "pip install 'labcal[lab]'") from None
    return open_lab(OpenLab(option, must_exist=not create))  # `user add` may create the lab database


def _password(given: str | None) -> str:
    if given is not None:
        if not given:
            raise LabcalError("--password may not be empty")
        return given
    import getpass

    first = getpass.getpass("Password for the web login: ")
    if not first:
        raise LabcalError("the password may not be empty; nothing was added")
    if getpass.getpass("The same password again: ") != first:
        raise LabcalError("the two passwords differ; nothing was added")
    return first


def cmd_add(args: argparse.Namespace) -> int:
    from labcal.app import users

    request = users.AddUser(args.name, args.role, _password(args.password))  # before the database is touched
    lab = _lab(args.db, create=True)
    try:
        added = users.add(lab, request)
    finally:
        lab.close()
    user, token = added.user, added.token
    if args.json:
        print_json({**user.to_json(), "token": token})
        return 0
    sys.stderr.write(f"{user.name} ({user.role}) added. Their API token, shown this once (give it as "
                     "Authorization: Bearer TOKEN):\n")
    sys.stdout.write(token + "\n")  # alone on its line, unstyled, for scripts
    return 0


def cmd_list(args: argparse.Namespace) -> int:
    from labcal.app import users

    lab = _lab(args.db, create=False)
    try:
        found = users.listed(lab)
    finally:
        lab.close()
    if args.json:
        print_json({"users": [u.to_json() for u in found]})
        return 0
    if not found:
        out.print("no users (`labcal user add NAME --role viewer`)")
    for u in found:
        state = "active" if u.active else f"disabled {u.disabled_utc}"
        out.print(f"{u.name}\t{u.role}\tadded {u.created_utc}\t{state}")
    return 0


def cmd_disable(args: argparse.Namespace) -> int:
    from labcal.app import users

    lab = _lab(args.db, create=False)
    try:
        u = users.disable(lab, args.name)
    finally:
        lab.close()
    if args.json:
        print_json(u.to_json())
        return 0
    out.print(f"{u.name} disabled at {u.disabled_utc}: their password, token and sessions no longer work")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("user", help=summary("user"),
                       description="Users of the lab server (`labcal serve`): a viewer reads, a technician "
                                   "reads, an approver also approves certificates. Each has a password for "
                                   "the web login and an API token; both are stored only as hashes.")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    db_help = "the lab database (default $LABCAL_DB, else the lab file's)"
    add = verbs.add_parser("add", help="add a user; prints their API token once")
    add.add_argument("name", metavar="NAME")
    add.add_argument("--role", required=True, choices=ROLES)
    add.add_argument("--password", default=None, metavar="PW",
                     help="the web login's password (default: asked for, without echo)")
    add.add_argument("--db", default=None, metavar="URL", help=db_help)
    add.add_argument("--json", action="store_true", help="print as JSON on stdout (the token under 'token')")
    add.set_defaults(func=cmd_add)
    listing = verbs.add_parser("list", help="every user, active and disabled")
    listing.add_argument("--db", default=None, metavar="URL", help=db_help)
    listing.add_argument("--json", action="store_true", help="print as JSON on stdout")
    listing.set_defaults(func=cmd_list)
    disable = verbs.add_parser("disable", help="disable a user (the record stays)")
    disable.add_argument("name", metavar="NAME")
    disable.add_argument("--db", default=None, metavar="URL", help=db_help)
    disable.add_argument("--json", action="store_true", help="print as JSON on stdout")
    disable.set_defaults(func=cmd_disable)

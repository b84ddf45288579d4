"""`labcal user`: the lab server's users (`labcal.app.users`)."""

from __future__ import annotations

import argparse
import getpass
import os
import sys
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import out, print_json, warn_if_secret_in
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import audit, users
else:
    audit = lazy("labcal.app.audit")  # SQLAlchemy: not for --help
    users = lazy("labcal.app.users")  # SQLAlchemy and argon2: not for --help

# as labcal.app.users.ROLES, without importing argon2 for --help
ROLES = ("technician", "approver", "viewer")
PASSWORD_ENV = "LABCAL_PASSWORD"


def _lab(option: str | None, create: bool):
    warn_if_secret_in(option)
    try:
        from labcal.app.labdatabase import OpenLab, open_lab
    except ImportError as exc:
        raise LabcalError(f"labcal user needs the lab server's packages ({exc.name} is missing): "
                          "pip install 'labcal[lab]'") from None
    return open_lab(OpenLab(option, must_exist=not create))  # `user add` may create the lab database


def _password(args: argparse.Namespace, done: str = "nothing was added") -> str:
    """The new password: from stdin (--password-stdin), $LABCAL_PASSWORD, else asked twice (without
    echo at a terminal). Never from the command line, where every local account sees it (``ps``):
    --password still works, with a warning, for the scripts that use it."""
    if args.password is not None:
        sys.stderr.write(f"warning: --password is visible to every account on this machine (ps); use "
                         f"--password-stdin or {PASSWORD_ENV}\n")
        if not args.password:
            raise LabcalError(f"--password may not be empty; {done}")
        return args.password
    if args.password_stdin:
        given = sys.stdin.readline().rstrip("\r\n")
        if not given:
            raise LabcalError(f"no password on stdin (--password-stdin); {done}")
        return given
    if os.environ.get(PASSWORD_ENV):
        return os.environ[PASSWORD_ENV]
    def ask(prompt: str) -> str:
        if sys.stdin.isatty():
            return getpass.getpass(prompt)  # without echo
        line = sys.stdin.readline()  # piped: the lines as given
        if not line:
            raise EOFError
        return line.rstrip("\r\n")

    try:
        first = ask("Password for the web login: ")
        if not first:
            raise LabcalError(f"the password may not be empty; {done}")
        if ask("The same password again: ") != first:
            raise LabcalError(f"the two passwords differ; {done}")
    except EOFError:
        raise LabcalError(f"no password given: type it at a terminal, or give it on stdin (--password-stdin) "
                          f"or in {PASSWORD_ENV}; {done}") from None
    return first


def cmd_add(args: argparse.Namespace) -> int:
    request = users.AddUser(args.name, args.role, _password(args))  # before the database is touched
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
    lab = _lab(args.db, create=False)
    try:
        found = users.listed(lab)
        locked = {u.name: audit.account_state(lab, u.name).locked for u in found}
    finally:
        lab.close()
    if args.json:
        print_json({"users": [{**u.to_json(), "locked": locked[u.name]} for u in found]})
        return 0
    if not found:
        out.print("no users (`labcal user add NAME --role viewer`)")
    for u in found:
        state = "active" if u.active else f"disabled {u.disabled_utc}"
        if locked[u.name]:
            state += ", locked out (`labcal user unlock`)"
        out.print(f"{u.name}\t{u.role}\tadded {u.created_utc}\t{state}", markup=False)
    return 0


def cmd_disable(args: argparse.Namespace) -> int:
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


def cmd_passwd(args: argparse.Namespace) -> int:
    password = _password(args, "the password is unchanged")
    lab = _lab(args.db, create=False)
    try:
        u = users.change_password(lab, args.name, password)
    finally:
        lab.close()
    out.print(f"{u.name}'s password changed: the old one no longer works, and a lockout is lifted")
    return 0


def cmd_token(args: argparse.Namespace) -> int:
    lab = _lab(args.db, create=False)
    try:
        issued = users.new_token(lab, args.name)
    finally:
        lab.close()
    if args.json:
        print_json({**issued.user.to_json(), "token": issued.token})
        return 0
    sys.stderr.write(f"{issued.user.name}'s new API token, shown this once (the old one no longer works; "
                     f"this one for {users.TOKEN_DAYS} days):\n")
    sys.stdout.write(issued.token + "\n")
    return 0


def cmd_unlock(args: argparse.Namespace) -> int:
    lab = _lab(args.db, create=False)
    try:
        before = users.unlock(lab, args.name)
    finally:
        lab.close()
    was = "was locked out" if before.locked else f"had {before.failures} failed password(s) in a row"
    out.print(f"{args.name} {was}; unlocked: their next password is heard")
    return 0


def cmd_audit(args: argparse.Namespace) -> int:
    lab = _lab(args.db, create=False)
    try:
        broken = audit.verify(lab)
        rows = audit.newest(lab, args.last)
    finally:
        lab.close()
    if args.json:
        print_json({"chain_intact": broken is None, "first_broken_id": broken,
                    "rows": [r.to_json() for r in rows]})
    else:
        for r in reversed(rows):
            out.print(f"{r.utc}\t{r.kind}\t{r.account or '-'}\tby {r.actor or 'anonymous'}\tfrom "
                      f"{r.client or '-'}\t{r.detail or ''}", markup=False)
    if broken is not None:
        raise LabcalError(f"the audit trail was altered: row {broken} does not follow the row before it")
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
    _password_options(add)
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
    passwd = verbs.add_parser("passwd", help="give a user a new password (lifts a lockout)")
    passwd.add_argument("name", metavar="NAME")
    _password_options(passwd)
    passwd.add_argument("--db", default=None, metavar="URL", help=db_help)
    passwd.set_defaults(func=cmd_passwd)
    token = verbs.add_parser("token", help="issue a user a new API token (the old one stops working)")
    token.add_argument("name", metavar="NAME")
    token.add_argument("--db", default=None, metavar="URL", help=db_help)
    token.add_argument("--json", action="store_true",
                       help="print as JSON on stdout (the token under 'token')")
    token.set_defaults(func=cmd_token)
    unlock = verbs.add_parser("unlock", help="lift a user's lockout after repeated wrong passwords")
    unlock.add_argument("name", metavar="NAME")
    unlock.add_argument("--db", default=None, metavar="URL", help=db_help)
    unlock.set_defaults(func=cmd_unlock)
    trail = verbs.add_parser("audit", help="the audit trail's newest rows, and whether its chain is intact "
                                           "(exit 2 if not)")
    trail.add_argument("--last", type=int, default=50, metavar="N", help="how many rows (default 50)")
    trail.add_argument("--db", default=None, metavar="URL", help=db_help)
    trail.add_argument("--json", action="store_true", help="print as JSON on stdout")
    trail.set_defaults(func=cmd_audit)


def _password_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--password-stdin", action="store_true",
                   help=f"read the password from the first line of stdin (else ${PASSWORD_ENV}, else asked "
                        "for, without echo)")
    p.add_argument("--password", default=None, metavar="PW",
                   help="deprecated: visible to every local account (ps); use --password-stdin")

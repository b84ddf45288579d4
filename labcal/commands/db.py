"""`labcal db upgrade` and `labcal db status`: the lab database's schema revision, and bringing it
to this labcal's (`labcal.store.labdb`). Opening a database never migrates it: a command refuses one
behind or ahead in one line, and this is the command that line names."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, out, print_json
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store import labdb
from labcal.store.labdb import lab_database, lab_server
from labcal.store.migrations import HEAD

if TYPE_CHECKING:
    from labcal.store import roles as store_roles
else:
    store_roles = lazy("labcal.store.roles")  # start-up without pydantic


def cmd_db_upgrade(args: argparse.Namespace) -> int:
    where = lab_database(args.db)
    done = labdb.upgrade(where)
    roles = None
    if not isinstance(where, Path):  # a server: who may write what, as this labcal says
        roles = store_roles.set_up(where)
    if args.json:
        print_json({"database": str(where), "found": done.found.revision, "legacy": done.found.legacy,
                    "revision": done.reached, "backup": None if done.backup is None else str(done.backup),
                    "roles": roles})
        return 0
    if done.found.revision is None:
        out.print(f"{where}: created at schema {done.reached}")
    elif done.found.revision == done.reached:
        out.print(f"{where}: already at schema {done.reached}; nothing to do")
    else:
        copy = "" if done.backup is None else f"; the file as it was is kept in {done.backup}"
        out.print(f"{where}: upgraded from schema {done.found} to {done.reached}{copy}")
    if roles is not None:
        out.print(f"{where}: {roles}")
    return 0


def cmd_db_grant_station(args: argparse.Namespace) -> int:
    """`labcal db grant-station` and `labcal db grant-server`."""
    admin = lab_server(args.db)
    if admin is None:
        raise LabcalError(f"labcal db {args.db_command} is for a PostgreSQL lab database (--db "
                          "postgresql://ADMIN@HOST/DB); a SQLite lab database is one machine, one trust "
                          "domain: it has no roles")
    if args.password_stdin and args.password_file:
        raise LabcalError("give --password-stdin or --password-file, not both")
    password = None
    if args.password_stdin:
        password = sys.stdin.readline().rstrip("\r\n")
        if not password:
            raise LabcalError("--password-stdin: no password on the first line of the standard input")
    grant = store_roles.grant_server if args.db_command == "grant-server" else store_roles.grant_station
    done = grant(admin, args.name, password, Path(args.password_file) if args.password_file else None)
    if args.json:
        print_json({"station": done.station, "role": done.role, "url": done.url,
                    "password_file": None if done.password_file is None else str(done.password_file),
                    "password_set": done.password_set})
        return 0
    who = "the bench" if args.db_command == "grant-station" else "the server"
    how = (f"its password is in {done.password_file} (readable by you only): give it to {who} as its "
           "PGPASSFILE" if done.password_file is not None else
           "its password is the one given" if done.password_set else
           "it has no password: the server's pg_hba.conf must authenticate it (cert, peer, or trust)")
    may = ("may append this station's runs, points and events and read the lab's record"
           if args.db_command == "grant-station" else "reads the lab database and alone writes approvals")
    out.print(f"{done.station!r}: role {done.role} {may}; {how}. {who.capitalize()} sets LABCAL_DB to:")
    out.print(done.url, soft_wrap=True)  # one line whatever the terminal's width: it is copied as is
    return 0


def cmd_db_status(args: argparse.Namespace) -> int:
    where = lab_database(args.db)
    found = labdb.status(where)
    state = ("current" if found.revision == HEAD else "empty" if found.revision is None
             else "ahead" if found.ahead else "behind")
    if args.json:
        print_json({"database": str(where), "revision": found.revision, "legacy": found.legacy,
                    "head": HEAD, "state": state})
        return 0
    advice = {"current": "", "empty": " (created at the first use)", "behind": "; run: labcal db upgrade",
              "ahead": "; upgrade labcal"}[state]
    out.print(f"{where}: schema {found}, this labcal's is {HEAD}: {state}{advice}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("db", help=summary("db"))
    actions = p.add_subparsers(dest="db_command", required=True, metavar="ACTION")
    up = actions.add_parser("upgrade", help="bring the lab database to this labcal's schema (a SQLite file "
                                            "is copied beside itself first; all steps or none)")
    add_db_option(up)
    up.add_argument("--json", action="store_true")
    up.set_defaults(func=cmd_db_upgrade)
    grants = {"grant-station": ("a role for a bench: it appends only its station's runs", "NAME",
                                "the station's name (its LABCAL_STATION)"),
              "grant-server": ("a role for the lab server: it reads everything and alone writes approvals",
                               "NAME", "a name for the server's role (labcal_server_NAME)")}
    for action, (what, metavar, name_help) in grants.items():
        g = actions.add_parser(action, help=f"(PostgreSQL, as the administrator) {what}; prints its "
                                            "LABCAL_DB URL last")
        g.add_argument("name", metavar=metavar, help=name_help)
        g.add_argument("--password-file", metavar="FILE", help="make a password and write it to FILE (new, "
                                                               "owner-only, libpq's PGPASSFILE form)")
        g.add_argument("--password-stdin", action="store_true",
                       help="read the role's password from the first line of the standard input")
        add_db_option(g)
        g.add_argument("--json", action="store_true")
        g.set_defaults(func=cmd_db_grant_station)
    st = actions.add_parser("status", help="the lab database's schema revision and this labcal's")
    add_db_option(st)
    st.add_argument("--json", action="store_true")
    st.set_defaults(func=cmd_db_status)

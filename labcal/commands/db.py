"""`labcal db upgrade` and `labcal db status`: the lab database's schema revision, and bringing it
to this labcal's (`labcal.run.labdb`). Opening a database never migrates it: a command refuses one
behind or ahead in one line, and this is the command that line names."""

from __future__ import annotations

import argparse

from labcal.commands import summary
from labcal.commands.common import add_db_option, out, print_json


def cmd_db_upgrade(args: argparse.Namespace) -> int:
    from labcal.run import labdb
    from labcal.run.labdb import lab_database

    where = lab_database(args.db)
    done = labdb.upgrade(where)
    if args.json:
        print_json({"database": str(where), "found": done.found.revision, "legacy": done.found.legacy,
                    "revision": done.reached, "backup": None if done.backup is None else str(done.backup)})
        return 0
    if done.found.revision is None:
        out.print(f"{where}: created at schema {done.reached}")
    elif done.found.revision == done.reached:
        out.print(f"{where}: already at schema {done.reached}; nothing to do")
    else:
        copy = "" if done.backup is None else f"; the file as it was is kept in {done.backup}"
        out.print(f"{where}: upgraded from schema {done.found} to {done.reached}{copy}")
    return 0


def cmd_db_status(args: argparse.Namespace) -> int:
    from labcal.run import labdb
    from labcal.run.labdb import lab_database
    from labcal.run.migrations import HEAD

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
    st = actions.add_parser("status", help="the lab database's schema revision and this labcal's")
    add_db_option(st)
    st.add_argument("--json", action="store_true")
    st.set_defaults(func=cmd_db_status)

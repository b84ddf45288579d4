"""`labcal sync`: send this station's journal to the lab's PostgreSQL database now (what a run sends
as it goes, and catches up after an outage by itself; `labcal.store.sync`)."""

from __future__ import annotations

import argparse

from labcal.commands import summary
from labcal.commands.common import add_db_option, out, print_json
from labcal.config.lab import ServerDatabase
from labcal.store import labdb
from labcal.store.journal import db_path
from labcal.store.labdb import lab_database
from labcal.store.sync import Sender, is_outage


def cmd_sync(args: argparse.Namespace) -> int:
    where = lab_database(args.db)
    nothing = {"database": str(where), "journal": str(where), "sent": {}, "new": {}, "received": {},
               "refused": {}}
    if not isinstance(where, ServerDatabase):
        return said(args, nothing, f"{where}: the lab database is this SQLite file itself; nothing to send")
    journal = db_path(args.db)
    labdb.open_server(where).dispose()  # reachable, at this labcal's schema (created if empty)
    if not journal.exists():
        return said(args, {**nothing, "journal": str(journal)},
                    f"{journal}: no journal on this station yet (it is $LABCAL_JOURNAL, else the lab file's "
                    "journal); nothing to send")
    sender = Sender(journal, where)
    try:
        sent = sender.push()
        received = sender.pull()  # every bench's records, for when the lab cannot be reached
    except Exception as exc:
        if is_outage(exc) and not isinstance(exc, labdb.Unreachable):
            raise labdb.unreachable(where, exc) from None
        raise
    finally:
        sender.close()
    if args.json:
        print_json({"database": str(where), "journal": str(journal), "sent": sent.offered,
                    "new": sent.stored, "received": received, "refused": sent.refused})
        return 0
    if sent.total == 0 and not sent.refused:
        out.print(f"{where}: nothing to send; everything in {journal} is there")
    elif sent.total:
        new = ", ".join(f"{sent.stored[n]} {n}" for n in sent.stored)
        out.print(f"{where}: sent {sent} from {journal} ({new} new there)")
    if sent.refused:
        what = ", ".join(f"{n} {t}" for t, n in sent.refused.items())
        out.print(f"{where}: refused this bench's role {what} ({sent.why}): an approver is the lab's "
                  "administrator's to register, an approved "
                  f"certificate the lab server's to write; they stay in {journal}")
    if any(received.values()):
        out.print(f"{where}: received " + ", ".join(f"{n} {t}" for t, n in received.items() if n)
                  + f" of other benches into {journal}")
    return 0


def said(args: argparse.Namespace, doc: dict, line: str) -> int:
    """Nothing to send: the line, or with --json the same document as a sync that sent nothing."""
    if args.json:
        print_json(doc)
    else:
        out.print(line)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sync", help=summary("sync"))
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print what was sent as JSON on stdout")
    p.set_defaults(func=cmd_sync)

"""`labcal serve`: the lab server (`labcal.server`, on the use cases of `labcal.app.lab`)."""

from __future__ import annotations

import argparse
import sys

from labcal.commands import summary
from labcal.commands.common import EXIT_USER_ERROR, bounded, err

LAB_EXTRA = "pip install 'labcal[lab]'"


def cmd_serve(args: argparse.Namespace) -> int:
    try:
        from labcal.server.serving import serve, settings_for
    except ImportError as exc:
        err.print(f"labcal serve needs the lab server's packages ({exc.name} is missing): {LAB_EXTRA}")
        return EXIT_USER_ERROR
    settings = settings_for(args.db, args.key, args.poll)

    def listening(url: str) -> None:
        signing = f"; signing with {settings.key}" if settings.key else ""
        where = settings.lab.shown
        sys.stdout.write(f"labcal lab server on {url} (lab database {where}{signing}); "
                         "Ctrl-C stops it\n")
        sys.stdout.flush()
    serve(settings, args.host, args.port, listening)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help=summary("serve"),
                       description="Serve the lab database over HTTP: pages (sign in with a user of `labcal "
                                   "user add`), a JSON API (Authorization: Bearer TOKEN) and live event "
                                   "streams of the runs. Reads the lab database only; approving signs with "
                                   f"--key. Needs {LAB_EXTRA}.")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only; 0.0.0.0: the lab's "
                        "network)")
    p.add_argument("--port", type=bounded(int, 0, 65535), default=8024,
                   help="port (default 8024; 0: any free port, printed)")
    p.add_argument("--db", default=None, metavar="URL",
                   help="the lab database: a path, sqlite:///PATH or postgresql://USER@HOST:PORT/DB "
                        "(default $LABCAL_DB, else the lab file's)")
    p.add_argument("--key", default=None, metavar="FILE",
                   help="the lab's private key (PEM) for approvals (default: the lab file's server_key), "
                        "registered with `labcal certificate approvers add \"lab server\" --role \"lab "
                        "server\"` (signs for every approver) or under one approver's name (signs for them "
                        "only)")
    p.add_argument("--poll", type=bounded(float, 0.05, 60), default=0.5, metavar="S",
                   help="how often the live streams look for new readings (seconds, default 0.5)")
    p.set_defaults(func=cmd_serve)

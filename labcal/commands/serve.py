"""`labcal serve`: the lab server (`labcal.server`, on the use cases of `labcal.app.lab`)."""

from __future__ import annotations

import argparse
import sys

from labcal.commands import summary
from labcal.commands.common import EXIT_USER_ERROR, bounded, err, warn_if_secret_in

LAB_EXTRA = "pip install 'labcal[lab]'"


def cmd_serve(args: argparse.Namespace) -> int:
    try:
        from labcal.server.serving import Transport, exposure_warning, serve, settings_for
    except ImportError as exc:
        err.print(f"labcal serve needs the lab server's packages ({exc.name} is missing): {LAB_EXTRA}")
        return EXIT_USER_ERROR
    warn_if_secret_in(args.db)
    transport = Transport(args.certfile, args.keyfile, args.forwarded_allow_ips)
    settings = settings_for(args.db, args.key, args.poll, tuple(args.server_name), args.host,
                            args.session_idle * 60.0, args.silent_after)

    def listening(url: str) -> None:
        warning = exposure_warning(args.host, transport)  # once listening (not before a refusal)
        if warning:
            sys.stderr.write(warning + "\n")
        signing = f"; signing with {settings.key}" if settings.key else ""
        where = settings.lab.shown
        sys.stdout.write(f"labcal lab server on {url} (lab database {where}{signing}); "
                         "Ctrl-C stops it\n")
        sys.stdout.flush()
    serve(settings, args.host, args.port, listening, transport)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help=summary("serve"),
                       description="Serve the lab database over HTTP: pages (sign in with a user of `labcal "
                                   "user add`), a JSON API (Authorization: Bearer TOKEN) and live event "
                                   "streams of the runs. Reads the lab database and writes only its audit "
                                   f"trail; approving signs with --key. Needs {LAB_EXTRA}. Before serving "
                                   "the lab's network: docs/user/deploying-the-lab-server.md.")
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
    p.add_argument("--server-name", action="append", default=[], metavar="NAME",
                   help="a name the server is reached by (its DNS name); requests naming another Host are "
                        "refused (repeatable; the --host address and, for 127.0.0.1 or 0.0.0.0, this "
                        "machine's names are always accepted)")
    p.add_argument("--certfile", default=None, metavar="PEM",
                   help="serve HTTPS with this certificate (chain), with --keyfile")
    p.add_argument("--keyfile", default=None, metavar="PEM", help="the certificate's private key")
    p.add_argument("--forwarded-allow-ips", default=None, metavar="IPS",
                   help="behind a TLS reverse proxy: its addresses (comma-separated); their "
                        "X-Forwarded-Proto and X-Forwarded-For are believed (secure cookies, HSTS, the "
                        "client's address in the audit trail)")
    p.add_argument("--session-idle", type=bounded(float, 1, 720), default=30, metavar="MIN",
                   help="minutes without a request after which a web session ends (default 30, OWASP ASVS "
                        "level 2; sessions end after 12 h in any case)")
    p.add_argument("--poll", type=bounded(float, 0.05, 60), default=0.5, metavar="S",
                   help="how often the live streams look for new readings (seconds, default 0.5)")
    p.add_argument("--silent-after", type=bounded(float, 1, 86400), default=60, metavar="S",
                   help="seconds without a word from a running bench (and never less than five of its "
                        "usual intervals between points) after which the overview shows it as not heard "
                        "from: its process killed, its computer off (default 60)")
    p.set_defaults(func=cmd_serve)

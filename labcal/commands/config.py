"""`labcal config`: which lab file is in force, and what it says."""

from __future__ import annotations

import argparse
import sys

from labcal.commands import summary
from labcal.commands.common import out, print_json
from labcal.config.lab import CONFIG_ENV, load_lab_config


def cmd_path(args: argparse.Namespace) -> int:
    lab = load_lab_config()
    if args.json:
        print_json({"path": None if lab.path is None else str(lab.path),
                    "searched": [str(p) for p in lab.searched], "database": str(lab.database())})
        return 0
    if lab.path is None:
        looked = ", ".join(map(str, lab.searched))
        out.print(f"no lab file; looked for {looked} (set ${CONFIG_ENV} to name one)")
    else:
        sys.stdout.write(f"{lab.path}\n")  # a path for scripts: never wrapped or styled
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    lab = load_lab_config()
    laboratory, certificate = lab.laboratory.model_dump(), lab.certificate.model_dump(mode="json")
    path, database = None if lab.path is None else str(lab.path), str(lab.database())
    urls, source = lab.notify_urls()
    notify = [url.partition("://")[0] + "://…" for url in urls]  # the scheme: the rest may hold a token
    if args.json:
        print_json({"path": path, "database": database, "laboratory": laboratory, "certificate": certificate,
                    "notify": notify, "notify_from": source})
        return 0
    out.print(f"lab file: {path or 'none (defaults)'}")
    out.print(f"database: {database}")
    out.print(f"notify: {', '.join(notify) or 'nobody'} ({source})", markup=False)
    for key, value in laboratory.items():
        out.print(f"laboratory.{key}: {value or 'not stated'}")
    for key, value in certificate.items():
        out.print(f"certificate.{key}: {'none' if value is None else value}")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help=summary("config"),
                       description="The lab file holds the lab database's location, the laboratory's name, "
                                   "address and accreditation, and the certificates' default tolerances and "
                                   "usage envelope. It is $LABCAL_CONFIG, else lab.toml in the user's "
                                   "labcal configuration folder, else labcal/lab.toml in $XDG_CONFIG_DIRS "
                                   "(/etc/xdg).")
    verbs = p.add_subparsers(dest="verb", required=True, metavar="VERB")
    show = verbs.add_parser("show", help="the settings in force (defaults where the file is silent)")
    show.add_argument("--json", action="store_true", help="print as JSON on stdout")
    show.set_defaults(func=cmd_show)
    path = verbs.add_parser("path", help="the lab file in force, or where it was looked for")
    path.add_argument("--json", action="store_true", help="print as JSON on stdout")
    path.set_defaults(func=cmd_path)

"""`labcal export`: rebuild a run folder from the journal, or write a copy of it elsewhere."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from labcal.commands import summary
from labcal.commands.common import add_db_option, err, print_json
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import folders
else:
    folders = lazy("labcal.app.folders")  # SQLAlchemy and scipy: not for --help


def cmd_export(args: argparse.Namespace) -> int:
    result = (folders.export_run(folders.ExportRun(args.run, args.out, args.db)) if args.out
              else folders.rebuild_run_folder(folders.RebuildRunFolder(args.run, args.db)))
    if args.json:
        print_json({"id": result.number, "label": result.label, "uuid": result.run_uuid,
                    "folder": str(result.folder), "status": result.status, "notes": list(result.notes),
                    "copy": bool(args.out)})
        return 0
    for note in result.notes:
        err.print(f"[yellow]note:[/] {note}")
    if args.out:
        err.print(f"run {result.label} ({result.status}): a copy in {result.folder}, from the journal; the "
                  f"run's folder is unchanged (`labcal export {result.folder}` makes this copy the run's "
                  "folder)")
        return 0
    err.print(f"run {result.label} ({result.status}): {result.folder} matches the journal"
              + ("" if result.status == "complete" else f"; `labcal resume {result.folder}` goes on with it"))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help=summary("export"),
                       description="Check a run folder against the journal and rewrite every file that is "
                                   "missing, out of date or edited (an edited one is kept as NAME.edited): "
                                   "plan.toml, readings.csv, fit.json, run.json. Given a run id, recreates "
                                   "the folder of a run whose folder was deleted, where the journal records "
                                   "it. --out DIR writes a copy into DIR and changes neither the run's "
                                   "folder nor the lab database; `labcal export DIR` then makes DIR the "
                                   "run's folder.")
    p.add_argument("run", metavar="RUN", help="a run folder, or a run number (see labcal runs)")
    p.add_argument("--out", metavar="DIR", help="write a copy of the run's folder here (the run's own "
                                                "folder and the lab database are left as they are)")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print a summary as JSON on stdout")
    p.set_defaults(func=cmd_export)

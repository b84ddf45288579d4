"""`labcal export`: rewrite a run folder's files from the journal (or make the folder anew)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from labcal.commands.common import add_db_option, err, print_json
from labcal.errors import LabcalError


def cmd_export(args: argparse.Namespace) -> int:
    from labcal.run import exports
    from labcal.run.journal import Journal, db_path
    from labcal.run.rundir import RUN, open_run, read_run_json, recorded_folder

    if args.run.isdigit():  # a run id: the folder may be gone; the journal has all of it
        journal = Journal(db_path(args.db))
        try:
            row = journal.run(int(args.run))
            folder = Path(args.out) if args.out else recorded_folder(journal, row)
        except BaseException:
            journal.close()
            raise
    else:
        _, journal, row = open_run(Path(args.run))
        folder = Path(args.out or args.run)
    with journal:
        if folder.exists() and not folder.is_dir():
            raise LabcalError(f"{folder}: exists and is not a folder; give another --out")
        if (folder / RUN).exists():  # a folder that shows another run is never written over
            from labcal.run.rundir import check_identity

            check_identity(folder, read_run_json(folder), row)
        elif folder.exists() and any(folder.iterdir()):
            raise LabcalError(f"{folder}: folder is not empty and is no run's; give an empty or new --out")
        created = not (folder / RUN).exists()  # else this run's own folder, only recorded anew
        try:
            folder.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise LabcalError(f"{folder}: cannot create the run folder ({exc.strerror})") from None
        notes, _ = exports.sync(journal, row, folder)
        where = os.path.abspath(folder)  # recorded absolute: found from any folder
        if where != row.run_dir:
            journal.set_run_dir(row.id, where)
            journal.event(row.id, "export", f"run folder recreated in {where}" if created
                          else f"run folder recorded as {where} (was {row.run_dir})")
    if args.json:
        print_json({"run_id": row.id, "run_uuid": row.uuid, "folder": str(folder), "status": row.status,
                    "notes": notes})
        return 0
    for note in notes:
        err.print(f"[yellow]note:[/] {note}")
    err.print(f"run {row.id} ({row.status}): {folder} matches the journal"
              + ("" if row.status == "complete" else f"; `labcal resume {folder}` goes on with it"))
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="rewrite a run folder's files from the journal",
                       description="Check a run folder against the journal and rewrite every file that is "
                                   "missing, out of date or edited (an edited one is kept as NAME.edited): "
                                   "plan.toml, readings.csv, fit.json, run.json. Given a run id, recreates "
                                   "the folder of a run whose folder was deleted (--out: elsewhere).")
    p.add_argument("run", metavar="RUN", help="a run folder, or a run id in the lab database")
    p.add_argument("--out", metavar="DIR", help="write the run's folder here (default: where the run is)")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print a summary as JSON on stdout")
    p.set_defaults(func=cmd_export)

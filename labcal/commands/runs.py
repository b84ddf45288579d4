"""`labcal runs` and `labcal log RUN`: the lab's runs, and what happened in one of them, from the
journal (before these, only `sqlite3` showed the prompts, answers, faults, pauses and resumes)."""

from __future__ import annotations

import argparse
from pathlib import Path

from labcal.commands.common import add_db_option, out, print_json
from labcal.errors import LabcalError

STATUSES = ("running", "complete", "stopped", "interrupted", "failed")


def _opened(db: str | None):
    """The lab's journal, or None when there is no database yet (listing it must not create one)."""
    from labcal.run.journal import Journal, db_path

    path = db_path(db)
    if not path.exists():
        return path, None
    if not path.is_file():
        raise LabcalError(f"{path}: not a database file; --db or $LABCAL_DB names the lab's database")
    return path, Journal(path)


def _when(utc: str | None) -> str:
    return "" if not utc else utc.replace("T", " ")[:19]


def _seen_status(db: Path, run) -> str:
    """The journal's status, except that a "running" run whose lock nobody holds was interrupted:
    its process ended without closing it (a kill, a power cut). `labcal resume` goes on with it."""
    from labcal.run.lock import held_by

    if run.status == "running" and held_by(db, run.id) is None:
        return "interrupted"
    return run.status


def cmd_runs(args: argparse.Namespace) -> int:
    path, journal = _opened(args.db)
    runs, seen = [], {}
    wanted = tuple(args.status or ())
    if journal is not None:
        with journal:
            # an interrupted run may still say "running" in the journal: ask for both, then sort out
            asked = wanted + (("running",) if "interrupted" in wanted else ())
            runs = journal.runs(args.serial, asked)
        seen = {r.id: _seen_status(path, r) for r in runs}
        runs = [r for r in runs if not wanted or seen[r.id] in wanted]
    if args.json:
        print_json({"database": str(path), "runs": [{
            "id": r.id, "instrument": r.instrument_serial, "plan": r.plan_name, "status": seen[r.id],
            "reason": r.reason, "started_utc": r.started_utc, "ended_utc": r.ended_utc,
            "points": r.points_ok, "points_failed": r.points_failed, "operator": r.operator,
            "run_dir": r.run_dir} for r in runs]})
        return 0
    if not runs:
        where = "" if journal is not None else " (it does not exist yet)"
        matching = " matching" if args.serial or args.status else ""
        out.print(f"no runs{matching} in {path}{where}", markup=False, soft_wrap=True)  # a path is not broken
        return 0
    from rich.table import Table

    table = Table(title=f"Runs in {path}", box=None, pad_edge=False)  # 80 columns
    for col in ("id", "instrument", "plan", "status", "started UTC", "points", "operator"):
        table.add_column(col, justify="right" if col in ("id", "points") else "left", min_width=len(col),
                         no_wrap=col in ("plan", "status", "started UTC"))
    for r in runs:
        failed = f" (+{r.points_failed} failed)" if r.points_failed else ""
        table.add_row(str(r.id), r.instrument_serial or "—", r.plan_name, seen[r.id],
                      _when(r.started_utc)[:16],
                      f"{r.points_ok}{failed}", r.operator or "—")
    table.caption = "labcal log ID: a run's events; --json: its run directory too"
    out.print(table)
    return 0


def _run_of(args: argparse.Namespace) -> tuple[str | None, int]:
    """RUN as a run id in the lab's database or as a run directory (whose run.json names both)."""
    if args.run.isdigit():
        return args.db, int(args.run)
    from labcal.run.rundir import read_run_json

    if not Path(args.run).is_dir():
        raise LabcalError(f"{args.run}: neither a run id (see labcal runs) nor a run directory")
    info = read_run_json(Path(args.run))
    try:
        return str(info["journal"]), int(info["run_id"])
    except (KeyError, TypeError, ValueError):
        raise LabcalError(f"{args.run}: run.json does not name its journal and run id") from None


def cmd_log(args: argparse.Namespace) -> int:
    from labcal.commands.console import format_duration

    db, run_id = _run_of(args)
    path, journal = _opened(db)
    if journal is None:
        raise LabcalError(f"{path}: no lab database here; --db or $LABCAL_DB names the lab's database")
    with journal:
        run = journal.run(run_id)
        events = journal.events(run_id)
        done = len(journal.points(run_id, status="ok"))
    if args.json:
        print_json({"run_id": run_id, "status": run.status, "reason": run.reason, "plan": run.plan_name,
                    "instrument": run.instrument_serial, "operator": run.operator, "run_dir": run.run_dir,
                    "started_utc": run.started_utc, "ended_utc": run.ended_utc, "points": done,
                    "events": events})
        return 0
    ended = f", ended {_when(run.ended_utc)}" if run.ended_utc else ""
    reason = f" ({run.reason})" if run.reason else ""
    out.print(f"run {run_id}: {run.plan_name}, instrument {run.instrument_serial or '—'}, operator "
              f"{run.operator or '—'}; {run.status}{reason}; {done} point(s); started "
              f"{_when(run.started_utc)} UTC{ended}; {run.run_dir}", markup=False)
    if not events:
        out.print("no events journaled", markup=False)
    for e in events:
        rig = "" if e["station_time"] is None else f"  rig {format_duration(e['station_time'])}"
        out.print(f"{_when(e['utc'])}{rig}  {e['kind']}: {_message(e)}", markup=False)
    return 0


def _message(event: dict) -> str:
    """An event's message with what its data adds for a reader: why the tables were stopped, why
    a prompt was declined (journals of every labcal carry both in the data, not in the words)."""
    data = event["data"] if isinstance(event["data"], dict) else {}
    why = data.get("cause") if event["kind"] == "stop" else data.get("reason") if event["kind"] == "answer" \
        else None
    if not why:
        return event["message"]
    return f"{event['message']} ({'after ' if event['kind'] == 'stop' else ''}{why})"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("runs", help="list the lab's runs (id, instrument, plan, status, start, points)",
                       description="Every run journaled in the lab's database, oldest first: id, "
                                   "instrument, plan, status, start, points committed, operator.")
    p.add_argument("--serial", metavar="SERIAL", help="only this instrument's runs")
    p.add_argument("--status", choices=STATUSES, action="append",
                   help="only runs in this status (repeatable)")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_runs)

    p = sub.add_parser("log", help="a run's journaled events: prompts, answers, retries, faults, pauses",
                       description="The events journaled during a run, in order, with their UTC time and "
                                   "the rig's clock: prompts and answers, retries, faults, pauses, resumes.")
    p.add_argument("run", metavar="RUN", help="run id (see labcal runs) or run directory")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_log)

"""`labcal runs` and `labcal log RUN`: the lab's runs, and what happened in one of them, from the
journal (before these, only `sqlite3` showed the prompts, answers, faults, pauses and resumes)."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from rich.table import Table

from labcal.app import STATUSES
from labcal.commands import summary
from labcal.commands.common import add_db_option, err, format_duration, out, print_json
from labcal.lazy import lazy

if TYPE_CHECKING:
    from labcal.app import runs as app_runs
else:
    app_runs = lazy("labcal.app.runs")  # not for --help: SQLAlchemy, scipy, matplotlib


def _when(utc: str | None) -> str:
    return "" if not utc else utc.replace("T", " ")[:19]


def cmd_runs(args: argparse.Namespace) -> int:
    found = app_runs.list_runs(
        app_runs.ListRuns(args.db, args.serial, tuple(args.status or ()), args.attention))
    where, runs = found.database, found.runs
    if found.stale:
        err.print(found.stale, markup=False)
    if args.json:
        print_json({"database": where, "runs": [r.to_json() for r in runs]})
        return 0
    if not runs:
        missing = "" if found.exists else " (it does not exist yet)"
        matching = " matching" if args.serial or args.status or args.attention else ""
        # a path is not broken
        out.print(f"no runs{matching} in {where}{missing}", markup=False, soft_wrap=True)
        return 0
    table = Table(title=f"Runs in {where}", box=None, pad_edge=False)  # 80 columns
    for col in ("id", "serial", "plan", "status", "started UTC", "points", "operator"):
        table.add_column(col, justify="right" if col in ("id", "points") else "left", min_width=len(col),
                         no_wrap=col in ("plan", "status", "started UTC"))
    for r in runs:
        failed = f" (+{r.points_failed} failed)" if r.points_failed else ""
        table.add_row(r.label, r.serial or "—", r.plan, r.status, _when(r.started_utc)[:16],
                      f"{r.points_ok}{failed}", r.operator or "—")
    table.caption = "labcal log ID: a run's events; --json: its station and run directory too"
    out.print(table)
    for r in runs:  # what the approver must know, under the table: a reason is a sentence, not a cell
        for why in r.attention:
            out.print(f"run {r.id}: {why}", markup=False)
    return 0


def cmd_log(args: argparse.Namespace) -> int:
    run = app_runs.read_log(app_runs.ReadLog(args.run, args.db))
    if run.stale:
        err.print(run.stale, markup=False)
    if args.json:
        print_json(run.to_json())
        return 0
    ended = f", ended {_when(run.ended_utc)}" if run.ended_utc else ""
    reason = f" ({run.reason})" if run.reason else ""
    out.print(f"run {run.label}: {run.plan}, instrument {run.serial or '—'}, operator "
              f"{run.operator or '—'}; {run.status}{reason}; {run.points_ok} point(s); started "
              f"{_when(run.started_utc)} UTC{ended}; {run.run_dir}", markup=False)
    if not run.events:
        out.print("no events journaled", markup=False)
    for e in run.events:
        rig = "" if e.station_time is None else f"  rig {format_duration(e.station_time)}"
        out.print(f"{_when(e.utc)}{rig}  {e.kind}: {_message(e)}", markup=False)
    return 0


def _message(event: app_runs.EventRow) -> str:
    """An event's message with what its data adds for a reader: why the tables were stopped, why
    a prompt was declined (journals of every labcal carry both in the data, not in the words)."""
    why = event.values.get("cause") if event.kind == "stop" else \
        event.values.get("reason") if event.kind == "answer" else None
    if not why:
        return event.message
    return f"{event.message} ({'after ' if event.kind == 'stop' else ''}{why})"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("runs", help=summary("runs"),
                       description="Every run in the lab's database, by the lab's run number (the same "
                                   "at every bench and on the lab server's pages): number, instrument "
                                   "serial, plan, status, start, points committed, operator. A bench's run "
                                   "the lab has not seen yet is listed last, by its provisional label.")
    p.add_argument("--serial", metavar="SERIAL", help="only this instrument's runs")
    p.add_argument("--status", choices=STATUSES, action="append",
                   help="only runs in this status (repeatable)")
    p.add_argument("--attention", action="store_true",
                   help="only runs an approver must look at, each reason listed (the approval queue's "
                        "rule): an unmet pre-run checklist item gone past, a reference standard overdue, "
                        "faults during the run, a device correction used, a failed verdict")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_runs)

    p = sub.add_parser("log", help=summary("log"),
                       description="The events journaled during a run, in order, with their UTC time and "
                                   "the rig's clock: prompts and answers, retries, faults, pauses, resumes.")
    p.add_argument("run", metavar="RUN",
                   help="run number (see labcal runs), a run's uuid (its first 8 digits will do) or "
                        "run directory")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_log)

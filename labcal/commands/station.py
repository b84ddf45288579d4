"""`labcal station list|check`: the example stations, and whether a station's devices answer."""

from __future__ import annotations

import argparse
from contextlib import ExitStack
from datetime import datetime
from pathlib import Path

from rich.markup import escape
from rich.table import Table

from labcal.bench.checklist import run_checklist, unmet
from labcal.bench.setup import bench_for_check
from labcal.commands import summary
from labcal.commands.common import (
    TIME_SCALE,
    TIME_SCALE_HELP,
    add_db_option,
    add_power_on_options,
    err,
    out,
    print_json,
)
from labcal.commands.console import power_on_given, print_checklist
from labcal.config.plans import load_plan
from labcal.config.station import load_station, shipped_stations
from labcal.config.uncertainty import overdue_standards
from labcal.errors import LabcalError
from labcal.store.journal import db_path
from labcal.store.labdb import lab_server


def cmd_list(args: argparse.Namespace) -> int:
    stations = {name: load_station(name)[0] for name in shipped_stations()}
    if args.json:
        print_json({"stations": [{"name": n, "description": s.description, "pitch": s.pitch.driver,
                                  "roll": s.roll.driver, "dmm": s.dmm.driver} for n, s in stations.items()]})
        return 0
    table = Table(title="Example stations (labcal station check NAME, labcal sim serve NAME)")
    for col in ("name", "pitch", "roll", "description"):
        table.add_column(col)
    for name, s in stations.items():
        table.add_row(name, s.pitch.driver, s.roll.driver, s.description)
    out.print(table)
    return 0


def _row(report: dict) -> tuple[str, str, str]:
    if report["device"] == "dmm" and "volts" in report:
        reading = "  ".join(f"{axis} {v:+.6f} V" for axis, v in zip("xyz", report["volts"], strict=True)
                            if v is not None)  # a package's sensors only
        if report.get("temp_c") is not None:
            reading += f"  {report['temp_c']:.2f} °C"
        return report.get("identity", ""), "scan ok", reading
    if "position_deg" in report:
        return report["identity"], report["status"], f"{report['position_deg']:.5f}°"
    return report.get("identity", ""), "", ""


def cmd_check(args: argparse.Namespace) -> int:
    config, _ = load_station(args.station)
    now = datetime.now().astimezone()
    power = power_on_given(args, now)  # a mistake here is one line before any device is opened
    plan, _ = load_plan(args.plan)
    today = now.date()
    overdue = [(t, line) for t in config.traceability for line in overdue_standards([t], today, today=True)]
    with ExitStack() as stack:
        bench = bench_for_check(config, stack, emulate=args.emulate, time_scale=args.time_scale)
        reports = bench.check(reset_alarms=args.reset_alarms)
        items = run_checklist(config, bench, None, db=db_path(args.db), run_folder=Path(args.out or "runs"),
                              points=plan.n_points, samples=config.sequencer.settle.samples, power=power,
                              now=now, unsaid="warning", server=lab_server(args.db))
    failed = [r for r in reports if r["problem"]]
    if args.json:
        print_json({"station": config.description or args.station, "ok": not failed and not unmet(items),
                    "devices": reports, "checklist": [i.to_json() for i in items],
                    "overdue_standards": [{"equipment": t.equipment, "identity": t.identity,
                                           "certificate": t.certificate, "due": t.due.isoformat(),
                                           "message": line} for t, line in overdue]})
    else:
        table = Table(title=f"Station {config.description or args.station}")
        for col in ("device", "identity", "status", "reading"):
            table.add_column(col)
        for report in reports:
            table.add_row(report["device"], *_row(report))
        out.print(table)
        for report in failed:
            err.print(f"[bold red]problem:[/] {report['problem']}")
        print_checklist(err, items)
    for _, line in overdue:  # a warning, not a failure: the devices answer; a certificate will say it too
        err.print(f"[bold yellow]warning:[/] {escape(line)}")
    if failed:
        raise LabcalError(f"{len(failed)} of {len(reports)} devices failed the check "
                          f"({', '.join(r['device'] for r in failed)}); see the lines above")
    if unmet(items):
        raise LabcalError(f"pre-run checklist: {', '.join(i.name for i in unmet(items))} not met; see the "
                          "lines above (a run would be refused)")
    if not args.json:
        err.print("every device answers; nothing was moved")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("station", help=summary("station"),
                       description="Station files say which driver runs each table and the DMM, on which "
                                   "port, with which settings (see `labcal station list`).")
    station_sub = p.add_subparsers(dest="station_command", required=True, metavar="SUBCOMMAND")
    lst = station_sub.add_parser("list", help="the example stations that ship with labcal",
                                 description="The example station files that ship with labcal.")
    lst.add_argument("--json", action="store_true", help="print the list as JSON on stdout")
    lst.set_defaults(func=cmd_list)
    chk = station_sub.add_parser(
        "check", help="identify every device, read status, position and one DMM scan; move nothing",
        description="Talk to every device of a station: identify it, read its status and position, take "
                    "one DMM scan, and say plainly what does not answer (exit code 2). Nothing moves.")
    chk.add_argument("station", metavar="STATION", help="station file (.toml) or example name")
    chk.add_argument("--emulate", action="store_true", help="start the station's emulators for the check")
    chk.add_argument("--time-scale", type=TIME_SCALE, help=TIME_SCALE_HELP)
    chk.add_argument("--reset-alarms", action="store_true",
                     help="reset a table drive's alarm (Oriental Motor AZ) once its cause is cleared, "
                          "and release its STOP input if a stop left it on")
    chk.add_argument("--plan", default="four-mount-64",
                     help="the plan a run would follow, for the free-disk estimate (default %(default)s)")
    chk.add_argument("--out", metavar="DIR", help="where the run's folder would go (default runs/)")
    add_power_on_options(chk)
    add_db_option(chk)
    chk.add_argument("--json", action="store_true", help="print the reports as JSON on stdout")
    chk.set_defaults(func=cmd_check)

"""`labcal plan list|show`."""

from __future__ import annotations

import argparse

from rich.table import Table

from labcal.commands.common import out, print_json
from labcal.plan import load_plan, shipped_plans


def cmd_list(args: argparse.Namespace) -> int:
    plans = {name: load_plan(name)[0] for name in shipped_plans()}
    if args.json:
        print_json({"plans": [{"name": n, "description": p.description, "mounts": len(p.mounts),
                               "points": p.n_points} for n, p in plans.items()]})
        return 0
    table = Table(title="Shipped plans")
    for col in ("name", "mounts", "points", "description"):
        table.add_column(col)
    for name, plan in plans.items():
        table.add_row(name, str(len(plan.mounts)), str(plan.n_points), plan.description)
    out.print(table)
    return 0


def cmd_show(args: argparse.Namespace) -> int:
    plan, _ = load_plan(args.plan)
    if args.json:
        print_json(plan.model_dump())
        return 0
    out.print(f"[bold]{plan.name}[/] — {plan.description}")
    out.print(f"{plan.replicates} replicate(s) × {len(plan.mounts)} mount(s) × "
              f"{len(plan.points)} points = {plan.n_points} points")
    for i, mount in enumerate(plan.mount_list, 1):
        out.print(f"  mount {i}: {mount.describe()} ({mount})")
    table = Table(title="Points")
    for col in ("#", "pitch (°)", "roll (°)"):
        table.add_column(col, justify="right")
    for i, (p, r) in enumerate(plan.points, 1):
        table.add_row(str(i), f"{p:g}", f"{r:g}")
    out.print(table)
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    plan = sub.add_parser("plan", help="list, show and design calibration plans",
                          description="Calibration plans shipped with labcal or in your own files.")
    actions = plan.add_subparsers(dest="plan_command", required=True, metavar="ACTION")
    p = actions.add_parser("list", help="list the shipped plans")
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_list)
    p = actions.add_parser("show", help="show one plan's mounts and points")
    p.add_argument("plan", help="plan name or .toml file")
    p.add_argument("--json", action="store_true", help="print as JSON on stdout")
    p.set_defaults(func=cmd_show)

"""The `labcal` command line. User errors print one line and exit 2; never a traceback."""

from __future__ import annotations

import argparse
import json
import sys

from rich.console import Console
from rich.table import Table

from labcal import __version__
from labcal.errors import LabcalError
from labcal.files import load_model
from labcal.kinematics import MISALIGNMENT_NAMES, IndexWobble, Misalignment
from labcal.operator import AutoOperator, ConsoleOperator, OperatorDeclined
from labcal.plan import load_plan, shipped_plans
from labcal.readings import read_readings, write_readings
from labcal.run import calibrate, json_safe, new_run_dir, points_on_disk
from labcal.sequencer import SequencerSettings

EXIT_USER_ERROR = 2
EXIT_STOPPED = 1
EXIT_INTERRUPTED = 130

out = Console(highlight=False)
err = Console(stderr=True, highlight=False, soft_wrap=True)  # prose: the terminal wraps it


def print_json(doc: dict) -> None:
    sys.stdout.write(json.dumps(json_safe(doc), indent=2) + "\n")


# --- plan ----------------------------------------------------------------------------------
def cmd_plan_list(args: argparse.Namespace) -> int:
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


def cmd_plan_show(args: argparse.Namespace) -> int:
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


# --- fit -----------------------------------------------------------------------------------
def cmd_fit(args: argparse.Namespace) -> int:
    from labcal.console import coefficient_table
    from labcal.fit import fit_linear

    fit = fit_linear(read_readings(args.readings))
    if args.json:
        print_json(fit.to_json())
    else:
        out.print(coefficient_table(fit))
    return 0


# --- simulate ------------------------------------------------------------------------------
def parse_misalign(text: str) -> Misalignment:
    angles: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        name, sep, value = part.partition("=")
        name = name.strip()
        if not sep or name not in MISALIGNMENT_NAMES:
            raise LabcalError(f"--misalign: {part!r} is not NAME=DEGREES with NAME one of "
                              f"{', '.join(MISALIGNMENT_NAMES)}")
        try:
            angles[name] = float(value)
        except ValueError:
            raise LabcalError(f"--misalign: {value.strip()!r} for {name} is not a number") from None
        if not abs(angles[name]) <= 5:
            raise LabcalError(f"--misalign: {name}={value.strip()}° is not a small misalignment (|x| ≤ 5°)")
    return Misalignment.from_degrees(**angles)


def cmd_simulate(args: argparse.Namespace) -> int:
    from labcal.sim.direct import simulate_readings
    from labcal.sim.instrument import InstrumentTruth

    plan, _ = load_plan(args.plan)
    truth = load_model(args.truth, InstrumentTruth, "truth") if args.truth else InstrumentTruth()
    if args.noise < 0:
        raise LabcalError("--noise must be ≥ 0 (V rms)")
    readings = simulate_readings(
        plan, truth, parse_misalign(args.misalign),
        IndexWobble(args.index_error, args.wobble, args.seed), args.noise, args.seed)
    try:
        write_readings(args.out, readings)
    except OSError as exc:
        raise LabcalError(f"{args.out}: cannot write readings ({exc.strerror})") from None
    err.print(f"{len(readings)} readings written to {args.out}")
    return 0


# --- run -----------------------------------------------------------------------------------
def cmd_run(args: argparse.Namespace) -> int:
    from labcal.console import ProgressDisplay, coefficient_table, format_duration
    from labcal.sim.rig import RigConfig, SimRig, load_rig_config

    if not args.sim:
        raise LabcalError("no station given: use --sim for a dry run on the simulated rig "
                          "(hardware stations arrive with the drivers)")
    plan, plan_text = load_plan(args.plan)
    settings = SequencerSettings(settle_s=args.settle, samples=args.samples)
    config = load_rig_config(args.rig) if args.rig else RigConfig()
    rig = SimRig(config, seed=args.seed)
    run_dir = new_run_dir(args.out, plan)
    operator = AutoOperator(err) if args.yes else ConsoleOperator(err)
    truth = {"coefficients": rig.instrument.X.tolist(),
             "misalignment_deg": rig.misalignment.degrees(), "seed": rig.seed}
    err.print(f"Run directory: {run_dir}")
    display = ProgressDisplay(err, plan.n_points)
    try:
        with display:
            result = calibrate(plan, plan_text, rig.station(), operator, settings, run_dir,
                               display, metadata={"simulated_truth": truth})
    except KeyboardInterrupt:
        kept = points_on_disk(run_dir)
        err.print(f"[bold red]interrupted[/]: tables stopped; {kept} reading(s) kept in {run_dir}")
        return EXIT_INTERRUPTED
    except OperatorDeclined as exc:
        kept = points_on_disk(run_dir)
        err.print(f"[bold yellow]stopped[/]: {exc}; {kept} reading(s) kept in {run_dir}")
        return EXIT_STOPPED
    summary = {
        "run_dir": str(result.directory), "points": result.outcome.points_recorded,
        "simulated_rig_time_s": result.outcome.station_time_s, "wall_time_s": result.wall_s,
        "fit": result.fit.to_json(),
    }
    if args.json:
        print_json(summary)
        return 0
    out.print(coefficient_table(result.fit))
    out.print(f"{result.outcome.points_recorded} points in {result.wall_s:.2f} s of wall time; "
              f"a real rig would need {format_duration(result.outcome.station_time_s)} "
              f"(including {format_duration(rig.config.remount_s)} per remount).")
    out.print(f"Files: {run_dir}/readings.csv, fit.json, plan.toml, run.json")
    return 0


# --- parser --------------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    fmt = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(
        prog="labcal", formatter_class=fmt,
        description="Calibrate three-axis accelerometer attitude instruments on a two-axis "
                    "rotary calibration device (Soto 2020; Tripp & Tcheng 1999).",
        epilog="examples:\n  labcal run --sim --yes\n  labcal fit runs/*/readings.csv --json\n"
               "  labcal plan show four-mount-64",
    )
    parser.add_argument("--version", action="version", version=f"labcal {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    run = sub.add_parser("run", help="run a calibration (on the simulated rig with --sim)",
                         description="Run a calibration plan: move the tables, prompt for each "
                                     "remount, record every point, fit the coefficients.")
    run.add_argument("--sim", action="store_true", help="dry run on the simulated rig")
    run.add_argument("--plan", default="four-mount-64", help="plan name or .toml file (default %(default)s)")
    run.add_argument("--seed", type=int, default=None, help="simulated rig's random seed")
    run.add_argument("--yes", action="store_true", help="confirm every remount prompt automatically")
    run.add_argument("--out", help="run directory (default runs/<UTC time>-<plan>)")
    run.add_argument("--rig", help="TOML file describing the simulated rig (truth, noise, speeds)")
    run.add_argument("--settle", type=float, default=SequencerSettings().settle_s,
                     help="dwell after in-position, s (default %(default)s)")
    run.add_argument("--samples", type=int, default=SequencerSettings().samples,
                     help="DMM samples averaged per point (default %(default)s)")
    run.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    run.set_defaults(func=cmd_run)

    fit = sub.add_parser("fit", help="fit calibration coefficients to a readings CSV",
                         description="Least-squares fit of V = B + gᵀS on the nominal gravity "
                                     "(Soto eqs. 13–21), with standard errors.")
    fit.add_argument("readings", help="readings CSV (replicate,y_deg,u_deg,pitch_deg,roll_deg,vx,vy,vz)")
    fit.add_argument("--model", choices=["linear"], default="linear", help="instrument model")
    fit.add_argument("--json", action="store_true", help="print the fit as JSON on stdout")
    fit.set_defaults(func=cmd_fit)

    sim = sub.add_parser("simulate", help="write readings straight from a plan and a truth",
                         description="Readings from a plan and a known truth, no sequencer: exact "
                                     "with --noise 0 and no index/wobble errors.")
    sim.add_argument("--plan", default="four-mount-64", help="plan name or .toml file")
    sim.add_argument("--misalign", default="", metavar="a=DEG,b=DEG,...",
                     help="CD misalignments in degrees (names a, b, d, e, f, k)")
    sim.add_argument("--truth", help="TOML with the instrument's B = [..] and S = [[..],[..],[..]] "
                                     "(default ideal: B = 0, S = I)")
    sim.add_argument("--noise", type=float, default=0.0, help="white noise per reading, V rms")
    sim.add_argument("--index-error", type=float, default=0.0, metavar="ARCSEC",
                     help="amplitude of the tables' index errors")
    sim.add_argument("--wobble", type=float, default=0.0, metavar="ARCSEC",
                     help="amplitude of the tables' wobble errors")
    sim.add_argument("--seed", type=int, default=0, help="random seed")
    sim.add_argument("--out", required=True, help="readings CSV to write")
    sim.set_defaults(func=cmd_simulate)

    plan = sub.add_parser("plan", help="list and show calibration plans",
                          description="Calibration plans shipped with labcal or in your own files.")
    plan_sub = plan.add_subparsers(dest="plan_command", required=True, metavar="ACTION")
    plan_list = plan_sub.add_parser("list", help="list the shipped plans")
    plan_list.add_argument("--json", action="store_true", help="print as JSON on stdout")
    plan_list.set_defaults(func=cmd_plan_list)
    plan_show = plan_sub.add_parser("show", help="show one plan's mounts and points")
    plan_show.add_argument("plan", help="plan name or .toml file")
    plan_show.add_argument("--json", action="store_true", help="print as JSON on stdout")
    plan_show.set_defaults(func=cmd_plan_show)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except LabcalError as exc:
        err.print(f"[bold red]labcal: error:[/] {exc}", soft_wrap=True)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        err.print("[bold red]interrupted[/]")
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())

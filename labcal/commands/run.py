"""`labcal run`: a calibration on a station (the simulated rig with --sim)."""

from __future__ import annotations

import argparse

from labcal.commands.common import EXIT_INTERRUPTED, EXIT_STOPPED, err, out, print_json
from labcal.errors import LabcalError
from labcal.operator import AutoOperator, ConsoleOperator, OperatorDeclined
from labcal.plan import load_plan
from labcal.run import calibrate, new_run_dir, points_on_disk
from labcal.sequencer import SequencerSettings
from labcal.station import Station


def sim_station(args: argparse.Namespace) -> tuple[Station, dict, float]:
    """The simulated rig, what the run should record about its truth, and its remount time."""
    from labcal.sim.rig import RigConfig, SimRig, load_rig_config

    config = load_rig_config(args.rig) if args.rig else RigConfig()
    rig = SimRig(config, seed=args.seed)
    truth = {"coefficients": rig.instrument.X.tolist(),
             "misalignment_deg": rig.misalignment.degrees(), "seed": rig.seed}
    return rig.station(), {"simulated_truth": truth}, config.remount_s


def cmd_run(args: argparse.Namespace) -> int:
    from labcal.console import ProgressDisplay, coefficient_table, format_duration

    if not args.sim:
        raise LabcalError("no station given: use --sim for a dry run on the simulated rig "
                          "(hardware stations arrive with the drivers)")
    plan, plan_text = load_plan(args.plan)
    settings = SequencerSettings(settle_s=args.settle, samples=args.samples)
    station, metadata, remount_s = sim_station(args)
    run_dir = new_run_dir(args.out, plan)
    operator = AutoOperator(err) if args.yes else ConsoleOperator(err)
    err.print(f"Run directory: {run_dir}")
    try:
        with ProgressDisplay(err, plan.n_points) as display:
            result = calibrate(plan, plan_text, station, operator, settings, run_dir, display, metadata)
    except KeyboardInterrupt:
        err.print(f"[bold red]interrupted[/]: tables stopped; {points_on_disk(run_dir)} reading(s) "
                  f"kept in {run_dir}")
        return EXIT_INTERRUPTED
    except OperatorDeclined as exc:
        err.print(f"[bold yellow]stopped[/]: {exc}; {points_on_disk(run_dir)} reading(s) kept in {run_dir}")
        return EXIT_STOPPED
    if args.json:
        print_json({
            "run_dir": str(result.directory), "points": result.outcome.points_recorded,
            "simulated_rig_time_s": result.outcome.station_time_s, "wall_time_s": result.wall_s,
            "fit": result.fit.to_json(),
        })
        return 0
    out.print(coefficient_table(result.fit))
    out.print(f"{result.outcome.points_recorded} points in {result.wall_s:.2f} s of wall time; "
              f"a real rig would need {format_duration(result.outcome.station_time_s)} "
              f"(including {format_duration(remount_s)} per remount).")
    out.print(f"Files in {run_dir}/: readings.csv, fit.json, plan.toml, run.json")
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    defaults = SequencerSettings()
    p = sub.add_parser("run", help="run a calibration (on the simulated rig with --sim)",
                       description="Run a calibration plan: move the tables, prompt for each "
                                   "remount, record every point, fit the coefficients.")
    p.add_argument("--sim", action="store_true", help="dry run on the simulated rig")
    p.add_argument("--plan", default="four-mount-64", help="plan name or .toml file (default %(default)s)")
    p.add_argument("--seed", type=int, default=None, help="simulated rig's random seed")
    p.add_argument("--yes", action="store_true", help="confirm every remount prompt automatically")
    p.add_argument("--out", help="run directory (default runs/<UTC time>-<plan>)")
    p.add_argument("--rig", help="TOML file describing the simulated rig (truth, noise, speeds)")
    p.add_argument("--settle", type=float, default=defaults.settle_s,
                   help="dwell after in-position, s (default %(default)s)")
    p.add_argument("--samples", type=int, default=defaults.samples,
                   help="DMM samples averaged per point (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.set_defaults(func=cmd_run)

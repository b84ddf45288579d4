"""`labcal run` and `labcal resume`: a calibration on a station: the simulated rig (--sim), or a
station file's devices through the real drivers (--station), on its emulators with --emulate."""

from __future__ import annotations

import argparse
import shlex
from contextlib import contextmanager
from dataclasses import fields
from typing import TYPE_CHECKING, Any

from labcal.commands import console, summary
from labcal.commands.common import (
    EXIT_INTERRUPTED,
    EXIT_STOPPED,
    SEED,
    TIME_SCALE,
    add_db_option,
    add_power_on_options,
    angle_deg,
    bounded,
    bounded_field,
    command_line,
    err,
    format_duration,
    literal,
    out,
    print_json,
)
from labcal.commands.console import ProgressDisplay, before_run, coefficients_with_standard_errors
from labcal.lazy import lazy
from labcal.run.operator import AutoOperator, ConsoleOperator, ScriptedOperator

# The run machinery (sequencer, journal, statistics) is imported where it is used, so that the
# other commands, which import this module to build the parser, do not pay for it at start-up.
if TYPE_CHECKING:
    from labcal.app import calibration
    from labcal.app.calibration import AlreadyComplete, Ended, Estimated, Finished
    from labcal.config.run_metadata import Checklist
else:
    calibration = lazy("labcal.app.calibration")  # start-up without scipy, numpy, pydantic, …


class CommandLine:
    """The terminal as the run's front end (`labcal.app.calibration.FrontEnd`): lines on stderr,
    prompts answered at the keyboard (or by --yes, --answers), a progress bar."""

    def __init__(self, args: argparse.Namespace):
        self.args = args

    def say(self, text: str, markup: bool = True) -> None:
        err.print(text, markup=markup)

    def operator(self):
        return make_operator(self.args)

    def checklist(self, bench, station, points: int, samples: int) -> Checklist:
        return before_run(self.args, bench, station, points, samples)

    def unregistered(self, serial: str) -> bool:
        if self.args.yes or self.args.answers:  # nobody is asked
            return False
        try:
            answer = err.input(f"{serial!r} is not in the lab's instrument register. Calibrate it anyway, "
                               "as an ad-hoc serial? (y/N) ", markup=False)
        except EOFError:
            answer = ""
        return answer.strip().lower() in ("y", "yes")

    @contextmanager
    def display(self, total: int, done: int):
        """The progress bar, which is also the terminal the prompts pause it for."""
        with ProgressDisplay(err, total, done) as display:
            yield display, display


def request(kind: type, args: argparse.Namespace) -> Any:
    """A use case's request from the parsed options of the same names."""
    return kind(**{f.name: (tuple(v) if isinstance(v := getattr(args, f.name), list) else v)
                   for f in fields(kind)})


def make_operator(args: argparse.Namespace):
    if args.answers:
        return ScriptedOperator(err, args.answers)
    return AutoOperator(err) if args.yes else ConsoleOperator(err)


def print_estimate(estimated: Estimated, as_json: bool) -> None:
    plan, est = estimated.plan, estimated.estimate
    doc: dict[str, Any] = {
        "plan": plan.name, "points": plan.n_points, "total_s": est.total_s,
        "estimated_rig_time_s": est.total_s, "moves_s": est.moves_s, "settling_s": est.settling_s,
        "averaging_s": est.averaging_s, "mounting_s": est.mounting_s}
    if est.thermal_s:
        doc["thermal_gate_s"] = est.thermal_s
    if as_json:
        print_json(doc)
        return
    out.print(f"{plan.name}: {plan.n_points} points would take about [bold]{format_duration(est.total_s)}[/] "
              "on this station:")
    for part in ("moves", "settling", "averaging", "mounting"):
        out.print(f"  {part:<10} {format_duration(doc[part + '_s'])}")
    if est.thermal_s:
        out.print(f"  (of which the thermal gate's least wait {format_duration(est.thermal_s)}: its hold at "
                  "every mount)")
    out.print("(mounting includes the operator's remount allowance and the mount checks; nothing moved)")


def run_and_report(args, ended: Ended | Finished) -> int:
    """How the run ended, in words and an exit code; a complete run's fit, files and certificate."""
    if isinstance(ended, calibration.Ended):
        run_dir = ended.run_dir
        if ended.how == "interrupted":
            why = f" ({ended.why})" if ended.why else ""
            err.print(f"[bold red]interrupted[/]{literal(why)}: {literal(ended.tables)}; {ended.points_kept} "
                      f"reading(s) kept in {literal(run_dir)}; continue with: "
                      f"{command_line('labcal', 'resume', run_dir)}")
            return 128 + ended.signum if ended.signum is not None else EXIT_INTERRUPTED  # 130 for Ctrl-C
        err.print(f"[bold yellow]stopped[/]: {literal(ended.why)}{literal(ended.tables)}; "
                  f"{ended.points_kept} reading(s) kept in {literal(run_dir)}; continue with: "
                  f"{command_line('labcal', 'resume', run_dir)}")
        return EXIT_STOPPED
    result, run_dir, est, issued, journal = (ended.result, ended.run_dir, ended.estimate, ended.issued,
                                             ended.journal)
    o = result.outcome
    if args.json:
        print_json({"run_dir": str(result.directory), "run_id": result.run_id, "points": o.points_recorded,
                    "points_failed": o.points_failed, "simulated_rig_time_s": o.station_time_s,
                    "estimated_rig_time_s": est.total_s,
                    "wall_time_s": result.wall_s, "fit": result.fit.to_json(),
                    "device": None if result.device is None else result.device.to_json(),
                    "model_note": result.model_note,
                    "certificate": None if issued is None else str(issued.certificate_path),
                    "verdict": None if issued is None or issued.certificate.conformity is None
                    else "pass" if issued.certificate.conformity.passed else "fail"})
        return 0
    if result.device is not None:
        for table in console.device_tables(result.device.to_json()):
            out.print(table)
    else:
        out.print(coefficients_with_standard_errors(result.fit))
    linear = shlex.join(["labcal", "fit", str(run_dir / "readings.csv"), "--model", "linear"])
    hint = f"; `{linear}` gives Soto's linear fit"
    for note in (result.model_note + (hint if result.device is not None else ""), *result.fit.notes):
        out.print(f"[yellow]note:[/] {literal(note)}")
    failed = f", {o.points_failed} failed (see the journal)" if o.points_failed else ""
    out.print(f"{o.points_recorded} points{failed} in {result.wall_s:.2f} s of wall time; the rig's clock "
              f"says {format_duration(o.station_time_s)} (remount allowances included).")
    files = ", ".join(sorted(p.name for p in run_dir.iterdir() if not p.name.startswith(".")))
    if issued is not None:
        conformity = issued.certificate.conformity
        if conformity is not None:
            verdict = "[green]PASS[/]" if conformity.passed else "[red]FAIL[/]"
            out.print(f"Verdict against the tolerances: [bold]{verdict}[/]")
        else:  # the certificate says only that none was given; how to give one is the technician's
            out.print("[yellow]note:[/] no statement of conformity: give --tolerance-deg (and optionally "
                      "--bias-max-v) or a \\[certificate] section in the station file")
    out.print(f"Files in {literal(run_dir)}/: {literal(files)}; journal {literal(journal)}")
    if issued is not None:
        cert = issued.certificate
        out.print(f"Certificate {literal(cert.number)} issued: {literal(issued.certificate_path)}; "
                  f"stored in {literal(issued.database)} "
                  f"({command_line('labcal', 'history', cert.instrument.serial)})")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    ended = calibration.start_run(request(calibration.StartRun, args), CommandLine(args))
    if isinstance(ended, calibration.Estimated):
        print_estimate(ended, args.json)
        return 0
    return run_and_report(args, ended)


def cmd_resume(args: argparse.Namespace) -> int:
    ended = calibration.resume_run(request(calibration.ResumeRun, args), CommandLine(args))
    if isinstance(ended, calibration.AlreadyComplete):
        return finish_complete(args, ended)
    return run_and_report(args, ended)


def finish_complete(args: argparse.Namespace, done: AlreadyComplete) -> int:
    """A complete run resumed: its exports were checked and repaired; its certificate and report
    issued again if any of them was missing or not the history's (a kill during `labcal report`)."""
    if done.certificate is None:
        message = f"run {done.run_id} is already complete; its files in {done.run_dir} match the journal"
    else:
        message = (f"run {done.run_id} is already complete; certificate {done.certificate_id} and "
                   f"its report written again in {done.run_dir}")
    if args.json:
        print_json({"run_dir": str(done.run_dir), "run_id": done.run_id, "status": "complete",
                    "already_complete": True, "certificate_rewritten": done.certificate})
    else:
        err.print(message)
    return 0


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--yes", action="store_true", help="confirm every remount prompt automatically")
    p.add_argument("--answers", metavar="FILE", help="answer prompts from this file, one answer per line")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--no-report", action="store_true",
                   help="skip the certificate and report at the end (labcal report RUN makes them later)")
    p.add_argument("--tolerance-deg", type=angle_deg(180), metavar="DEG",
                   help="pass/fail tolerance on the attitude U95 over the usage envelope: degrees, or with "
                        "its unit (7.5arcsec)")
    p.add_argument("--usage-pitch", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="usage pitch range for the attitude uncertainty (default -60 60)")
    p.add_argument("--pace", type=TIME_SCALE, metavar="X",
                   help="with --sim: run the simulated rig at X times real time (1: a rig second takes a "
                        "wall second; default: as fast as it can)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help=summary("run"),
                       description="Run a calibration plan: check every angle against the limits, move the "
                                   "tables, prompt for each remount and verify it, settle, record every "
                                   "point in the journal, fit the coefficients. Ctrl-C once pauses after "
                                   "the current point; twice (or SIGTERM, SIGHUP) stops the tables at once. "
                                   "At a remount prompt: y when mounted, n to wait, stop to end the run.")
    p.add_argument("--sim", action="store_true", help="run on the simulated rig")
    p.add_argument("--station", metavar="STATION",
                   help="run on a station's devices through the drivers (station file or example name)")
    p.add_argument("--emulate", action="store_true",
                   help="with --station: start the emulators the station file points at, and run on them")
    p.add_argument("--time-scale", type=TIME_SCALE, metavar="X",
                   help="with --emulate: emulated seconds per wall second (default: the station's)")
    p.add_argument("--plan", default="four-mount-64", help="plan name or .toml file (default %(default)s)")
    p.add_argument("--replicates", type=bounded_field("labcal.analysis.plan:Plan", "replicates"),
                   help="override the plan's number of replicates (1..100)")
    p.add_argument("--order", choices=["shortest", "plan", "sweep", "random"], default="shortest",
                   help="order of the points within a mount (default %(default)s)")
    p.add_argument("--seed", type=SEED, default=None,
                   help="simulated or emulated rig's (and random order's) seed")
    p.add_argument("--out", help="run directory (default runs/<UTC time>-<plan>)")
    p.add_argument("--rig", help="TOML file describing the simulated rig (truth, noise, speeds)")
    p.add_argument("--thermal-gate", nargs=2, type=bounded(float, 0, 86400, lo_open=True),
                   metavar=("RATE", "HOLD"),
                   help="before each mount's points, wait until the instrument's temperature changes by "
                        "less than RATE °C/min over HOLD s (default: the station's [instrument] "
                        "thermal_gate, else none)")
    p.add_argument("--instrument", choices=["three-axis", "two-axis-xy", "two-axis-xz", "single-axis"],
                   help="with --sim: the simulated instrument's sensor package (default: the rig's, "
                        "three-axis)")
    p.add_argument("--samples", type=bounded_field("labcal.config.settings:SettleSettings", "samples"),
                   help="DMM samples per settle window, averaged per point (4..10000)")
    p.add_argument("--fixed-dwell", type=bounded(float, 0, 3600), metavar="S",
                   help="dwell S seconds (0..3600) instead of detecting settling")
    p.add_argument("--max-dwell", type=bounded(float, 0, 3600, lo_open=True), metavar="S",
                   help="give up settling after S seconds (at most 3600)")
    p.add_argument("--settle", choices=["detect", "model"], default=None,
                   help="model: estimate each point from its exponential tail, τ pooled over the run's "
                   "points; a point waits until the run's records rule out a slower tail (the first "
                   "hundred-odd points do) (default: the station file's, else detect)")
    p.add_argument("--on-failure", choices=["skip", "pause", "abort"], default="skip",
                   help="a point that does not settle after one retry (default %(default)s)")
    p.add_argument("--no-mount-check", action="store_true", help="do not verify each mount from gravity")
    p.add_argument("--ambient-temp", type=bounded(float, -20, 60), metavar="C",
                   help="the laboratory's air temperature at the start, °C (the certificate's environmental "
                        "conditions; a station's temperature channel measures the instrument, not the room)")
    p.add_argument("--humidity", type=bounded(float, 0, 100), metavar="PCT",
                   help="the laboratory's relative humidity at the start, %%")
    p.add_argument("--serial", help="the instrument's serial number (kept in the journal)")
    p.add_argument("--operator", help="who runs the calibration (kept in the journal)")
    p.add_argument("--dry-run", action="store_true",
                   help="print the estimated duration of the plan on this station; move nothing")
    add_power_on_options(p)
    _common(p)
    p.set_defaults(func=cmd_run)

    r = sub.add_parser("resume", help=summary("resume"),
                       description="Continue a run after Ctrl-C, a fault, a killed process or a power cut: "
                                   "checks the plan hash and the station, asks to confirm the mount, and "
                                   "goes on at the first point not in the journal.")
    r.add_argument("run", help="the run directory")
    r.add_argument("--station", metavar="STATION",
                   help="go on with this station file instead of the one the run started on: the same bench "
                        "(drivers, addresses, steps, limits, channels) on other links (ports, TCP addresses, "
                        "baud rates, timeouts, retries); anything else is refused, field by field")
    _common(r)
    r.set_defaults(func=cmd_resume)

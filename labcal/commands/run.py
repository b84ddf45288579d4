"""`labcal run` and `labcal resume`: a calibration on a station: the simulated rig (--sim), or a
station file's devices through the real drivers (--station), on its emulators with --emulate."""

from __future__ import annotations

import argparse
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.commands.common import (
    EXIT_INTERRUPTED,
    EXIT_STOPPED,
    SEED,
    TIME_SCALE,
    add_db_option,
    bounded,
    bounded_field,
    err,
    out,
    print_json,
)
from labcal.errors import LabcalError

# The run machinery (sequencer, journal, statistics) is imported where it is used, so that the
# other commands, which import this module to build the parser, do not pay for it at start-up.
if TYPE_CHECKING:
    from labcal.analysis.plan import Plan
    from labcal.bench.setup import StationSetup
    from labcal.config.settings import CertificateSettings, SequencerSettings
    from labcal.config.station import StationFile
    from labcal.run.estimate import Estimate
    from labcal.run.runner import RunResult


def sequencer_settings_for_run(args: argparse.Namespace, setup: StationSetup, speed: float = 20.0,
                               accel: float = 40.0) -> SequencerSettings:
    from labcal.config.files import validate_model
    from labcal.config.settings import SequencerSettings, SettleSettings

    settle = validate_model({**setup.settle.model_dump(), **{
        k: v for k, v in (("samples", args.samples), ("fixed_dwell_s", args.fixed_dwell),
                          ("max_dwell_s", args.max_dwell),
                          ("mode", args.settle)) if v is not None}}, SettleSettings,
        "command line: settle")  # validated: the options and the station file share one range
    return SequencerSettings(settle=settle, order=args.order, seed=args.seed or 0,
                             on_failure=args.on_failure, check_mount=not args.no_mount_check,
                             speed_dps=speed, accel_dps2=accel)


def make_operator(args: argparse.Namespace):
    from labcal.run.operator import AutoOperator, ConsoleOperator, ScriptedOperator

    if args.answers:
        return ScriptedOperator(err, args.answers)
    return AutoOperator(err) if args.yes else ConsoleOperator(err)


def print_estimate(plan: Plan, est: Estimate, as_json: bool) -> None:
    from labcal.commands.console import format_duration

    doc: dict[str, Any] = {
        "plan": plan.name, "points": plan.n_points, "total_s": est.total_s,
        "estimated_rig_time_s": est.total_s, "moves_s": est.moves_s, "settling_s": est.settling_s,
        "averaging_s": est.averaging_s, "mounting_s": est.mounting_s}
    if as_json:
        print_json(doc)
        return
    out.print(f"{plan.name}: {plan.n_points} points would take about [bold]{format_duration(est.total_s)}[/] "
              "on this station:")
    for part in ("moves", "settling", "averaging", "mounting"):
        out.print(f"  {part:<10} {format_duration(doc[part + '_s'])}")
    out.print("(mounting includes the operator's remount allowance and the mount checks; nothing moved)")


def certificate_settings_for_run(args: argparse.Namespace, station: CertificateSettings | None,
                                 source: str) -> CertificateSettings:
    """The lab file's certificate defaults, the station's [certificate] settings over them, and the
    command line's tolerances over both."""
    from labcal.config.lab import certificate_settings

    usage = tuple(args.usage_pitch) if args.usage_pitch else None
    return certificate_settings(station, source).overridden(source, attitude_u95_max_deg=args.tolerance_deg,
                                                         usage_pitch_deg=usage)


def _stop_failure(exc: BaseException) -> str:
    """'; STOP FAILED: …' when the run's last stop did not reach a table (noted on the exception
    that ended the run), else ''."""
    return "".join(f"; {note}" for note in getattr(exc, "__notes__", ()) if note.startswith("STOP FAILED"))


def run_and_report(args, runner, run_dir: Path, plan: Plan, est: Estimate, done: int,
                   certificate=None, journal: Path | None = None) -> int:
    """Run with a progress display; turn the ways a run can end into messages and exit codes; at the
    end of a complete run issue its certificate and report (``certificate``: their settings) into
    the run's journal (``journal``: a resumed run's, which its folder names; else --db's)."""
    from labcal.commands.console import ProgressDisplay, coefficients_with_standard_errors, format_duration
    from labcal.run.events import EventBus
    from labcal.run.interrupts import StopSignal
    from labcal.run.journal import db_path
    from labcal.run.operator import OperatorDeclined
    from labcal.run.rundir import points_on_disk

    journal = journal or db_path(args.db)
    err.print(f"Run directory: {run_dir}")
    try:
        with ProgressDisplay(err, plan.n_points, done) as display:
            events = EventBus()  # the journal is subscribed first, by the runner
            events.subscribe(display, kinds=display.KINDS)
            result: RunResult = runner(events, display, est.forecast())
    except KeyboardInterrupt as exc:
        why = f" ({exc.reason})" if isinstance(exc, StopSignal) else ""
        tables = _stop_failure(exc).removeprefix("; ") or "tables stopped"
        err.print(f"[bold red]interrupted[/]{why}: {tables}; {points_on_disk(run_dir)} reading(s) kept in "
                  f"{run_dir}; continue with: labcal resume {run_dir}")
        return 128 + exc.signum if isinstance(exc, StopSignal) else EXIT_INTERRUPTED  # 130 for Ctrl-C
    except OperatorDeclined as exc:
        err.print(f"[bold yellow]stopped[/]: {exc}{_stop_failure(exc)}; {points_on_disk(run_dir)} reading(s) "
                  f"kept in {run_dir}; continue with: labcal resume {run_dir}")
        return EXIT_STOPPED
    except LabcalError as exc:
        if not (run_dir / "run.json").exists():  # the run never started (or its folder is gone)
            raise
        raise LabcalError(f"{exc}{_stop_failure(exc)}; {points_on_disk(run_dir)} reading(s) kept in "
                          f"{run_dir}; continue with: labcal resume {run_dir}") from None
    o = result.outcome
    if result.device is not None:  # the device's estimate is the run's, whether or not a report is made
        from labcal.documents.device_history import store_device_estimate
        from labcal.run.record import load_run

        store_device_estimate(load_run(run_dir), result.device, args.db)
    issued = None
    if not args.no_report:
        from labcal.documents.report import write_run_outputs

        issued = write_run_outputs(run_dir, certificate, db=journal)
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
        from labcal.commands.console import device_tables

        for table in device_tables(result.device.to_json()):
            out.print(table)
    else:
        out.print(coefficients_with_standard_errors(result.fit))
    for note in (result.model_note, *result.fit.notes):
        out.print(f"[yellow]note:[/] {note}")
    failed = f", {o.points_failed} failed (see the journal)" if o.points_failed else ""
    out.print(f"{o.points_recorded} points{failed} in {result.wall_s:.2f} s of wall time; the rig's clock "
              f"says {format_duration(o.station_time_s)} (remount allowances included).")
    files = ", ".join(sorted(p.name for p in run_dir.iterdir() if not p.name.startswith(".")))
    if issued is not None:
        conformity = issued.certificate.conformity
        if conformity is not None:
            verdict = "[green]PASS[/]" if conformity.passed else "[red]FAIL[/]"
            out.print(f"Verdict against the tolerances: [bold]{verdict}[/]")
    out.print(f"Files in {run_dir}/: {files}; journal {journal}")
    if issued is not None:
        cert = issued.certificate
        out.print(f"Certificate {cert.certificate_id} issued: {issued.certificate_path}; stored in "
                  f"{issued.database} (labcal history {cert.instrument.serial})")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from labcal.analysis.plan import Plan
    from labcal.bench.setup import hardware_station, prepare, sim_station
    from labcal.config.plans import load_plan, plan_toml
    from labcal.run.estimate import estimate
    from labcal.run.interrupts import stop_signals_raise
    from labcal.run.journal import Journal, db_path
    from labcal.run.rundir import new_run_dir
    from labcal.run.runner import calibrate
    from labcal.run.sequencer import check_limits, schedule
    from labcal.run.sync import sending

    if not args.sim and not args.station:
        raise LabcalError("no station given: use --sim for a dry run on the simulated rig, or --station FILE "
                          "for a station's devices (add --emulate to run them on their emulators)")
    if args.sim and args.station:
        raise LabcalError("give --sim (the simulated rig) or --station FILE, not both")
    if args.emulate and not args.station:
        raise LabcalError("--emulate needs --station FILE: it starts the emulators that file points at")
    if args.rig and not args.sim:
        raise LabcalError("--rig describes the rig of --sim; an emulated station has [emulation.rig]")
    if args.pace is not None and not args.sim:
        raise LabcalError(PACE_SIM_ONLY)
    plan, plan_text = load_plan(args.plan)
    if not args.dry_run:  # a lab database behind or ahead of this labcal: refused before anything moves
        from labcal.run.sync import ready

        ready(args.db, _note)
    if args.replicates is not None:  # the journal keeps the plan that actually runs
        plan = Plan.model_validate({**plan.model_dump(), "replicates": args.replicates})
        plan_text = plan_toml(plan)
    with ExitStack() as stack:
        stack.enter_context(stop_signals_raise())  # a SIGTERM while homing stops the tables too
        bench = None
        if args.sim:
            setup = sim_station(args.rig, args.seed, pace=args.pace)
            settings = sequencer_settings_for_run(args, setup)
            cert_settings = certificate_settings_for_run(args, None, "command line")
        else:
            from labcal.config.station import load_station

            config, _ = load_station(args.station)
            cert_settings = certificate_settings_for_run(args, config.certificate, args.station)
            if not args.emulate and not args.serial and not args.no_report and not args.dry_run:
                raise LabcalError("a calibration on real hardware needs the instrument's --serial for its "
                                  "certificate (or --no-report)")
            if not args.dry_run:  # before an emulator or a device is opened, held until the end
                lock_station(stack, config, args.station, args.db)
            setup, bench = hardware_station(config, args.station, stack, emulate=args.emulate,
                                            time_scale=args.time_scale, seed=args.seed)
            if not args.dry_run:  # the links the emulators chose, by the addresses they chose
                lock_station(stack, config, args.station, args.db, chosen=bench.config)
            pitch, roll = config.pitch, config.roll  # the slower table sets the pace of the estimates
            settings = sequencer_settings_for_run(args, setup, min(pitch.speed_dps, roll.speed_dps),
                                                  min(pitch.accel_dps2, roll.accel_dps2))
            settings = settings.model_copy(update={
                "move_timeout_s": config.sequencer.move_timeout_s,
                "position_tolerance_deg": config.sequencer.position_tolerance_deg})
        ambient = ambient_entered(args)
        if ambient:
            setup.metadata["ambient"] = ambient  # the manifest's metadata: the certificate quotes it
        steps = schedule(plan, settings)  # once: the estimate, the limits and the run share it
        est = estimate(plan, settings, setup.timing, steps)
        if args.dry_run:
            print_estimate(plan, est, args.json)
            return 0
        setup.metadata["estimated_rig_time_s"] = est.total_s  # run.json: the estimate beside the actual
        check_limits(setup.station, steps, settings.check_mount)  # first: homing moves a table too
        if bench is not None:
            prepare(bench, setup.station, err.print)
            setup.metadata["device_identity"] = bench.identities  # the manifest's metadata and run.json
        operator = make_operator(args)
        run_dir = new_run_dir(args.out, plan)
        with Journal(db_path(args.db), durable=not args.sim) as journal, \
                sending(args.db, journal.path, _note):
            return run_and_report(args, lambda events, terminal, forecast: calibrate(
                plan, plan_text, setup.station, setup.text, operator, settings, run_dir, journal, events,
                setup.metadata, args.serial, args.operator, steps, terminal=terminal, forecast=forecast),
                run_dir, plan, est, 0, cert_settings)


def _note(line: str) -> None:
    from rich.markup import escape

    err.print(f"[yellow]note:[/] {escape(line)}")


def lock_station(stack: ExitStack, config: StationFile, name: str, db: str | Path | None,
                 chosen: StationFile | None = None) -> None:
    """Hold the station for this command (one run per station at a time, across processes: a second
    one is refused in one line naming who holds it); a lock left by a process that is gone is
    taken over, with a note. A link the emulators choose (port 0, ``pty:NAME``) is no address
    yet: it is held once they have chosen it, by a second call with ``chosen``, the station as
    they serve it (`Emulation.station_config`)."""
    from labcal.run.journal import db_path
    from labcal.run.lock import StationLock, station_locks

    links = {(chosen.devices()[n] if chosen is not None else s).bus:
             (chosen.devices()[n] if chosen is not None else s).where
             for n, s in config.devices().items() if s.chosen_by_emulators == (chosen is not None)}
    if not links:
        return
    lock = stack.enter_context(StationLock(station_locks(db_path(db)), links, name))
    for note in lock.notes:
        err.print(f"[yellow]note:[/] {note}")


def ambient_entered(args: argparse.Namespace) -> dict[str, float | str]:
    """The environmental conditions the operator entered at the start (ISO/IEC 17025 §7.8.2.1 i),
    as the run journals them; empty when none was entered."""
    found: dict[str, float | str] = {}
    if args.ambient_temp is not None:
        found["temperature_c"] = args.ambient_temp
    if args.humidity is not None:
        found["humidity_pct"] = args.humidity
    if found:
        found["source"] = "entered at the start of the run"
    return found


def cmd_resume(args: argparse.Namespace) -> int:
    from labcal.bench.setup import prepare, read_snapshot, sim_station, station_for_resume
    from labcal.config.settings import CertificateSettings
    from labcal.config.station import load_station
    from labcal.run.estimate import estimate
    from labcal.run.interrupts import stop_signals_raise
    from labcal.run.journal import sha256
    from labcal.run.runner import execute, open_for_resume
    from labcal.run.sequencer import check_limits, schedule
    from labcal.run.sync import sending
    from labcal.run.winding import left_at

    run_dir = Path(args.run)
    ctx = open_for_resume(run_dir)
    with ExitStack() as stack:
        stack.enter_context(stop_signals_raise())  # a SIGTERM while homing stops the tables too
        stack.callback(ctx.journal.close)
        stack.callback(ctx.lock.release)
        for note in ctx.notes:
            err.print(f"[yellow]note:[/] {note}")
        run_name = f"run {ctx.run_id} in {run_dir}"
        snapshot = read_snapshot(ctx.station_text, run_name, ctx.software_version)
        if args.pace is not None and snapshot is not None:
            raise LabcalError(f"{run_name} runs on a station, not the simulated rig: {PACE_SIM_ONLY}")
        if ctx.complete:
            settings = certificate_settings_for_run(args, snapshot.config.certificate if snapshot else None,
                                                    "the run's station")
            return finish_complete(args, run_dir, ctx.run_id, settings, ctx.journal.path)
        points = ctx.journal.points(ctx.run_id)
        start = ctx.journal.rig_time(ctx.run_id)  # the rig's clock goes on from here (one clock per run)
        new_station, on_station, station_record = None, "on the station it started on", None
        if args.station:
            if snapshot is None:
                raise LabcalError(f"{run_name} is a dry run on the simulated rig (--sim): it resumes on that "
                                  "rig; omit --station")
            new_config, new_text = load_station(args.station)
            new_station = (new_config, args.station)
            on_station = f"on station file {args.station} (sha256 {sha256(new_text)[:12]})"
            station_record = {"station_file": args.station, "station_sha256": sha256(new_text),
                              "station_text": new_text}
        bench = None
        tables_at = left_at(ctx.journal.events(ctx.run_id))  # a simulated rig's tables stayed there too
        if snapshot is None:
            ctx.journal.relax()  # a dry run: as when it started
            setup = sim_station(None, None, snapshot=ctx.station_text, start_time_s=start,
                                tables_at=tables_at, pace=args.pace)
            certificate = CertificateSettings()
        else:
            resumed_on = new_station[0] if new_station else snapshot.config
            lock_station(stack, resumed_on, args.station or run_name, ctx.journal.path)
            setup, bench = station_for_resume(snapshot, run_name, stack, start, new_station, tables_at)
            lock_station(stack, resumed_on, args.station or run_name, ctx.journal.path, chosen=bench.config)
            certificate = (new_station[0] if new_station else snapshot.config).certificate
        steps = schedule(ctx.plan, ctx.settings)
        est = estimate(ctx.plan, ctx.settings, setup.timing, steps)
        if bench is not None:
            check_limits(setup.station, steps)
            prepare(bench, setup.station, err.print)
        operator = make_operator(args)
        ctx.journal.reopen(ctx.run_id)
        ctx.journal.event(ctx.run_id, "resume",
                          f"resumed after {len(points)} committed point(s) {on_station}", station_record)
        if bench is not None:
            ctx.journal.event(ctx.run_id, "device_identity", "the devices that answered on resuming",
                              bench.identities)
        cert_settings = certificate_settings_for_run(args, certificate, args.station or "the run's station")
        stack.enter_context(sending(args.db, ctx.journal.path, _note))
        return run_and_report(args, lambda events, terminal, forecast: execute(
            ctx.journal, ctx.run_id, run_dir, ctx.plan, setup.station, operator, ctx.settings, events,
            steps, terminal=terminal, forecast=forecast),
            run_dir, ctx.plan, est, len(points), cert_settings, ctx.journal.path)


def finish_complete(args: argparse.Namespace, run_dir: Path, run_id: int,
                    settings: CertificateSettings, journal: Path) -> int:
    """A complete run resumed: its exports were checked and repaired; its certificate and report are
    issued again if any of them is missing or not the history's (a kill during `labcal report`)."""
    from labcal.documents.report import outputs_in_place, write_run_outputs

    if args.no_report or outputs_in_place(run_dir, db=journal):
        certificate = None
        message = f"run {run_id} is already complete; its files in {run_dir} match the journal"
    else:
        issued = write_run_outputs(run_dir, settings, db=journal)
        certificate = str(issued.certificate_path)
        message = (f"run {run_id} is already complete; certificate {issued.certificate.certificate_id} and "
                   f"its report written again in {run_dir}")
    if args.json:
        print_json({"run_dir": str(run_dir), "run_id": run_id, "status": "complete",
                    "already_complete": True, "certificate_rewritten": certificate})
    else:
        err.print(message)
    return 0


PACE_SIM_ONLY = ("--pace paces the simulated rig (--sim) only; a station's devices keep real time, and its "
                 "emulators run at --time-scale")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--pace", type=TIME_SCALE, metavar="X",
                   help="with --sim: run the simulated rig at X times real time (1: a rig second takes a "
                        "wall second; default: as fast as it can)")
    p.add_argument("--yes", action="store_true", help="confirm every remount prompt automatically")
    p.add_argument("--answers", metavar="FILE", help="answer prompts from this file, one answer per line")
    add_db_option(p)
    p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    p.add_argument("--no-report", action="store_true",
                   help="skip the certificate and report at the end (labcal report RUN makes them later)")
    p.add_argument("--tolerance-deg", type=bounded(float, 0, 180, lo_open=True), metavar="DEG",
                   help="pass/fail tolerance on the attitude U95 over the usage envelope")
    p.add_argument("--usage-pitch", type=float, nargs=2, metavar=("MIN", "MAX"),
                   help="usage pitch range for the attitude uncertainty (default -60 60)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="run a calibration (on the simulated rig with --sim, or on a --station)",
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
    _common(p)
    p.set_defaults(func=cmd_run)

    r = sub.add_parser("resume", help="continue an interrupted run where it stopped",
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

"""Running a calibration, and resuming one: the one sequence both share (run with a view, turn the
ways a run ends into outcomes, store the device's estimate, issue the certificate), and what
each does before it (a new run: the station, the plan, the locks, the estimate; a resume: the
journal's run, its station or another file of the same bench).

Whoever starts a run (the command line; later the lab server) gives a `FrontEnd`: the operator
who answers prompts, the view that shows progress, and where messages go. What the run ended as
comes back as a typed outcome; printing it is the front end's business.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from contextlib import AbstractContextManager, ExitStack
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING, Literal, Protocol

from labcal.analysis.packages import package_problem
from labcal.app.standards import standards_for_run
from labcal.bench.setup import hardware_station, prepare, read_snapshot, sim_station, station_for_resume
from labcal.config import station as config_station
from labcal.config.files import validate_model
from labcal.config.lab import certificate_settings, load_lab_config
from labcal.config.plans import correction_toml, load_plan, plan_correction, plan_toml
from labcal.config.snapshot import SimulatedRigSnapshot, is_simulated, parse_snapshot
from labcal.config.station import load_station
from labcal.devices.winding import left_at
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.run.events import EventBus
from labcal.run.interrupts import StopSignal, stop_signals_raise
from labcal.run.operator import OperatorDeclined
from labcal.run.runner import calibrate, execute, open_for_resume
from labcal.run.sequencer import check_limits, schedule
from labcal.store import journal as store_journal
from labcal.store.journal import Journal, db_path, sha256, station_name
from labcal.store.labquery import lab_number_of
from labcal.store.lock import StationLock, station_locks
from labcal.store.rundir import new_run_dir, points_on_disk
from labcal.store.sync import check_server, ready, sending

if TYPE_CHECKING:
    from labcal.analysis import plan as analysis_plan
    from labcal.analysis.plan import Plan
    from labcal.app import folders, instruments, run_documents
    from labcal.app.standards import RunStandards
    from labcal.bench.hardware import Bench
    from labcal.bench.setup import StationSetup
    from labcal.config import run_metadata
    from labcal.config import settings as config_settings
    from labcal.config.run_metadata import Ambient, Checklist, PackageUse, RunMetadata
    from labcal.config.settings import CertificateSettings, SequencerSettings, ThermalGate
    from labcal.config.station import InstrumentSettings, StationFile
    from labcal.devices.station import Station
    from labcal.documents import device_history, overrides, report
    from labcal.documents.report import RunOutputs
    from labcal.run import estimate as run_estimate
    from labcal.run import notify
    from labcal.run.estimate import Estimate
    from labcal.run.events import RunEvent
    from labcal.run.notify import RunName, RunNotifier
    from labcal.run.operator import Operator, Terminal
    from labcal.run.runner import RunResult
    from labcal.store import record as store_record
    from labcal.store.sync import Background
else:
    analysis_plan = lazy("labcal.analysis.plan")  # start-up without numpy, pydantic
    config_settings = lazy("labcal.config.settings")  # start-up without pydantic
    device_history = lazy("labcal.documents.device_history")  # start-up without scipy, numpy, pydantic
    folders = lazy("labcal.app.folders")  # start-up without scipy, numpy, pydantic, …
    instruments = lazy("labcal.app.instruments")  # start-up without matplotlib, scipy, numpy, …
    notify = lazy("labcal.run.notify")  # start-up without scipy, numpy, pydantic
    overrides = lazy("labcal.documents.overrides")  # start-up without pydantic
    report = lazy("labcal.documents.report")  # start-up without matplotlib, scipy, numpy, …
    run_documents = lazy("labcal.app.run_documents")  # start-up without matplotlib, scipy, numpy, …
    run_estimate = lazy("labcal.run.estimate")  # start-up without scipy, numpy, pydantic, …
    run_metadata = lazy("labcal.config.run_metadata")  # start-up without pydantic
    store_record = lazy("labcal.store.record")  # start-up without scipy, numpy, pydantic


class Display(Protocol):
    """The front end's view of a run: a subscriber to its events, and the terminal its prompts use."""

    KINDS: tuple[str, ...]

    def __call__(self, event: RunEvent) -> None: ...


class FrontEnd(Protocol):
    """What a run needs from whoever started it."""

    def say(self, text: str, markup: bool = True) -> None:
        """A line for the operator: where the run goes, homing, a note (rich markup unless
        ``markup`` is False: text from elsewhere, such as a notification service's answer)."""

    def operator(self) -> Operator:
        """Who answers the run's prompts."""

    def checklist(self, bench: Bench | None, station: Station, points: int, samples: int) -> Checklist:
        """The pre-run checklist (`labcal.bench.checklist`), shown before anything moves; what the
        run journals of it. An unmet item raises LabcalError unless whoever is there says to go on."""

    def unregistered(self, serial: str) -> bool:
        """Whether to calibrate ``serial``, which the lab's instrument register does not hold: asked at
        the terminal; False where nobody is asked (--yes, a script)."""

    def display(self, total: int, done: int) -> AbstractContextManager[tuple[Display, Terminal]]:
        """The view of the run's progress while it measures (subscribed to the run's events), and the
        terminal the run's prompts use."""


@dataclass(frozen=True)
class StartRun:
    """`labcal run`'s options, by the same names."""

    sim: bool = False
    station: str | None = None
    emulate: bool = False
    time_scale: float | None = None
    plan: str = "four-mount-64"
    replicates: int | None = None
    order: Literal["shortest", "plan", "sweep", "random"] = "shortest"
    seed: int | None = None
    out: str | None = None
    rig: str | None = None
    instrument: Literal["three-axis", "two-axis-xy", "two-axis-xz", "single-axis"] | None = None
    samples: int | None = None
    fixed_dwell: float | None = None
    max_dwell: float | None = None
    settle: str | None = None
    on_failure: Literal["skip", "pause", "abort"] = "skip"
    no_mount_check: bool = False
    ambient_temp: float | None = None
    humidity: float | None = None
    serial: str | None = None
    operator: str | None = None
    dry_run: bool = False
    pace: float | None = None
    db: str | None = None
    no_report: bool = False
    tolerance_deg: float | None = None
    usage_pitch: tuple[float, float] | None = None
    thermal_gate: tuple[float, float] | None = None  # °C/min, s


@dataclass(frozen=True)
class ResumeRun:
    """`labcal resume`'s options, by the same names."""

    run: str
    station: str | None = None
    pace: float | None = None
    db: str | None = None
    no_report: bool = False
    tolerance_deg: float | None = None
    usage_pitch: tuple[float, float] | None = None


@dataclass(frozen=True)
class Estimated:
    """A dry run (--dry-run): what the plan would take on this station; nothing moved."""

    plan: Plan
    estimate: Estimate


@dataclass(frozen=True)
class Ended:
    """A run that ended before its last point: Ctrl-C or a signal ("interrupted"), or the operator
    ("stopped"); every reading taken is in the journal and the run resumes."""

    run_dir: Path
    how: str  # "interrupted" or "stopped"
    why: str  # the signal's or the operator's reason, "" when none
    tables: str  # "tables stopped", or the STOP FAILED notes
    points_kept: int
    signum: int | None = None  # the signal that stopped it (None: Ctrl-C or the operator)


@dataclass(frozen=True)
class Finished:
    run_dir: Path
    result: RunResult
    estimate: Estimate
    journal: Path
    issued: RunOutputs | None  # None with --no-report


@dataclass(frozen=True)
class AlreadyComplete:
    """A complete run resumed: its exports were checked and repaired; its certificate and report
    issued again if any was missing or not the history's."""

    run_id: int
    run_dir: Path
    certificate: str | None  # the certificate written again, if it was
    certificate_id: str | None = None


def sequencer_settings_for_run(args: StartRun, setup: StationSetup, speed: float = 20.0,
                               accel: float = 40.0, station_gate: ThermalGate | None = None
                               ) -> SequencerSettings:
    """The run's sequencer settings: the options over the station's (``station_gate``: its
    [instrument] thermal_gate; --thermal-gate overrides it)."""
    settle = validate_model({**setup.settle.model_dump(), **{
        k: v for k, v in (("samples", args.samples), ("fixed_dwell_s", args.fixed_dwell),
                          ("max_dwell_s", args.max_dwell),
                          ("mode", args.settle)) if v is not None}}, config_settings.SettleSettings,
        "command line: settle")  # validated: the options and the station file share one range
    gate = (
        None
        if args.thermal_gate is None
        else config_settings.ThermalGate(rate_c_per_min=args.thermal_gate[0], hold_s=args.thermal_gate[1])
    )
    return config_settings.SequencerSettings(
        settle=settle,
        order=args.order,
        seed=args.seed or 0,
        on_failure=args.on_failure,
        check_mount=not args.no_mount_check,
        speed_dps=speed,
        accel_dps2=accel,
        thermal_gate=gate or station_gate,
    )


def certificate_settings_for_run(args: StartRun | ResumeRun, station: CertificateSettings | None,
                                 source: str) -> CertificateSettings:
    """The lab file's certificate defaults, the station's [certificate] settings over them, and the
    command line's tolerances over both."""
    usage = tuple(args.usage_pitch) if args.usage_pitch else None
    return certificate_settings(station, source).overridden(source, attitude_u95_max_deg=args.tolerance_deg,
                                                         usage_pitch_deg=usage)


def _stop_failure(exc: BaseException) -> str:
    """'; STOP FAILED: …' when the run's last stop did not reach a table (noted on the exception
    that ended the run), else ''."""
    return "".join(f"; {note}" for note in getattr(exc, "__notes__", ()) if note.startswith("STOP FAILED"))


PACE_SIM_ONLY = ("{0} paces the simulated rig ({1}) only; a station's devices keep real time, and its "
                 "emulators run at {2}")
PACE_FIELDS = ("pace", "sim", "time_scale")


def _run_status(run_dir: Path) -> str | None:
    """The status run.json states (None where it cannot be read)."""
    try:
        return json.loads((run_dir / "run.json").read_text(encoding="utf-8")).get("status")
    except (OSError, ValueError, AttributeError):
        return None


def _noted(front: FrontEnd) -> Callable[[str], None]:
    """A note for the operator from elsewhere (the lab server's sender): plain text, no markup."""
    return lambda line: front.say(f"note: {line}", markup=False)


def run_and_finish(front: FrontEnd, runner, run_dir: Path, plan: Plan, est: Estimate, done: int,
                   db: str | None, no_report: bool, certificate=None,
                   journal: Path | None = None, notifier: RunNotifier | None = None,
                   sender: Background | None = None) -> Ended | Finished:
    """The sequence a run and a resume share: run with the front end's view and the notifier
    subscribed to its events (the journal is subscribed first, by the runner); turn the ways a run can
    end into outcomes; at the end of a complete run store the device's estimate and issue its
    certificate and report (``certificate``: their settings) into the run's journal (``journal``: a
    resumed run's, which its folder names; else ``db``'s)."""
    journal = journal or db_path(db)
    front.say(f"Run directory: {run_dir}", markup=False)  # a folder named run[1] is a name, not markup
    try:
        with front.display(plan.n_points, done) as (display, terminal):
            events = EventBus()
            events.subscribe(display, kinds=display.KINDS)
            if notifier is not None:  # remounts, pauses and the end, through apprise
                events.subscribe(notifier.handle, kinds=notifier.KINDS)
            if sender is not None:  # a record journaled: sent to the lab's server now, not at the next poll
                events.subscribe(lambda _: sender.wake())
            result: RunResult = runner(events, terminal, est.forecast())
    except KeyboardInterrupt as exc:
        tables = _stop_failure(exc).removeprefix("; ") or "tables stopped"
        if isinstance(exc, StopSignal):
            return Ended(run_dir, "interrupted", exc.reason, tables, points_on_disk(run_dir), exc.signum)
        return Ended(run_dir, "interrupted", "", tables, points_on_disk(run_dir))
    except OperatorDeclined as exc:
        return Ended(run_dir, "stopped", str(exc), _stop_failure(exc), points_on_disk(run_dir))
    except LabcalError as exc:
        if not (run_dir / "run.json").exists():  # the run never started (or its folder is gone)
            raise
        # the refusal's own fields kept (its message, not its command-line spelling): a front end spells them
        kept = f"{exc.message}{_stop_failure(exc)}; {points_on_disk(run_dir)} reading(s) kept in {run_dir}"
        if _run_status(run_dir) == "failed":  # measured to the end: a resume has nothing left to measure
            raise LabcalError(kept, *exc.options) from None
        raise LabcalError(f"{kept}; continue with: labcal resume {run_dir}", *exc.options) from None
    record = None  # the finished run as its journal has it, read (and its fits made) once for both
    if result.device is not None:  # the device's estimate is the run's, whether or not a report is made
        record = store_record.load_run(run_dir)
        device_history.store_device_estimate(record, result.device, db)
    issued = None
    if not no_report:
        try:
            issued = run_documents.write_run_outputs(run_dir, certificate, db=journal, record=record)
        except (
            device_history.DeviceMoved
        ) as exc:  # journaled for the lab, then the one line to the technician
            with store_journal.Journal(journal) as book:
                book.event(
                    result.run_id, "device_moved", str(exc), {"changes": [c.to_json() for c in exc.changes]}
                )
            raise
    return Finished(run_dir, result, est, journal, issued)


def start_run(args: StartRun, front: FrontEnd) -> Estimated | Ended | Finished:
    """A calibration on the simulated rig (``sim``) or a station file's devices (``station``, on its
    emulators with ``emulate``): every angle checked before anything moves, the station locked
    for the run, then the shared sequence."""
    if not args.sim and not args.station:
        raise LabcalError("no station given: use {0} for a dry run on the simulated rig, or {1} FILE "
                          "for a station's devices (add {2} to run them on their emulators)",
                          "sim", "station", "emulate")
    if args.sim and args.station:
        raise LabcalError("give {0} (the simulated rig) or {1} FILE, not both", "sim", "station")
    if args.emulate and not args.station:
        raise LabcalError("{0} needs {1} FILE: it starts the emulators that file points at", "emulate",
                          "station")
    if args.rig and not args.sim:
        raise LabcalError("{0} describes the rig of {1}; an emulated station has [emulation.rig]",
                          "rig", "sim")
    if args.pace is not None and not args.sim:
        raise LabcalError(PACE_SIM_ONLY, *PACE_FIELDS)
    if args.instrument and not args.sim:
        raise LabcalError("{0} chooses the simulated rig's package ({1}); a station's is its "
                          "[instrument] package", "instrument", "sim")
    serial, adhoc = run_serial(args, front)  # before the station is opened: a bad serial costs no rig time
    plan, plan_text = load_plan(args.plan)
    correction = plan_correction(plan_text, args.plan)  # the device's misalignments it corrects for
    if args.replicates is not None:  # the journal keeps the plan that actually runs
        plan = analysis_plan.Plan.model_validate({**plan.model_dump(), "replicates": args.replicates})
        plan_text = plan_toml(plan) + ("" if correction is None else "\n" + correction_toml(correction))
    with ExitStack() as stack:
        stack.enter_context(stop_signals_raise())  # a SIGTERM while homing stops the tables too
        notifications = stack.enter_context(
            notify.lab_notifications(lambda line: front.say(line, markup=False))
        )
        bench = None
        if args.sim:
            setup = sim_station(args.rig, args.seed, pace=args.pace, package=args.instrument)
            journaled = SimulatedRigSnapshot.model_validate_json(setup.text)
            package = journaled.rig_config().instrument.package
            if package != "three-axis":  # how its angles are obtained in use, for its statement
                setup.metadata.package = sim_package_use(package, journaled.rig)
            settings = sequencer_settings_for_run(args, setup)
            cert_settings = certificate_settings_for_run(args, None, "command line")
        else:
            assert args.station is not None
            config, _ = config_station.load_station(args.station)
            cert_settings = certificate_settings_for_run(args, config.certificate, args.station)
            check_package(config.instrument, cert_settings, args.station, args.plan)  # before anything moves
            if not args.emulate and not args.serial and not args.no_report and not args.dry_run:
                raise LabcalError("a calibration on real hardware needs the instrument's {0} for its "
                                  "certificate (or {1})", "serial", "no_report")
            if not args.dry_run:  # before an emulator or a device is opened, held until the end
                lock_station(stack, config, args.station, args.db, front)
            setup, bench = hardware_station(config, args.station, stack, emulate=args.emulate,
                                            time_scale=args.time_scale, seed=args.seed)
            if not args.dry_run:  # the links the emulators chose, by the addresses they chose
                lock_station(stack, config, args.station, args.db, front, chosen=bench.config)
            if config.instrument.package != "three-axis":
                setup.metadata.package = station_package_use(config.instrument)  # its statement
            pitch, roll = config.pitch, config.roll  # the slower table sets the pace of the estimates
            settings = sequencer_settings_for_run(args, setup, min(pitch.speed_dps, roll.speed_dps),
                                                  min(pitch.accel_dps2, roll.accel_dps2),
                                                  config.instrument.thermal_gate)
            settings = settings.model_copy(update={
                "move_timeout_s": config.sequencer.move_timeout_s,
                "position_tolerance_deg": config.sequencer.position_tolerance_deg})
        if adhoc:  # run.json and the journal: why a serial the register lacks was certified
            setup.metadata.unregistered_serial = adhoc
        ambient = ambient_entered(args)
        if ambient:
            setup.metadata.ambient = ambient  # the manifest's metadata: the certificate quotes it
        steps = schedule(plan, settings)  # once: the estimate, the limits and the run share it
        est = run_estimate.estimate(plan, settings, setup.timing, steps)
        if args.dry_run:
            return Estimated(plan, est)
        ready(args.db)  # a lab database behind or ahead of this labcal: refused before anything moves
        # an overdue reference standard stops the run here unless an approver's override holds
        used = run_standards([] if bench is None else bench.config.standards, args.db, front)
        if used.used:  # journaled only where the run used any
            setup.metadata.standards = used.used
        if used.overrides:
            setup.metadata.standard_overrides = used.overrides
        if correction is not None:  # still this station's device, still in control: else nothing moves
            device_history.check_correction(
                correction,
                device_history.station_device_id(
                    setup.metadata.with_station(setup.station.description), args.sim or args.emulate
                ),
                args.db,
                plan,
            )
        setup.metadata.estimated_rig_time_s = est.total_s  # run.json: the estimate beside the actual
        check_limits(setup.station, steps, settings.check_mount)  # first: homing moves a table too
        run_dir = new_run_dir(args.out, plan)  # a bad --out is one line before the checklist
        setup.metadata.checklist = front.checklist(bench, setup.station, plan.n_points,
                                                      settings.settle.samples)  # before anything moves
        if bench is not None:
            prepare(bench, setup.station, front.say)
            setup.metadata.device_identity = dict(bench.identities)  # the manifest's metadata and run.json
        operator = front.operator()
        with Journal(db_path(args.db), durable=not args.sim) as journal, \
                sending(args.db, journal.path, _noted(front)) as sender:
            return run_and_finish(
                front,
                lambda events, terminal, forecast: calibrate(
                    plan,
                    plan_text,
                    setup.station,
                    setup.text,
                    operator,
                    settings,
                    run_dir,
                    journal,
                    events,
                    setup.metadata,
                    serial,
                    args.operator,
                    steps,
                    terminal=terminal,
                    forecast=forecast,
                ),
                run_dir,
                plan,
                est,
                0,
                args.db,
                args.no_report,
                cert_settings,
                notifier=notify.RunNotifier(
                    notifications,
                    _run_name(setup.metadata, setup.text, serial),
                    run_dir,
                    _lab_label(journal.path, args.db),
                    not operator.confirms_mounts,
                ),
                sender=sender,
            )


def _run_name(metadata: RunMetadata, station_text: str, serial: str | None) -> RunName:
    """How the run's notifications name it: this bench as the lab database names it, the serial, and
    the lab server's page of the run where the lab file gives the server's address."""
    lab = load_lab_config()
    return notify.RunName(lab.station(), serial, lab.file.server_url,
                          is_simulated(metadata, parse_snapshot(station_text)))


def _lab_label(journal: Path, db: str | Path | None) -> Callable[[int], str]:
    """How a notification names the run: by the lab's number (its provisional label until the lab
    has numbered it), as every bench, page and API answer does."""
    return lambda run_id: lab_number_of(journal, run_id, db)


def sim_package_use(package: str, rig: dict) -> PackageUse:
    """How the simulated rig's package is used: an x–y package infers roll itself (Tripp §6.4); a
    single sensor and an x–z package (whose F_z is singular at roll 0, Tripp eq. 94, so that it is
    used over pitch at a known roll, §6.5) at the roll the roll table sets, whose standard deviation
    is the table's index error (the rig's ±index_arcsec taken as uniform bounds)."""
    if package == "two-axis-xy":
        return run_metadata.PackageUse(package=package, roll_in_use="inferred", roll_sd_deg=None)
    index_deg = rig["device"]["index_arcsec"] / 3600
    return run_metadata.PackageUse(package=package, roll_in_use="table", roll_sd_deg=index_deg / 3 ** 0.5)


def station_package_use(instrument: InstrumentSettings) -> PackageUse:
    """How a station's package is used, as its ``[instrument]`` states it: roll inferred from its own
    outputs, none (pitch at roll 0), or measured by the table or a sensor with its σ_R."""
    return run_metadata.PackageUse(package=instrument.package, roll_in_use=instrument.roll_source,
                                   roll_sd_deg=instrument.roll_sd_deg)


ADHOC_ALLOWED = "not in the instrument register; the lab file allows ad-hoc serials"
ADHOC_ASKED = "not in the instrument register; the operator said to calibrate it as an ad-hoc serial"


def run_serial(args: StartRun, front: FrontEnd) -> tuple[str | None, str | None]:
    """The serial the run certifies (`labcal.app.instruments`): whitespace around it stripped with a
    note, a control character refused, the register's spelling taken; a serial the register (when it
    holds any instrument) lacks is asked about, and refused where nobody is asked unless the lab file
    allows ad-hoc serials — then also why it was taken (`ADHOC_ALLOWED`, `ADHOC_ASKED`; None: it is
    registered, or the register is empty). A dry run only cleans it (it certifies nothing, and opens
    no database)."""
    if args.serial is None:
        return None, None
    if args.dry_run:
        return instruments.checked_serial(args.serial)[0], None
    found = instruments.serial_for_run(args.serial, args.db)
    for note in found.notes:
        front.say(f"note: {note}", markup=False)
    if not found.unregistered:
        return found.serial, None
    if load_lab_config().file.instruments.allow_adhoc:
        front.say(f"note: {found.serial!r} is {ADHOC_ALLOWED} ([instruments] allow_adhoc)", markup=False)
        return found.serial, ADHOC_ALLOWED
    if front.unregistered(found.serial):
        return found.serial, ADHOC_ASKED
    raise LabcalError(f"{found.serial!r} is not in the lab's instrument register (nothing moved): "
                      f"register it with `labcal instrument add {found.serial}`, check the serial with "
                      "`labcal instrument list --search TEXT`, or allow ad-hoc serials in the lab file "
                      "([instruments] allow_adhoc = true)")


def run_standards(named: list[str], db: str | None, front: FrontEnd) -> RunStandards:
    """The reference standards the run uses, checked before anything moves (`labcal.app.standards`):
    an overdue one without an approver's override stops it in one line; what the run journals of them."""
    found = standards_for_run(named, station_name(), db, datetime.now().astimezone().date())
    for note in found.notes:
        front.say(f"note: {note}", markup=False)
    for held in found.overrides:
        front.say(f"note: reference standard {held.serial} is overdue (due {held.due_on}); the run "
                  f"goes on under {held.approver}'s override until {held.valid_until}: {held.reason}",
                  markup=False)
    return found


def check_package(instrument: InstrumentSettings, envelope: CertificateSettings, station: str, plan: str
                  ) -> None:
    """Refuse a package that cannot give its angles over the certificate's usage envelope (Tripp §6)."""
    roll = instrument.roll_source
    assert roll is not None  # the station file's validation requires it for a single axis
    problem = package_problem(instrument.package, roll, envelope.usage_pitch_deg, envelope.usage_roll_deg)
    if problem:
        raise LabcalError(f"{station}: {problem} (labcal plan audit {plan} --station {station})")


def lock_station(stack: ExitStack, config: StationFile, name: str, db: str | Path | None, front: FrontEnd,
                 chosen: StationFile | None = None) -> None:
    """Hold the station for this command (one run per station at a time, across processes: a second
    one is refused in one line naming who holds it); a lock left by a process that is gone is
    taken over, with a note. A link the emulators choose (port 0, ``pty:NAME``) is no address
    yet: it is held once they have chosen it, by a second call with ``chosen``, the station as
    they serve it (`Emulation.station_config`)."""
    links = {(chosen.devices()[n] if chosen is not None else s).bus:
             (chosen.devices()[n] if chosen is not None else s).where
             for n, s in config.devices().items() if s.chosen_by_emulators == (chosen is not None)}
    if not links:
        return
    lock = stack.enter_context(StationLock(station_locks(db_path(db)), links, name))
    for note in lock.notes:
        front.say(f"note: {note}", markup=False)


def ambient_entered(args: StartRun) -> Ambient | None:
    """The environmental conditions the operator entered at the start (ISO/IEC 17025 §7.8.2.1 i),
    as the run journals them; None when none was entered."""
    entered = {k: v for k, v in (("temperature_c", args.ambient_temp), ("humidity_pct", args.humidity))
               if v is not None}
    return run_metadata.Ambient(**entered, source="entered at the start of the run") if entered else None


def resume_run(args: ResumeRun, front: FrontEnd) -> Ended | Finished | AlreadyComplete:
    """Go on with an interrupted run at the first point not in the journal, on the station it
    started on or another station file of the same bench; then the shared sequence."""
    run_dir = Path(args.run)
    check_server(args.db)  # a lab server behind or ahead of this labcal: refused before anything changes
    ctx = open_for_resume(run_dir)
    with ExitStack() as stack:
        stack.enter_context(stop_signals_raise())  # a SIGTERM while homing stops the tables too
        notifications = stack.enter_context(
            notify.lab_notifications(lambda line: front.say(line, markup=False))
        )
        stack.callback(ctx.journal.close)
        stack.callback(ctx.lock.release)
        # a copy (`labcal export RUN --out DIR`) resumed is the run's folder from now on
        folders.record_folder(ctx.journal, ctx.journal.run(ctx.run_id), run_dir, "resume")
        for note in ctx.notes:
            front.say(f"note: {note}", markup=False)
        run_name = f"run {_lab_label(ctx.journal.path, args.db)(ctx.run_id)} in {run_dir}"
        snapshot = read_snapshot(ctx.station_text, run_name, ctx.software_version)
        if args.pace is not None and snapshot is not None:
            raise LabcalError(f"{run_name} runs on a station, not the simulated rig: " + PACE_SIM_ONLY,
                              *PACE_FIELDS)
        if ctx.complete:
            settings = certificate_settings_for_run(args, snapshot.config.certificate if snapshot else None,
                                                    "the run's station")
            return finish_complete(args, run_dir, ctx.run_id, settings, ctx.journal.path)
        points = ctx.journal.points(ctx.run_id)
        start = ctx.journal.rig_time(ctx.run_id)  # the rig's clock goes on from here (one clock per run)
        new_station, on_station, station_record = None, "on the station it started on", None
        if args.station:
            if snapshot is None:
                raise LabcalError(f"{run_name} is a dry run on the simulated rig ({{0}}): it resumes on that "
                                  "rig; omit {1}", "sim", "station")
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
            certificate = config_settings.CertificateSettings()
        else:
            resumed_on = new_station[0] if new_station else snapshot.config
            lock_station(stack, resumed_on, args.station or run_name, ctx.journal.path, front)
            setup, bench = station_for_resume(snapshot, run_name, stack, start, new_station, tables_at)
            lock_station(stack, resumed_on, args.station or run_name, ctx.journal.path, front,
                         chosen=bench.config)
            certificate = (new_station[0] if new_station else snapshot.config).certificate
        steps = schedule(ctx.plan, ctx.settings)
        est = run_estimate.estimate(ctx.plan, ctx.settings, setup.timing, steps)
        # a standard that fell due since the run started stops it here too, unless an override holds
        checked = run_standards([] if bench is None else bench.config.standards, args.db, front)
        if bench is not None:
            check_limits(setup.station, steps)
            prepare(bench, setup.station, front.say)
        operator = front.operator()
        ctx.journal.reopen(ctx.run_id)
        ctx.journal.event(ctx.run_id, "resume",
                          f"resumed after {len(points)} committed point(s) {on_station}", station_record)
        for held in checked.overrides:  # the certificate states it with the run's own
            ctx.journal.event(
                ctx.run_id,
                overrides.STANDARD_OVERRIDE_EVENT,
                f"resumed under {held.approver}'s override for the overdue reference standard {held.serial}",
                held.model_dump(mode="json"),
            )
        if bench is not None:
            ctx.journal.event(ctx.run_id, "device_identity", "the devices that answered on resuming",
                              {role: said.model_dump(mode="json") for role, said in bench.identities.items()})
        cert_settings = certificate_settings_for_run(args, certificate, args.station or "the run's station")
        sender = stack.enter_context(sending(args.db, ctx.journal.path, _noted(front)))
        name = _run_name(ctx.metadata, ctx.station_text, ctx.journal.run(ctx.run_id).instrument_serial)
        return run_and_finish(front, lambda events, terminal, forecast: execute(
            ctx.journal, ctx.run_id, run_dir, ctx.plan, setup.station, operator, ctx.settings, events,
            steps, terminal=terminal, forecast=forecast),
            run_dir, ctx.plan, est, len(points), args.db, args.no_report, cert_settings, ctx.journal.path,
            notifier=notify.RunNotifier(notifications, name, run_dir, _lab_label(ctx.journal.path, args.db),
                                        not operator.confirms_mounts), sender=sender)


def finish_complete(args: ResumeRun, run_dir: Path, run_id: int,
                    settings: CertificateSettings, journal: Path) -> AlreadyComplete:
    """A complete run resumed: its exports were checked and repaired; its certificate and report are
    issued again if any of them is missing or not the history's (a kill during `labcal report`)."""
    if args.no_report or report.outputs_in_place(run_dir, db=journal):
        return AlreadyComplete(run_id, run_dir, None)
    issued = run_documents.write_run_outputs(run_dir, settings, db=journal)
    return AlreadyComplete(run_id, run_dir, str(issued.certificate_path), issued.certificate.certificate_id)

"""Terminal output: the run's progress bar and the tables people read."""

from __future__ import annotations

import argparse
from collections.abc import Iterable
from contextlib import ExitStack, contextmanager
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from rich import box
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
)
from rich.table import Table

from labcal.analysis.fit import ROW_NAMES, SENSORS, Fit
from labcal.commands.common import err
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.run.events import Discarded, Fault, PointMeasured, RunEvent, Status, Stopped
from labcal.run.operator import GATE_KEY, QuietKeys, Terminal
from labcal.store.journal import db_path
from labcal.store.labdb import lab_server

if TYPE_CHECKING:
    from labcal.bench import checklist
    from labcal.bench.checklist import Item, PowerOn
    from labcal.bench.hardware import Bench
    from labcal.config.run_metadata import Checklist
    from labcal.devices.station import Station
    from labcal.documents import certificate
else:
    certificate = lazy("labcal.documents.certificate")  # start-up without scipy, numpy, pydantic
    checklist = lazy("labcal.bench.checklist")  # start-up without pydantic


def clock(seconds: float) -> str:
    """'25:34' or '1:02:03': a duration in the fewest columns (the progress line must fit 80)."""
    seconds = int(round(max(seconds, 0.0)))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


RIG_CLOCK_NOTE = ("progress: 'rig' is the rig's own clock (the simulated or emulated station's, which may "
                  "run faster than the wall's); 'ETA' is the plan's estimate of the rest on that clock: "
                  "moves, settling, averaging and remount allowances")


class ProgressDisplay(Terminal):
    """The run's console view, one subscriber of its events among others (subscribe it for
    ``KINDS``): a progress bar with the rig's clock and the ETA of what remains, both on the rig's
    clock (an emulated run's wall time says nothing about the rig's), and the last point; fits 80
    columns; faults, stops that failed and points measured again are printed above it. While it is
    shown, keys typed at the terminal do not echo into it (`QuietKeys`); a prompt (`pause`, the
    terminal's, not an event) has them echo again."""

    KINDS = ("point", "status", "fault", "stop", "discarded")

    def __init__(self, console: Console, total: int, done: int = 0):
        self.progress = Progress(
            BarColumn(bar_width=16), MofNCompleteColumn(),
            TextColumn("rig {task.fields[rig]} ETA {task.fields[rig_eta]}"),
            TextColumn("{task.fields[last]}"), console=console, transient=False,
        )
        self.task = self.progress.add_task("calibrating", total=total, completed=done, last="", rig="–",
                                           rig_eta="–")
        console.print(f"[dim]{RIG_CLOCK_NOTE}[/]")
        self.keys = QuietKeys()
        if self.keys.fd is not None:  # a terminal to type at: what its keys do during the run
            console.print(f"[dim]keys: {GATE_KEY} holds the run at the thermal gate before its next point; "
                          "Ctrl-C pauses after the current point[/]")
        self._shown = ExitStack()

    def __enter__(self) -> ProgressDisplay:
        with ExitStack() as stack:
            stack.enter_context(self.keys)
            self.progress.start()
            stack.callback(self.progress.stop)
            self._shown = stack.pop_all()  # the terminal restored after the display stops, always
        return self

    def __exit__(self, *exc: object) -> None:
        self._shown.close()

    @contextmanager
    def pause(self):
        self.__exit__()
        try:
            yield
        finally:
            self.__enter__()

    def __call__(self, event: RunEvent) -> None:
        if isinstance(event, PointMeasured):
            settled = "" if event.settle_s is None else f" {event.settle_s:.1f} s"
            self.progress.update(self.task, completed=event.points_done, rig=clock(event.rig_time_s),
                                 last=f"p={event.pitch_deg:g}° r={event.roll_deg:g}°{settled}")
        elif isinstance(event, Status):  # the ETA: the plan's estimate of what remains
            self.progress.update(self.task, completed=event.points_done,
                                 rig_eta="–" if event.eta_s is None else clock(event.eta_s))
        elif isinstance(event, Fault):
            self.notice(f"[bold red]Fault:[/] {event.message}")
        elif isinstance(event, Stopped) and event.failed is not None:
            self.notice(f"[bold red]STOP FAILED:[/] {event.failed}; make the table safe by hand")
        elif isinstance(event, Discarded) and not event.faulted:
            self.notice(f"[yellow]Point {event.seq} measured again:[/] {event.reason}")

    def notice(self, text: str) -> None:
        self.progress.console.print(text)

    def typed(self) -> str:
        return self.keys.typed()


def with_standard_error(value: float, se: float) -> str:
    """'value ± SE' to the digits the standard error supports (SE to two significant digits,
    the value rounded to the same decimal), as the certificate rounds (GUM 7.2.6)."""
    if not np.isfinite(se):
        return f"{value:+.7g}"
    text = certificate.format_result(value, se)
    return f"{'+' if not text.startswith('-') else ''}{text}"


def coefficients_with_standard_errors(fit: Fit, title: str = "Fitted coefficients X = [Bᵀ; S]",
                                      units: str = "V") -> Table:
    """The fit's coefficients ± one standard error, for the terminal (the certificate's table,
    `labcal.documents.report_tables.coefficients_with_expanded_uncertainty`, states ± U95 instead)."""
    table = Table(title=f"{title}, ± u (k=1)", box=box.SIMPLE_HEAD, pad_edge=False)  # fits 80 columns
    table.add_column("row", no_wrap=True)
    for name in fit.sensors:
        table.add_column(f"sensor {name}", justify="right")  # wrapped, never cut, on a narrow terminal
    se = fit.stderr
    for i, row in enumerate(ROW_NAMES):
        unit = units if i == 0 else f"{units}/g"
        table.add_row(f"{row} ({unit})", *(with_standard_error(fit.coefficients[i, j], se[i, j])
                                           for j in range(len(fit.sensors))))
    table.add_row(f"S_E ({units})", *(f"{s:.3g}" for s in fit.ls.residual_se))
    basis = "; ".join(sorted({f"{b} ({d} df)" for b, d in zip(fit.variance_basis, fit.variance_dof,
                                                                  strict=True)}))
    table.caption = f"{fit.ls.n_obs} points; ± is one standard error (k=1), from the {basis}"
    return table


def extension_terms(fit: Fit) -> Table | None:
    """The fitted extension coefficients (temperature, harmonics) ± one standard error, or None."""
    n_base = len(ROW_NAMES)
    if len(fit.names) == n_base:
        return None
    table = Table(title=f"Extension terms (t_ref = {fit.model.t_ref:.2f} °C), ± u (k=1)", box=box.SIMPLE_HEAD,
                  pad_edge=False)
    table.add_column("term")
    for name in fit.sensors:
        table.add_column(f"sensor {name}", justify="right")
    se = fit.stderr
    for i, term in enumerate(fit.names[n_base:], start=n_base):
        unit = {"dB/dT": "V/°C"}.get(term, "V/(g·°C)" if term.startswith("dS") else "V")
        table.add_row(f"{term} ({unit})",
                      *(with_standard_error(fit.ls.coef[i, j], se[i, j]) for j in range(len(fit.sensors))))
    return table


def device_tables(doc: dict) -> list[Table]:
    """The device fit (its JSON document) for the terminal: misalignments ± U, X ± one standard
    error, and the instrument's intrinsic parameters."""
    k = doc["coverage_factor_95"]
    mis = Table(title="Calibration-device misalignments (Soto Table 1)")
    for col in ("", "value (″)", f"U95 (″, k = {k:.3g})"):
        mis.add_column(col, justify="right")
    for name, m in doc["misalignments"].items():
        mis.add_row(name, f"{m['value_arcsec']:+.2f}", f"{m['U_arcsec']:.2f}")
    ident = doc["identifiability"]
    mis.caption = f"rank {ident['rank']} of {ident['parameters']}, condition {ident['condition']:.3g}"
    coef = Table(title="Fitted coefficients X = [Bᵀ; S], device model")
    coef.add_column("row")
    for name in SENSORS:
        coef.add_column(f"sensor {name}", justify="right")
    X, se = np.array(doc["coefficients"]), np.array(doc["standard_errors"])
    units = doc.get("units", "V")
    for i, row in enumerate(ROW_NAMES):
        unit = units if i == 0 else f"{units}/g"
        coef.add_row(f"{row} ({unit})", *(f"{X[i, j]:+.9f} ± {se[i, j]:.2g}" for j in range(3)))
    coef.add_row(f"S_E ({units})", *(f"{s:.3g}" for s in doc["residual_standard_error"]))
    coef.add_row(f"S_E linear ({units})", *(f"{s:.3g}" for s in doc["residual_standard_error_linear"]))
    coef.caption = (f"{doc['n_points']} points; ± is one standard error ({doc['degrees_of_freedom']} df), "
                    "the misalignments' uncertainty included")
    intrinsic = Table(title="Intrinsic parameters (independent of the mount)")
    for col in ("", "value", "u"):
        intrinsic.add_column(col, justify="right")
    for s, v in doc["intrinsic"]["sensitivity_v_per_g"].items():
        intrinsic.add_row(f"|s_{s}| ({units}/g)", f"{v['value']:.9f}", f"{v['u']:.2g}")
    for pair, v in doc["intrinsic"]["inter_axis_angle_deg"].items():
        intrinsic.add_row(f"angle {pair} − 90° (″)", f"{v['deviation_from_90_arcsec']:+.2f}",
                          f"{v['u_arcsec']:.2g}")
    return [mis, coef, intrinsic]


CHECK_MARKS = {"ok": "[green]ok[/]", "warning": "[yellow]warning[/]", "fail": "[bold red]FAIL[/]"}


def print_checklist(console: Console, items: Iterable[Item]) -> None:
    """The pre-run checklist (`labcal.bench.checklist`), one line per item."""
    console.print("[bold]Pre-run checklist[/] (nothing moves):")
    for item in items:
        console.print(f"  {CHECK_MARKS[item.status]} {item.name}: {escape(item.why)}")


def power_on_given(args: argparse.Namespace, now: datetime) -> PowerOn:
    """What the command line says of the instrument's power (`labcal.bench.checklist.PowerOn`)."""
    at = None if args.powered_on is None else checklist.parse_power_on(args.powered_on, now)
    return checklist.PowerOn(at, args.warmed_up)


def before_run(args: argparse.Namespace, bench: Bench | None, station: Station, points: int,
               samples: int) -> Checklist:
    """The pre-run checklist of `labcal run`, shown before anything moves. An unmet item stops the
    run in one line (exit 2, nothing moved) unless the operator, asked at the terminal, says to go
    on; with --yes or --answers nobody is asked. Where the station asks for a warm-up and the
    command line did not say when the instrument was switched on, the operator at the terminal is
    asked. Returns what the run journals of it (its metadata: run.json, the manifest)."""
    now = datetime.now().astimezone()
    power = power_on_given(args, now)
    config = None if bench is None else bench.config
    attended = not (args.yes or args.answers)
    if attended and config is not None and config.instrument.warm_up_min and power == checklist.PowerOn():
        while True:  # a typo is asked again; an empty answer (or none) leaves it unsaid
            try:
                text = err.input(f"The instrument needs {config.instrument.warm_up_min:g} min of warm-up: "
                                 "when was it switched on? (HH:MM, 'warm' if it has warmed up): ").strip()
            except EOFError:
                text = ""
            if text.lower() in ("", "warm"):
                power = checklist.PowerOn(warmed_up=text.lower() == "warm")
                break
            try:
                power = checklist.PowerOn(checklist.parse_power_on(text, now, "the answer"))
                break
            except LabcalError as exc:
                err.print(f"[yellow]{exc}[/]")
    items = checklist.run_checklist(
        config,
        bench,
        station,
        db=db_path(args.db),
        run_folder=Path(args.out or "runs"),
        points=points,
        samples=samples,
        power=power,
        now=now,
        server=lab_server(args.db),
    )
    print_checklist(err, items)
    failed = checklist.unmet(items)
    if not failed:
        return checklist.journaled(items, power)
    names = ", ".join(i.name for i in failed)
    if attended:
        try:
            go_on = err.input(f"{len(failed)} item(s) not met ({names}). Go on anyway? (y/N) ")
            go_on = go_on.strip().lower()
        except EOFError:
            go_on = ""
        if go_on in ("y", "yes"):
            return checklist.journaled(items, power, went_on_regardless=True)
    raise checklist.refusal(failed)

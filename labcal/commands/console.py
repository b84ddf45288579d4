"""Terminal output: the run's progress bar and the tables people read."""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table

from labcal.analysis.fit import ROW_NAMES, SENSORS, Fit
from labcal.run.sequencer import Display, Step


def format_duration(seconds: float) -> str:
    seconds = int(round(seconds))
    h, rem = divmod(seconds, 3600)
    m, s = divmod(rem, 60)
    return f"{h} h {m:02d} min {s:02d} s" if h else f"{m} min {s:02d} s"


class ProgressDisplay(Display):
    """A rich progress bar with ETA and a live line of the last reading and station time."""

    def __init__(self, console: Console, total: int, step_estimates: dict[int, float] | None = None,
                 done: int = 0):
        self.progress = Progress(
            TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), TextColumn("rig ETA {task.fields[rig_eta]}"),
            TextColumn("{task.fields[last]}"), console=console, transient=False,
        )
        self.estimates = step_estimates or {}
        self.after: dict[int, float] = {}  # rig time of the steps after each one: an O(1) ETA per point
        remaining = sum(self.estimates.values())
        for seq in sorted(self.estimates):
            remaining -= self.estimates[seq]
            self.after[seq] = remaining
        self.task = self.progress.add_task("calibrating", total=total, completed=done, last="",
                                           rig_eta=format_duration(sum(self.estimates.values())))

    def __enter__(self) -> ProgressDisplay:
        self.progress.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.progress.stop()

    @contextmanager
    def pause(self):
        self.progress.stop()
        try:
            yield
        finally:
            self.progress.start()

    def point_done(self, step: Step, volts: np.ndarray, station_time_s: float, settle_s: float) -> None:
        last = f"p={step.pitch_deg:g}° r={step.roll_deg:g}° settled in {settle_s:.1f} s"
        remaining = self.after.get(step.seq, 0.0)
        self.progress.update(self.task, advance=1, last=last, rig_eta=format_duration(remaining))

    def message(self, text: str) -> None:
        self.progress.console.print(text)


def coefficients_with_standard_errors(fit: Fit, title: str = "Fitted coefficients X = [Bᵀ; S]") -> Table:
    """The fit's coefficients ± one standard error, for the terminal (the certificate's table,
    `labcal.documents.report.coefficients_with_expanded_uncertainty`, states ± U95 instead)."""
    table = Table(title=title)
    table.add_column("row")
    for name in SENSORS:
        table.add_column(f"sensor {name}", justify="right")
    se = fit.stderr
    for i, row in enumerate(ROW_NAMES):
        unit = "V" if i == 0 else "V/g"
        table.add_row(f"{row} ({unit})", *(
            f"{fit.coefficients[i, j]:+.9f} ± {se[i, j]:.2g}" if np.isfinite(se[i, j])
            else f"{fit.coefficients[i, j]:+.9f}" for j in range(3)))
    table.add_row("S_E (V)", *(f"{s:.3g}" for s in fit.ls.residual_se))
    basis = "; ".join(sorted({f"{b} ({d} df)" for b, d in zip(fit.variance_basis, fit.variance_dof,
                                                                  strict=True)}))
    table.caption = f"{fit.ls.n_obs} points; ± is one standard error, from the {basis}"
    return table

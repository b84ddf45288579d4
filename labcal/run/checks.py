"""A run's readings judged before any certificate, as `labcal fit` judges a readings file.

The same checks, by the same functions: the gross-error checks of the fit (|g| = 1, each reading
against its mount, studentised residuals: `labcal.analysis.gross_errors.fit_flags`) on the fit the
run's exports make (`labcal.store.exports.run_fits`), and the residual against what the run's station
declares of its scatter (`labcal.analysis.declared_noise`). A reading that fails is named by its
point; the sequencer measures those points once more, and a run whose readings still fail issues no
certificate.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from labcal.analysis.declared_noise import (
    NO_ANGLE_ERRORS,
    NOISE_ALPHA,
    RECTANGULAR,
    Declared,
    NoiseCheck,
    noise_check,
)
from labcal.analysis.gross_errors import SENSORS, Flag, fit_flags, implausible_volts, t_threshold
from labcal.analysis.kinematics import ARCSEC
from labcal.analysis.readings import Readings
from labcal.config.settings import SettleSettings
from labcal.config.snapshot import (
    StationFileSnapshot,
    StationSnapshot,
    stated_angle_errors,
    stated_mount_repeatability,
)
from labcal.store.exports import run_fits

IN_POSITION_ARCSEC = 5.0  # a table's default read-back tolerance (the station file's in_position_arcsec)


@dataclass(frozen=True)
class Verdict:
    """What the checks found: every flag (rows 1-based, in the readings' order), the declared-noise
    test (None where it could not be made, with ``note`` saying why)."""

    flags: tuple[Flag, ...]
    noise: NoiseCheck | None
    note: str = ""

    @property
    def passed(self) -> bool:
        return not self.flags and (self.noise is None or self.noise.passed)

    @property
    def rows(self) -> list[int]:
        """The readings (1-based) some check names, in order."""
        return sorted({f.row for f in self.flags})

    def summary(self, units: str = "V") -> str:
        """One line: what failed, first finding first."""
        parts = []
        if self.noise is not None and not self.noise.passed:
            parts.append(self.noise.summary(units))
        gross = [f for f in self.flags if f.check != "noise"]
        if gross:
            f = gross[0]
            parts.append(f.message if f.check == "mount" else f"reading {f.row}: {f.message}")
        return "; ".join(parts)


def declared_of(settle: SettleSettings, station: StationSnapshot | None) -> Declared | None:
    """What the run's station declares: its settle settings' noise per sample and samples per point
    (as journaled with the run), its tables' stated index and wobble errors; None where it states no
    angle errors (`NO_ANGLE_ERRORS`)."""
    errors = stated_angle_errors(station)
    if errors is None:
        return None
    declared = Declared.of(settle.noise_v, settle.samples, errors)
    seating = stated_mount_repeatability(station)  # each remount seats the plate anew: pitch, roll, yaw
    return declared if not seating else replace(declared, angle_half_widths=(*declared.angle_half_widths,
                                                                                (seating, 3)))


def check_readings(readings: Readings, plan_text: str, station: StationSnapshot | None,
                   settle: SettleSettings) -> Verdict:
    """Every check of ``readings`` (a run's good points, one row each). LabcalError where they cannot
    be fitted at all (too few points): nothing to judge them by."""
    present = ~np.isnan(readings.volts).all(axis=0)  # a package's sensors: the absent ones are all NaN
    implausible_volts(readings.volts[:, present], readings.units)
    fit, _, _ = run_fits(readings, plan_text, station)
    flags = list(fit_flags(readings, fit))
    package = "" if present.all() else (f"the {', '.join(fit.sensors)} sensor(s) of a package were judged by "
                                        "their residuals and the declared noise; |g| = 1 needs three sensors")
    if readings.units != "V":
        units = readings.units
        return Verdict(tuple(flags), None, "; ".join(filter(None, (
            package, f"the noise is declared in volts, the readings are in {units}"))))
    declared = declared_of(settle, station)
    if declared is None:
        return Verdict(tuple(flags), None, "; ".join(filter(None, (package, NO_ANGLE_ERRORS))))
    noise = noise_check(readings, fit.coefficients[1:], declared)
    seen = {f.row for f in flags}
    flags += [f for f in noise.flags if f.row not in seen]
    return Verdict(tuple(flags), noise, package)


def repeatability_rad(station: StationSnapshot | None) -> tuple[float, float]:
    """What the run's station states of returning to an attitude, as ± half-widths in rad: where a
    table stops (its in-position tolerance; the simulated tables', 5″) and how the plate re-seats
    the instrument at a remount (its mount repeatability, each of pitch, roll and yaw)."""
    if isinstance(station, StationFileSnapshot):
        stated = [station.device(name).in_position_arcsec for name in ("pitch", "roll")]
        stop = max(IN_POSITION_ARCSEC if t is None else t for t in stated) * ARCSEC
        return stop, float(station.section().uncertainty.mount_repeatability)
    return IN_POSITION_ARCSEC * ARCSEC, stated_mount_repeatability(station)  # the rig's, as a half-width


def closure(before: tuple[list[float], int], after: tuple[list[float], int], settle: SettleSettings,
            station: StationSnapshot | None, remounted: bool, alpha: float = NOISE_ALPHA) -> str | None:
    """Why the rig is not where it was when a reading (``before``: mean volts and samples) was taken
    at the same attitude as ``after`` (None: it is). The difference of the two scatters by the
    DMM's noise of both, both tables' stops (rectangular, GUM 4.3.7) and, across a remount, the
    plate's seating of each of three angles; a rotation by θ moves a sensor's output by at most
    |S|·θ (|S| the settle settings' sensitivity). The tables' index errors are the same at the same
    angle and cancel. A table or coupling that slipped since moves it by |S|·slip."""
    (v0, n0), (v1, n1) = before, after
    stop, seat = repeatability_rad(station)
    noise_v, reach = settle.noise_v, settle.sensitivity_v_per_g
    angle_var = 4 * (stop * RECTANGULAR) ** 2 + (6 * (seat * RECTANGULAR) ** 2 if remounted else 0.0)
    sd = float(np.sqrt(noise_v**2 / n0 + noise_v**2 / n1 + reach**2 * angle_var))
    diff = np.asarray(v1, dtype=float) - np.asarray(v0, dtype=float)
    limit = t_threshold(3, np.inf, alpha)
    j = int(np.nanargmax(np.abs(diff)))  # a package's absent sensors (NaN) are passed over
    if not abs(diff[j]) > limit * sd:
        return None
    return (f"sensor {SENSORS[j]} reads {diff[j] * 1e3:+.3g} mV otherwise ({abs(diff[j]) / sd:.3g} times "
            f"the scatter the station declares for a return, limit {limit:.3g})")

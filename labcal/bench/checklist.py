"""The pre-run checklist: what must hold before a calibration moves anything, asked of the station
itself. `labcal run` shows it before the tables are homed (an unmet item stops the run, nothing
moved, unless the operator says to go on) and `labcal station check` runs it.

Each item is ok, warning or fail, with one line saying what was found and what to do:

- warm-up: the instrument's time since power-on against the station's ``[instrument]
  warm_up_min`` (the technician says when it was switched on, or that it has warmed up);
- reference standards: none overdue (`labcal.config.uncertainty.overdue_standards`, the function
  the certificate uses, so the two never disagree);
- tables homed: each table's controller says whether it is referenced (SMC100 ``TS``: READY from
  HOMING, or NOT REFERENCED, hardware_protocols.md §2.2; an AZ drive has an absolute encoder and
  says only whether an alarm such as 4Ah "return-to-home incomplete" is on, §2.1);
- DMM: it identifies itself, takes the declared configuration and reads it back (the driver's
  verification); the manual's excerpt (hardware_protocols.md §3.1) documents no self-test query,
  so ``*TST?`` is not sent;
- free disk: the journal's folder and the run folder against an estimate of what the run writes;
- lab database: opened as a run opens it (`labcal.store.labdb.connect`), its one-line error if not.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import date, datetime, timedelta
from pathlib import Path
from typing import TYPE_CHECKING, Literal

from labcal.config.files import size_text
from labcal.config.run_metadata import Checklist, ChecklistItem
from labcal.config.uncertainty import overdue_standards
from labcal.drivers.errors import DriverError
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.store.labdb import Unreachable, connect, open_server

if TYPE_CHECKING:
    from labcal.bench.hardware import Bench
    from labcal.config.lab import ServerDatabase
    from labcal.config.station import InstrumentSettings, StationFile
    from labcal.config.uncertainty import Traceability
    from labcal.devices.station import Station
    from labcal.drivers import oriental_az
else:
    # the drivers (pymodbus) only for a bench: a simulated run loads none of them
    oriental_az = lazy("labcal.drivers.oriental_az")

Status = Literal["ok", "warning", "fail"]
CHANNELS_STORED = 4  # x, y, z and temperature: the most a point's raw samples hold
BYTES_PER_SAMPLE = 8  # each raw sample is a little-endian double in the journal
# A point's row, its events (move, settle verdict, retries) and SQLite's indexes and write-ahead log,
# beside its raw samples; and each try of a point that is retried keeps its samples too
POINT_OVERHEAD_B = 4_000  # measured: 3.2 kB a point in all, raw samples included (64 points, 10 samples)
TRIES_ALLOWED = 3
READINGS_ROW_B = 300  # a readings.csv row with its audit columns
# fit.json, run.json, plan.toml, the certificate, its DCC and the report (HTML and PDF with figures):
# 2.0 MB for Soto's 64 points on the simulated rig (measured), with room for longer plans' figures
RUN_FOLDER_FIXED_B = 5_000_000
MARGIN = 2.0  # free space below this multiple of the estimate is a warning: other runs share the disk


@dataclass(frozen=True)
class Item:
    """One line of the checklist."""

    name: str
    status: Status
    why: str  # what was found, and what to do when it is not ok

    def to_json(self) -> dict[str, str]:
        return {"item": self.name, "status": self.status, "message": self.why}


@dataclass(frozen=True)
class PowerOn:
    """What the technician said about the instrument's power: when it was switched on, or that it
    has warmed up (left on overnight, say). Neither: nobody said."""

    at: datetime | None = None
    warmed_up: bool = False


def parse_power_on(text: str, now: datetime, where: str = "--powered-on") -> datetime:
    """"14:05" (today) or "2026-11-25 23:30", local time, as aware as ``now``; a time after ``now``
    is one line (it was switched on earlier than that)."""
    text = text.strip()
    try:
        if len(text) <= 5:
            clock = datetime.strptime(text, "%H:%M")
            at = now.replace(hour=clock.hour, minute=clock.minute, second=0, microsecond=0)
        else:
            at = datetime.strptime(text.replace("T", " "), "%Y-%m-%d %H:%M").replace(tzinfo=now.tzinfo)
    except ValueError:
        raise LabcalError(f"{where}: {text!r} is not a time; give HH:MM (today) or YYYY-MM-DD HH:MM"
                          ) from None
    if at > now:
        raise LabcalError(f"{where}: {text} is later than now ({now:%H:%M}); give when the instrument was "
                          "switched on, with its date if that was another day (YYYY-MM-DD HH:MM)")
    return at


def warm_up(instrument: InstrumentSettings | None, power: PowerOn, now: datetime,
            unsaid: Status = "fail") -> Item:
    """The instrument's warm-up, where the station declares one (``unsaid``: the verdict when nobody
    said when it was switched on: a run is refused, `labcal station check` warns)."""
    name = "warm-up"
    wanted = None if instrument is None else instrument.warm_up_min
    if wanted is None:
        return Item(name, "ok", "the station declares no warm-up time ([instrument] warm_up_min)")
    if power.warmed_up:
        return Item(name, "ok", f"warmed up, as the operator stated ({wanted:g} min asked)")
    if power.at is None:
        return Item(name, unsaid, f"the station asks {wanted:g} min after power-on and nobody said when the "
                                  "instrument was switched on: give --powered-on HH:MM, or --warmed-up")
    on_for = (now - power.at).total_seconds() / 60.0
    if on_for >= wanted:
        return Item(name, "ok", f"powered on at {power.at:%H:%M}, {on_for:.0f} min ago "
                                f"({wanted:g} min asked)")
    ready = power.at + timedelta(minutes=wanted)
    return Item(name, "fail", f"powered on at {power.at:%H:%M}, only {on_for:.0f} min ago; the station asks "
                              f"{wanted:g} min: wait until {ready:%H:%M}, or go on with --warmed-up")


def standards(traceability: Iterable[Traceability] | None, today: date) -> Item:
    """Reference standards in date, by the certificate's own rule."""
    name = "reference standards"
    if traceability is None:
        return Item(name, "ok", "simulated rig: no reference standards")
    listed = list(traceability)
    if not listed:
        return Item(name, "warning", "the station names no reference standards ([[traceability]]): the "
                                     "certificate will state none; add the DMM's and the tables' "
                                     "certificates")
    overdue = overdue_standards(listed, today, today=True)
    if overdue:
        more = f" (and {len(overdue) - 1} more)" if len(overdue) > 1 else ""
        return Item(name, "warning", f"{overdue[0]}{more} The certificate will say so on page 1; have it "
                                     "recalibrated, or update [[traceability]] in the station file")
    due = min(t.due for t in listed)
    return Item(name, "ok", f"{len(listed)} in date (next due {due:%Y-%m-%d})")


def tables_homed(bench: Bench | None, station: Station | None) -> Item:
    """Each table's referenced state, as its controller reports it. A table the run homes first
    (NOT REFERENCED, no error) is a warning: homing moves it to its home switch."""
    name = "tables homed"
    if bench is None:
        if station is None:
            raise ValueError("tables_homed needs a bench or a station")
        faults = [s.fault for s in (station.pitch.state(), station.roll.state()) if s.fault]
        if faults:
            return Item(name, "fail", "; ".join(faults))
        return Item(name, "ok", "simulated tables: homed")
    found: list[tuple[Status, str]] = []
    for axis in bench.axes:
        try:
            status = axis.status()
        except DriverError as exc:
            found.append(("fail", f"{axis.name}: no status ({exc})"))
            continue
        if status.needs_homing:
            found.append(("warning", f"{axis.name}: {status.words}"))
        elif status.fault:
            found.append(("fail", f"{axis.name}: {status.fault}"))
        elif not status.ready and not status.moving:  # an AZ drive whose STOP input a lost release left on
            why = axis.not_ready_why() or "; it would start no move"
            found.append(("fail", f"{axis.name}: {status.words}{why}"))
        elif isinstance(axis, oriental_az.AzAxis):
            found.append(("ok", f"{axis.name}: {status.words}, absolute encoder, no alarm"))
        else:
            found.append(("ok", f"{axis.name}: {status.words}"))
    worst: Status = "fail" if any(s == "fail" for s, _ in found) else \
        "warning" if any(s == "warning" for s, _ in found) else "ok"
    homes = " (the run homes a table NOT REFERENCED first: it moves to its home switch, so keep the " \
        "instrument clear)" if worst == "warning" else ""
    return Item(name, worst, "; ".join(line for _, line in found) + homes)


def dmm(bench: Bench | None) -> Item:
    """The DMM identifies itself and holds the declared configuration, read back."""
    name = "DMM"
    if bench is None:
        return Item(name, "ok", "simulated DMM: nothing to test")
    d = bench.dmm
    try:
        identity = d.identify()
        d.configure()  # sends the declared configuration and reads every setting back
    except DriverError as exc:
        return Item(name, "fail", str(exc))  # the driver's line says what to check
    channels = ",".join(str(c) for c in d.channels)
    maker, model, serial = (field.strip() for field in identity.split(",")[:3])
    return Item(name, "ok", f"{maker} {model} serial {serial} configured and read back as declared "
                            f"({d.range_v:g} V range, {d.nplc:g} PLC, channels {channels})")


def bytes_needed(points: int, samples: int) -> tuple[int, int]:
    """What a run of ``points`` points of ``samples`` samples writes: into the journal, into its folder
    (an upper estimate: every point tried `TRIES_ALLOWED` times, every channel stored)."""
    journal = points * TRIES_ALLOWED * (samples * CHANNELS_STORED * BYTES_PER_SAMPLE + POINT_OVERHEAD_B)
    return journal, points * READINGS_ROW_B + RUN_FOLDER_FIXED_B


def existing(path: Path) -> Path:
    """The nearest folder of ``path`` that exists (a run folder is made when the run starts)."""
    path = path.absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path if path.is_dir() else path.parent


def free_disk(journal_folder: Path, run_folder: Path, points: int, samples: int) -> Item:
    """Free space where the run writes, against the estimate (folders on one disk add up)."""
    journal_b, folder_b = bytes_needed(points, samples)
    wants: dict[int, tuple[Path, int]] = {}
    for folder, need in ((existing(journal_folder), journal_b), (existing(run_folder), folder_b)):
        device = folder.stat().st_dev
        where, before = wants.get(device, (folder, 0))
        wants[device] = (where, before + need)
    lines, worst = [], "ok"
    for where, need in wants.values():
        free = shutil.disk_usage(where).free
        lines.append(f"{size_text(free)} free in {where}, the run needs about {size_text(need)}")
        if free < need:
            worst = "fail"
        elif free < MARGIN * need and worst == "ok":
            worst = "warning"
    what = {"fail": "; free space there before the run", "warning": "; little to spare: free some space",
            "ok": ""}[worst]
    return Item("free disk", worst, "; ".join(lines) + f" ({points} points){what}")  # type: ignore[arg-type]


def lab_database(path: Path, server: ServerDatabase | None = None) -> Item:
    """The journal opens as a run opens it; the lab's server, where there is one, answers at this
    labcal's schema. A server that cannot be reached is a warning, not a failure: a run never waits
    for it (its records stay in the journal and are sent when it is back)."""
    try:
        connect(path).close()
    except LabcalError as exc:
        return Item("lab database", "fail", str(exc))
    if server is None:
        return Item("lab database", "ok", f"{path} opens")
    try:
        open_server(server).dispose()
    except Unreachable as exc:
        return Item("lab database", "warning", f"{exc}; the run would measure into {path} and send its "
                                               "records when the server is back (or with labcal sync)")
    except LabcalError as exc:
        return Item("lab database", "fail", str(exc))
    return Item("lab database", "ok", f"{server} answers; this station journals into {path}")


def run_checklist(config: StationFile | None, bench: Bench | None, station: Station | None, *, db: Path,
                  run_folder: Path, points: int, samples: int, power: PowerOn, now: datetime,
                  unsaid: Status = "fail", server: ServerDatabase | None = None) -> list[Item]:
    """Every item, for a station file's bench (``config``, ``bench``) or the simulated rig (``station``).
    Nothing moves."""
    return [
        warm_up(None if config is None else config.instrument, power, now, unsaid),
        standards(None if config is None else config.traceability, now.date()),
        tables_homed(bench, station),
        dmm(bench),
        free_disk(db.parent, run_folder, points, samples),
        lab_database(db, server),
    ]


def unmet(items: Iterable[Item]) -> list[Item]:
    return [item for item in items if item.status == "fail"]


def journaled(items: Iterable[Item], power: PowerOn, went_on_regardless: bool = False) -> Checklist:
    """The checklist as the run journals it in its metadata: each item, whether the operator went
    on past an unmet one, and what was said of the instrument's power."""
    return Checklist(items=[ChecklistItem(item=i.name, status=i.status, message=i.why) for i in items],
                     went_on_regardless=went_on_regardless,
                     powered_on=None if power.at is None else power.at.isoformat(timespec="minutes"),
                     warmed_up_stated=power.warmed_up)


def refusal(failed: list[Item]) -> LabcalError:
    """The one line a run is refused with when items are not met and nobody said to go on."""
    return LabcalError(f"pre-run checklist: {failed[0].name}: {failed[0].why}"
                       + (f" (and {len(failed) - 1} more item(s) not met)" if len(failed) > 1 else "")
                       + "; nothing was moved")

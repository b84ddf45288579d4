"""The lab at a glance (`/`): every bench the lab knows, with its state in one word and what a person
walking the lab needs from it, and the latest runs; pure reads.

A bench is known by its runs (the station each journaled under) and, on a PostgreSQL lab database,
by its role (`labcal db grant-station NAME`, the ``station_roles`` table): a bench granted its role
shows, idle, before its first run. Each bench's state is a replay of its current run's journal
(`labcal.app.station_state`): the current run is the one running (the newest, if several), else its
newest.

A run is shown in the same words wherever it is listed (`run_state`): one the journal says is
running is what the replay of its journal makes of it (running, waiting for a person, paused on a
fault, not heard from: a killed bench's run still says "running" in the journal), any other by the
status the journal closed it with (complete, stopped, failed, …).
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from labcal.app.lab import RUNNING, RunJson, _json, _list_runs, _progress
from labcal.app.labdatabase import LabDatabase
from labcal.app.station_state import (
    LABELS,
    PACE_POINTS,
    TIMELINE_KINDS,
    Heard,
    Silence,
    State,
    StationView,
    mount_angles,
    replay,
)
from labcal.store import lab_view

if TYPE_CHECKING:
    from labcal.store.handles import Connection

UNNAMED = "(unnamed station)"


@dataclass(frozen=True)
class Overview:
    """The lab at a glance: each bench with its state and current run, and the latest runs."""

    stations: tuple[dict, ...]  # see `station_json`, in name order
    runs: tuple[RunJson, ...]  # newest first, each with its ``state`` and ``state_label`` (`run_state`)
    as_of_utc: str  # when it was read: what every "since" and "for" on the page is counted to


def lab_overview(lab: LabDatabase, silence: Silence | None = None, latest: int = 50) -> Overview:
    """Every bench the lab knows with its state and current run, and the ``latest`` runs."""
    now, silence = datetime.now(UTC), silence or Silence()
    with lab.engine.connect() as conn:
        listed = _list_runs(conn)
        current: dict[str, dict | None] = {name: None for name in _registered(conn)}
        for run in listed:  # newest first
            name = run["station"] or UNNAMED
            held = current.get(name)
            if held is None or (held["status"] != RUNNING and run["status"] == RUNNING):
                current[name] = run
        stations = tuple(_station(conn, name, run, now, silence) for name, run in sorted(current.items()))
        replayed = {s["run"]["id"]: s["state"] for s in stations if s["run"] is not None}
        shown = tuple(_with_state(conn, r, replayed.get(r["id"]), now, silence) for r in listed[:latest])
    return Overview(stations, shown, now.isoformat(timespec="milliseconds"))


def run_state(lab: LabDatabase, run: RunJson, silence: Silence | None = None) -> dict[str, str]:
    """The run's state as the overview states it (its ``state`` and ``state_label``): see the module."""
    with lab.engine.connect() as conn:
        return _state(conn, run, None, datetime.now(UTC), silence or Silence())


def _state(conn: Connection, run: RunJson, replayed: str | None, now: datetime, silence: Silence
           ) -> dict[str, str]:
    if run["status"] != RUNNING:
        return {"state": run["status"], "state_label": run["status"]}
    state = State(replayed) if replayed is not None else _replayed(conn, run, now, silence)[1].state
    return {"state": state.value, "state_label": LABELS[state]}


def _with_state(conn: Connection, run: RunJson, replayed: str | None, now: datetime, silence: Silence
                ) -> RunJson:
    return {**run, **_state(conn, run, replayed, now, silence)}


def _registered(conn: Connection) -> list[str]:
    """The benches granted a role of their own (none on SQLite, where nothing grants one)."""
    return lab_view.registered_stations(conn)


def _station(conn: Connection, name: str, run: dict | None, now: datetime, silence: Silence) -> dict:
    if run is None:
        return station_json(name, None, replay(None, (), now, silence), now)
    return station_json(name, *_replayed(conn, run, now, silence), now)


def _replayed(conn: Connection, run: RunJson, now: datetime, silence: Silence) -> tuple[RunJson, StationView]:
    """The run with where it stands (its progress, while running), and the replay of its journal."""
    progress = _progress(conn, run["id"]) if run["status"] == RUNNING else None
    shown = progress or run
    view = replay(run["status"], timeline(conn, run["id"]), now, silence,
                  eta_rig_s=shown.get("eta_s"), remount_rig_s=shown.get("next_remount_in_s"),
                  last_heard=_utc(shown.get("last_heard_utc")))
    return shown, view


def timeline(conn: Connection, run_id: int) -> list[Heard]:
    """What the replay reads of a run: its events of `TIMELINE_KINDS` and its latest points, in the
    order journaled (the two tables' UTC stamps, which one clock wrote)."""
    heard, latest = lab_view.timeline_rows(conn, run_id, TIMELINE_KINDS, PACE_POINTS)
    found = [Heard(_utc(r.utc), r.kind, r.message, _dict(_json(r.data))) for r in heard]
    found += [Heard(_utc(r.utc), "point", data={"t_end": r.t_end, "y_deg": r.y_deg, "u_deg": r.u_deg})
              for r in latest]
    return sorted(found, key=lambda heard: heard.utc)  # stable: each table's own order among equal stamps


def station_json(name: str, run: RunJson | None, view: StationView, now: datetime) -> dict:
    """A bench as the overview states it (times in UTC, ISO 8601; durations in wall seconds)."""
    fault, waiting = view.fault, view.waiting
    return {"station": name, "run": run, "state": view.state.value, "label": view.label,
            "waiting": None if waiting is None else {"utc": _iso(waiting.utc), "text": waiting.text,
                                                     "for_s": view.waited_s(now)},
            "mount": mount_angles(view.mount),
            "fault": None if fault is None else {"utc": _iso(fault.utc), "message": fault.message,
                                                 "cleared_utc": _iso(fault.cleared_utc)},
            "last_heard_utc": _iso(view.last_heard), "silent_s": view.silent_s(now),
            "silent_after_s": view.silent_after_s, "interval_s": view.interval_s,
            "done_at_utc": _iso(view.done_at), "next_remount_utc": _iso(view.next_remount_at)}


def _utc(text: str | None) -> Any:
    if not text:
        return None
    found = datetime.fromisoformat(text)
    return found if found.tzinfo is not None else found.replace(tzinfo=UTC)


def _iso(when: datetime | None) -> str | None:
    return None if when is None else when.astimezone(UTC).isoformat(timespec="milliseconds")


def _dict(found: Any) -> dict | None:
    return found if isinstance(found, dict) else None

"""Model settling's pool of step records, kept per instrument and station across runs.

The settling model needs a hundred-odd step records before it can rule out a slow tail
(`labcal.run.settle.TailPool`), so a 64-point run never got there. The pool's sums are the
instrument's, not the run's: kept in the lab database (table ``settle_pools``, migration 4 of
`labcal.store.labdb`), a run starts with the records of the runs before it.

Which runs share a pool is its key, the SHA-256 of a canonical identity:
- the instrument: its serial (``pool = "instrument"``, the default) or the station's
  ``instrument_type`` (``pool = "type"``); a simulated or emulated instrument is also its simulated
  truth (time constant, noise, coefficients…: the rig file's ``[instrument]``), because every dry
  run is serial SIMULATED and two rig files are two instruments. The seed is not the instrument: it
  draws the noise, the device's index errors and the mount errors of a run;
- the station: the devices as the station file describes them, links aside (a port may move), and
  the identities they answered with (serial numbers); for a simulated rig, the rig file less its
  instrument and seed;
- what the sums are made on: the configured τ and σ (the τ grid and the noise scale) and the
  pool's layout version.
A changed instrument or station is therefore another pool, which starts empty: it never biases a
point. An instrument that changed under its key (a repaired sensor) is caught by the pool itself
(`TailPool`: this run's records against the history's).

The same seed draws the same noise for the same point: a new dry run repeating a seed that the pool
already holds would count one noise realisation twice, so it starts without the history (and adds
nothing to it). A resumed run goes on with the pool it saved at its pause.
"""

from __future__ import annotations

import hashlib
import io
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from labcal.config.run_metadata import parse_run_metadata
from labcal.config.settings import SettleSettings
from labcal.config.snapshot import SimulatedRigSnapshot, StationFileSnapshot, parse_snapshot
from labcal.config.station import LinkSettings
from labcal.run.settle import SLOW, TAU_GRID, TAU_RANGE, PoolState, TailPool
from labcal.store import settle_pools
from labcal.store.journal import RunRow
from labcal.store.settle_pools import PoolRow

if TYPE_CHECKING:
    from labcal.store.handles import SQLiteConnection

LAYOUT = f"tailpool/1 grid={TAU_GRID} range={TAU_RANGE[0]:g}-{TAU_RANGE[1]:g} slow={SLOW:g}"
LINK_FIELDS = frozenset(LinkSettings.model_fields) | {"visa", "visa_library"}


@dataclass(frozen=True)
class PoolKey:
    key: str  # SHA-256 of the identity's canonical JSON
    identity: dict
    run: str  # the run's uuid (or id): a resumed run is the same source
    noise: str | None  # what draws a dry run's noise (its seed); None on real hardware


def pool_key(row: RunRow, settle: SettleSettings) -> PoolKey | None:
    """Whose pool a run shares (module docstring); None when the station pools nothing across runs."""
    if settle.pool == "none":
        return None
    instrument: dict[str, object] = ({"type": settle.instrument_type} if settle.pool == "type"
                                     else {"serial": row.instrument_serial or "SIMULATED"})
    return _key(row, settle, instrument, True)


def prior_key(row: RunRow, settle: SettleSettings) -> PoolKey | None:
    """Where the records of every instrument of the run's type on its station (``prior = "type"``)
    or of every instrument on it (``"station"``) are summed; None without a prior. A simulated
    instrument's truth is left out: the prior is across instruments."""
    if settle.prior == "none":
        return None
    whose = {"type": settle.instrument_type} if settle.prior == "type" else {"station": "every instrument"}
    prior: dict[str, object] = {"prior": whose}
    return _key(row, settle, prior, False)


def _key(row: RunRow, settle: SettleSettings, instrument: dict[str, object], with_truth: bool) -> PoolKey:
    snapshot = parse_snapshot(row.station_text)
    truth: object = None
    noise: str | None = None
    station: dict[str, object]
    if isinstance(snapshot, SimulatedRigSnapshot):
        rig = dict(snapshot.rig)
        truth = rig.pop("instrument", None)
        rig.pop("seed", None)
        station = {"simulated rig": rig}
        noise = f"seed {snapshot.seed}"
    elif isinstance(snapshot, StationFileSnapshot):
        described = snapshot.station
        station = {name: {k: v for k, v in (described.get(name) or {}).items() if k not in LINK_FIELDS}
                   for name in ("pitch", "roll", "dmm")}
        station["identities"] = _identities(row)
        emulated = snapshot.simulator_rig()
        if emulated is not None:
            rig = dict(emulated)
            truth = rig.pop("instrument", None)
            rig.pop("seed", None)
            station["emulated rig"] = rig
            noise = f"seed {snapshot.seed}"
    else:  # not a snapshot labcal wrote: the text itself is the station
        station = {"text": row.station_text, "identities": _identities(row)}
    if truth is not None and with_truth:
        instrument["simulated truth"] = truth
    identity = {"instrument": instrument, "station": station,
                "sums": {"layout": LAYOUT, "tau_s": settle.tau_s, "noise_v": settle.noise_v}}
    text = json.dumps(identity, sort_keys=True, separators=(",", ":"), default=str)
    return PoolKey(hashlib.sha256(text.encode()).hexdigest(), identity, row.uuid or str(row.id), noise)


def _identities(row: RunRow) -> dict[str, dict] | None:
    """The devices' identities the run journaled, as the documents it journaled (the pool's key hashes
    their JSON, so it is the same key for every run of the same devices)."""
    said = parse_run_metadata(row.metadata).device_identity
    return None if said is None else {role: found.model_dump(mode="json") for role, found in said.items()}


def _sources(text: str) -> list[dict]:
    return list(json.loads(text))


def load(db: SQLiteConnection, key: PoolKey, whose: str = "this instrument"
         ) -> tuple[PoolState | None, str, bool]:
    """The pool the earlier runs left under ``key`` (None: start empty), one line saying what it
    holds, and whether this run may keep its records there (not when it repeats a seed's noise)."""
    row = settle_pools.read(db, key.key)
    if row is None:
        return None, f"model settling: no earlier runs of {whose} on this station", True
    records, sources, mismatch, blob = row.records, row.sources, row.mismatch, row.sums
    if key.noise is not None and any(s.get("noise") == key.noise and s.get("run") != key.run
                                     for s in _sources(sources)):
        return None, (f"model settling: the records of {whose}'s earlier runs already hold "
                      f"{key.noise}'s noise; this dry run repeats it and starts without them"), False
    sums = np.load(io.BytesIO(blob), allow_pickle=False)
    runs = len({s.get("run") for s in _sources(sources)})
    note = f"model settling starts with {records} step records of {runs} earlier run(s) of {whose}"
    return PoolState(sums, int(records), str(mismatch)), note + (f"; {mismatch}" if mismatch else ""), True


def save(db: SQLiteConnection, key: PoolKey, pool: TailPool) -> None:
    """Keep ``pool`` (the history it started with and this run's records) under ``key``, in one
    transaction; only for a run that `load` allowed to."""
    if pool.own_records == 0:
        return
    state = pool.state()
    buffer = io.BytesIO()
    np.save(buffer, state.sums, allow_pickle=False)

    def kept(row: PoolRow | None) -> PoolRow:
        sources = [s for s in _sources(row.sources) if s.get("run") != key.run] if row else []
        sources.append({"run": key.run, "noise": key.noise})
        return PoolRow(state.records, json.dumps(sources), state.mismatch, buffer.getvalue())

    settle_pools.replace(db, key.key, json.dumps(key.identity, sort_keys=True, default=str), kept)


def load_prior(db: SQLiteConnection, key: PoolKey, whose: str) -> tuple[PoolState | None, str, bool]:
    """`load` for a prior (``key``: `prior_key`). A resumed run finds its own earlier records in the
    prior as well as in its instrument's pool: it goes on without the prior rather than count them
    twice (and still adds what it takes from now on)."""
    row = settle_pools.read(db, key.key)
    if row is not None and any(s.get("run") == key.run for s in _sources(row.sources)):
        return None, f"model settling: {whose} already hold this run's records; it goes on without them", True
    return load(db, key, whose)


def add_to_prior(db: SQLiteConnection, key: PoolKey, pool: TailPool) -> None:
    """Add this run's own records to its type's or station's (``key``: `prior_key`), in one
    transaction; only for a run that `load` allowed to. Every segment of a run adds the records it
    took (a resumed run's pool starts again from its saved history), so none counts twice. A run
    whose pool saw a mismatch adds nothing: its instrument is not one the prior may speak for."""
    own = pool.own_state()
    if own.records == 0 or own.mismatch:
        return

    def added(row: PoolRow | None) -> PoolRow:
        sums, records, sources = own.sums, own.records, [{"run": key.run, "noise": key.noise}]
        if row is not None:
            sums = sums + np.load(io.BytesIO(row.sums), allow_pickle=False)
            records += row.records
            sources = _sources(row.sources) + sources
        buffer = io.BytesIO()
        np.save(buffer, sums, allow_pickle=False)
        return PoolRow(records, json.dumps(sources), row.mismatch if row else "", buffer.getvalue())

    settle_pools.replace(db, key.key, json.dumps(key.identity, sort_keys=True, default=str), added)

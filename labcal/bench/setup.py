"""Stations ready to run: the simulated rig (`--sim`), or a station file's devices through the
drivers, on the emulators it points at with `--emulate`.

These factories are the one production path into `labcal.sim`: everything else drives a station
through the interfaces of `labcal.devices.station` and cannot tell a simulator from hardware. Each
factory also says what the journal keeps of the station (its snapshot), so that `labcal resume`
rebuilds the same one, and the station's pace for the estimates.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from labcal.config import snapshot as config_snapshot
from labcal.config.emulation import RigConfig, load_rig_config
from labcal.config.files import one_line
from labcal.config.snapshot import SimulatedRigSnapshot
from labcal.errors import LabcalError
from labcal.lazy import lazy
from labcal.sim.clock import PacedClock, VirtualClock
from labcal.sim.rig import SimRig

if TYPE_CHECKING:  # the simulator and the drivers are imported where a station of theirs is made
    import pydantic

    from labcal.bench import hardware
    from labcal.bench.hardware import Bench
    from labcal.config import run_metadata
    from labcal.config import settings as config_settings
    from labcal.config import station as config_station
    from labcal.config.emulation import InstrumentTruth
    from labcal.config.run_metadata import RunMetadata
    from labcal.config.settings import SettleSettings
    from labcal.config.snapshot import StationFileSnapshot
    from labcal.config.station import Smc100Settings, StationFile
    from labcal.devices.station import Station
    from labcal.drivers import keysight_34970a, modbus
    from labcal.run import estimate
    from labcal.run.estimate import LinkTiming, Timing
    from labcal.sim import emulation as sim_emulation
else:
    config_settings = lazy("labcal.config.settings")  # start-up without pydantic
    config_station = lazy("labcal.config.station")  # start-up without scipy, numpy, pydantic
    estimate = lazy("labcal.run.estimate")  # start-up without scipy, numpy, pydantic, …
    hardware = lazy("labcal.bench.hardware")  # start-up without scipy, numpy, pydantic, …
    keysight_34970a = lazy("labcal.drivers.keysight_34970a")  # start-up without numpy, serial
    modbus = lazy("labcal.drivers.modbus")  # start-up without numpy, pymodbus, serial
    pydantic = lazy("pydantic")  # start-up without pydantic
    run_metadata = lazy("labcal.config.run_metadata")  # start-up without pydantic
    sim_emulation = lazy("labcal.sim.emulation")  # start-up without scipy, numpy, pydantic, …

REMOUNT_ALLOWANCE_S = 300.0  # the operator's time for one remount, for estimates on real hardware


@dataclass
class StationSetup:
    """A station ready to run, what the journal keeps of it, and its pace for estimates."""

    station: Station
    text: str  # the snapshot the journal keeps; a resume must rebuild the same station from it
    metadata: RunMetadata  # what the run journals of itself; its creator adds to it before the start
    timing: Timing
    settle: SettleSettings


def sim_station(rig_file: str | None, seed: int | None, snapshot: str | None = None,
                start_time_s: float = 0.0, tables_at: tuple[float, float] | None = None,
                pace: float | None = None, package: str | None = None) -> StationSetup:
    """The simulated rig, from a rig file or from a journal snapshot (resume); ``tables_at``: where
    a resumed run's tables were left, accumulated from home (`labcal.devices.winding.left_at`);
    ``pace``: run at that many times real time (None: as fast as it can). The pace is not part of
    the snapshot: it changes how long a run takes on the wall's clock, not what it measures.
    ``package``: the simulated instrument's sensor package instead of the rig file's (it is part of
    the snapshot: a resume reads the same channels)."""
    if snapshot is not None:  # validated by today's model: defaults fill the fields added since
        journaled = SimulatedRigSnapshot.model_validate_json(snapshot)
        config, seed = journaled.rig_config(), journaled.seed
    else:
        config = load_rig_config(rig_file) if rig_file else RigConfig()
        if package is not None:
            config = config.model_copy(update={"instrument": config.instrument.model_copy(
                update={"package": package})})
    clock = VirtualClock(start_time_s) if pace is None else PacedClock(pace, start_time_s)
    rig = SimRig(config, seed=seed, clock=clock)
    if tables_at is not None:
        rig.pitch.place(tables_at[0])
        rig.roll.place(tables_at[1])
    truth = run_metadata.SimulatedTruth(coefficients=rig.instrument.X.tolist(),
                                        misalignment_deg=rig.misalignment.degrees(), seed=rig.seed)
    text = json.dumps({"kind": "simulated rig", "seed": rig.seed, "rig": config.model_dump()}, sort_keys=True)
    timing = estimate.Timing(
        clamp_s=config.clamp_s, sample_s=config.nplc / config.line_hz, remount_s=config.remount_s
    )
    settle = known_settle(config.instrument)
    return StationSetup(rig.station(), text, run_metadata.RunMetadata(simulated_truth=truth), timing, settle)


def known_settle(inst: InstrumentTruth) -> SettleSettings:
    """Settle settings for a simulated or emulated instrument, whose time constant and noise are known."""
    return config_settings.SettleSettings(
        tau_s=inst.tau_s,
        noise_v=max(inst.noise_v, 1e-7),
        sensitivity_v_per_g=float(max(abs(x) for row in inst.S for x in row)),
    )


def links_fixed(config: StationFile, source: str) -> None:
    """Without emulators, a link they would choose (port 0, ``pty:NAME``) reaches nothing: one line."""
    for name, link in config.devices().items():
        if link.chosen_by_emulators:
            raise LabcalError(f"{source}: {name}'s link {link.where} is one the emulators choose as they "
                              "start (any free port, a pty of their own); use {0}, or point a copy of "
                              "the station file at the addresses `labcal sim serve` printed", "emulate")


def station_timing(config: StationFile, time_scale: float = 1.0) -> Timing:
    """A station file's pace for estimates on real hardware: one DMM sweep of its channels per sample,
    the operator's remount allowance (`labcal run --dry-run`, `labcal plan optimize`), its links."""
    dmm = config.dmm
    sweep_s = (len(dmm.channels) + bool(dmm.temperature_channel)) * keysight_34970a.channel_time_s(
        dmm.nplc, dmm.line_hz
    )
    return estimate.Timing(
        clamp_s=0.0,
        sample_s=sweep_s,
        remount_s=REMOUNT_ALLOWANCE_S,
        link=link_timing(config, time_scale),
        temperature=bool(config.dmm.temperature_channel),
    )


# One exchange's latency beyond its bytes on the line: the host's system calls and scheduling, a
# USB-serial adapter's or the network's delivery, the device's parsing. Measured through the drivers
# on the emulators (whose devices answer at once): 0.3 ms median, 1.5 ms mean on a loaded two-core
# host; a real controller adds its own few milliseconds, and a real bench's clock is the wall's.
EXCHANGE_LATENCY_S = 1.5e-3
# what the sequencer's exchanges are, counted from the drivers (labcal.drivers):
START_EXCHANGES = {"oriental-az": 2, "newport-smc100": 3}  # position read, then DDO write / PA + TE
FRAME_BYTES = {"oriental-az": 8 + 13, "newport-smc100": 5 + 11}  # a status read: request and reply
# (FC 03 of 4 registers: 8 bytes out, 5 + 8 back; "1TS" CR LF out, "1TS000028" CR LF back)
AZ_REPLY_BYTES = 10  # the mean reply of the sequencer's AZ exchanges: status 13, position 9, move 8 bytes
DMM_VERIFY_EXCHANGES = 12  # at each mount: *ESR?, SYST:ERR? and the configuration's ten queries back


def link_timing(config: StationFile, time_scale: float = 1.0) -> LinkTiming:
    """The station's links, priced in the rig's seconds. On an emulated station the rig's clock runs
    ``time_scale`` times faster than the wall's, and the host's and the drivers' own waits (the
    latency, the Modbus RTU silent interval before each request, pymodbus's look for the end of a
    reply) are the wall's: they count ``time_scale`` times. Bytes on a serial line take their
    characters' time (as the emulated DMM's RS-232 paces them, in the rig's time)."""
    def exchange_s(settings: config_station.AzSettings | Smc100Settings) -> float:
        bits = 1 + settings.bytesize + (settings.parity != "N") + settings.stopbits
        serial = not settings.tcp
        wire = FRAME_BYTES[settings.driver] * bits / settings.baudrate if serial else 0.0
        waits = EXCHANGE_LATENCY_S
        if (
            isinstance(settings, config_station.AzSettings) and serial
        ):  # pymodbus polls the port every 4 characters,
            poll = max(4 * bits / settings.baudrate, 1e-3)  # 1 ms at least, and takes a reply once its
            # length stays put for a poll; over socket:// (a serial-device server) pyserial's in_waiting
            # says only whether a byte waits, so each of the reply's bytes takes a poll of its own
            polls = AZ_REPLY_BYTES if (settings.port or "").startswith("socket://") else 2
            waits += modbus.silent_interval_s(settings.baudrate, bits) + polls * poll
        return wire + time_scale * waits

    dmm = config.dmm
    char_s = 10 / dmm.baudrate if dmm.serial_line else 0.0  # 8N1
    channels = len(dmm.channels) + bool(dmm.temperature_channel)
    return estimate.LinkTiming(
        table_s=(exchange_s(config.pitch) + exchange_s(config.roll)) / 2,
        start_exchanges=START_EXCHANGES[config.pitch.driver] + START_EXCHANGES[config.roll.driver],
        poll_s=(config.pitch.poll_s + config.roll.poll_s) / 2, dmm_s=time_scale * EXCHANGE_LATENCY_S,
        fetch_per_sample_s=channels * (keysight_34970a.READING_CHARS * char_s + keysight_34970a.OUTPUT_S),
        verify_exchanges=DMM_VERIFY_EXCHANGES)


def hardware_station(config: StationFile, source: str, stack: ExitStack, *, emulate: bool = False,
                     time_scale: float | None = None, seed: int | None = None,
                     start_time_s: float = 0.0, tables_at: tuple[float, float] | None = None
                     ) -> tuple[StationSetup, Bench]:
    """A station file's devices through the real drivers (on the emulators it points at with
    ``emulate``, started here and stopped with ``stack``). The journal keeps the file, so that a
    resume can rebuild the same station, or check that a new file describes the same bench."""
    # injected faults are a test, not the station: a resume has none
    station = config.model_dump(mode="json", exclude={"emulation": {"faults"}})
    snapshot: dict[str, Any] = {"kind": "station", "station": station, "emulate": emulate}
    timing = station_timing(config)
    sweep_s = timing.sample_s
    settle, clock, hooks = config.sequencer.settle, None, {}
    metadata = run_metadata.RunMetadata(station_file=source)
    if emulate:
        emulation = stack.enter_context(sim_emulation.Emulation(config, time_scale=time_scale, seed=seed,
                                                                start_s=start_time_s))
        rig = emulation.rig.rig
        if tables_at is not None:  # a resumed run: the emulated tables are where it left them
            rig.pitch.place(tables_at[0])
            rig.roll.place(tables_at[1])
        snapshot.update(time_scale=emulation.time_scale, seed=rig.seed)
        timing = estimate.Timing(
            clamp_s=rig.config.clamp_s,
            sample_s=sweep_s,
            remount_s=0.0,
            link=link_timing(config, emulation.time_scale),
            temperature=timing.temperature,
        )
        pooling = config.sequencer.settle.model_dump(include={"pool", "instrument_type"})
        settle = known_settle(rig.instrument).model_copy(update=pooling)  # the station says whose records
        clock, hooks = emulation.rig.clock, emulation.hooks()
        metadata.simulated_truth = run_metadata.SimulatedTruth.model_validate(emulation.truth())
        config = emulation.station_config
    else:
        links_fixed(config, source)
    bench = stack.enter_context(hardware.Bench(config, clock))
    text = json.dumps(snapshot, sort_keys=True)
    return StationSetup(bench.station(**hooks), text, metadata, timing, settle), bench


def read_snapshot(text: str, run_name: str, started_with: str) -> StationFileSnapshot | None:
    """The station a journaled run started on; None for the simulated rig (``--sim``). Validated
    with today's models, so that fields added since take their defaults; one that no longer
    validates is one line naming the field (``run_name``: the run; ``started_with``: its labcal)."""
    snapshot = config_snapshot.parse_snapshot(text)
    if not isinstance(snapshot, config_snapshot.StationFileSnapshot):
        return None
    try:
        snapshot.config  # noqa: B018 - validated here, so that one that no longer is says so in one line
    except pydantic.ValidationError as exc:
        raise LabcalError(
            f"{run_name}: the station it started on no longer validates "
            f"({one_line(exc, config_station.StationFile)}); resume it with labcal {started_with}, "
            "which started it"
        ) from None
    return snapshot


def station_for_resume(snapshot: StationFileSnapshot, run_name: str, stack: ExitStack, start_time_s: float,
                       new: tuple[StationFile, str] | None = None,
                       tables_at: tuple[float, float] | None = None) -> tuple[StationSetup, Bench]:
    """The station a journaled run goes on with: the one it started on, or ``new`` (a station
    file and its name) when that describes the same bench on other links; emulators restarted."""
    config, source = snapshot.config, "the journaled station"
    if new is not None:
        config, source = new
        differences = snapshot.config.identity_differences(config, Path(source).name, snapshot.emulate)
        if differences:
            raise LabcalError(f"{source} is not the bench {run_name} started on: {'; '.join(differences)}; a "
                              "resumed run may change only links, timeouts and retries: correct the file, or "
                              "omit {0} to resume on the run's own station", "station")
    return hardware_station(config, source, stack, emulate=snapshot.emulate, time_scale=snapshot.time_scale,
                            seed=snapshot.seed, start_time_s=start_time_s, tables_at=tables_at)


def prepare(bench: Bench, station: Station, say: Callable[[str], None]) -> None:
    """Home and enable the tables and configure the DMM; a stop reaches the tables if that fails
    after a table was told to move (a homing; ``say`` tells the operator what is being done, and a
    stop that failed too). A run refused before any table was told to move sends no stop: a stop
    on a shared bus (a broadcast on a gateway) would stop tables another process drives."""
    try:
        bench.prepare(say=say)
    except BaseException as exc:
        if not any(axis.commanded for axis in bench.axes):
            raise
        try:
            station.stop()
        except LabcalError as stop_error:
            if str(stop_error) != str(exc):  # an unreachable table fails both the same way: say it once
                say(f"[bold red]and stopping the tables failed:[/] {stop_error}")
        raise


def bench_for_check(config: StationFile, stack: ExitStack, *, emulate: bool = False,
                    time_scale: float | None = None) -> Bench:
    """A station's devices for `labcal station check` (on the emulators it points at with ``emulate``,
    started here and stopped with ``stack``). A check says at once that a port is missing instead
    of retrying for the reconnect budget."""
    clock = None
    if emulate:
        emulation = stack.enter_context(sim_emulation.Emulation(config, time_scale=time_scale))
        config, clock = emulation.station_config, emulation.rig.clock
    else:
        links_fixed(config, "the station")
    quick = config.model_copy(update={name: link.model_copy(update={"reconnect_s": 0.0})
                                      for name, link in config.devices().items()})
    return stack.enter_context(hardware.Bench(quick, clock))

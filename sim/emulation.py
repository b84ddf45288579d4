"""Start the emulators a station file points at, fed by one simulated rig.

Devices on the same port share one emulated bus (two AZ drives behind one gateway, two SMC100
controllers on one daisy chain). The station file's ``[emulation]`` table (validated with the
station file, as `labcal.config.emulation.EmulationSettings`) sets the time scale, the seed, the
rig (``[emulation.rig]``) and the faults to inject. `Emulation.station_config` is the station
file as the running emulators answer it (free TCP ports filled in).

A station may let the emulators choose its links (`LinkSettings.chosen_by_emulators`): port 0
is any free TCP port (the devices of one driver on port 0 share it: one gateway, one daisy
chain), and ``port = "pty:NAME"`` a pty linked as NAME in a temporary folder of this emulation's
own, removed when it stops. Two emulated runs of one such station file then never meet.
"""

from __future__ import annotations

import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

from labcal.config.station import PTY_PREFIX, AzSettings, LinkSettings, Smc100Settings, StationFile
from labcal.errors import LabcalError
from labcal.sim.az_emulator import AzDrives, AzServer, AzUnit
from labcal.sim.dmm_emulator import Keysight34970AEmulator
from labcal.sim.emulated_rig import EmulatedRig
from labcal.sim.endpoint import Endpoint
from labcal.sim.faults import Fault, FaultInjector
from labcal.sim.line_server import LineServer
from labcal.sim.smc100_emulator import Positioner, Smc100Emulator

Server = AzServer | LineServer
NO_LIMITS = (-1e9, 1e9)


class Emulation:
    """Running emulators; `close` (or leaving the `with` block) stops them and removes their ptys."""

    def __init__(self, config: StationFile, *, time_scale: float | None = None, seed: int | None = None,
                 start_s: float = 0.0):
        settings = config.emulation
        if time_scale is not None and not 0 < time_scale <= 1e5:
            raise LabcalError(f"time scale {time_scale:g} must be > 0 and ≤ 100000")
        self.time_scale = time_scale or settings.time_scale
        seed = settings.seed if seed is None else seed
        # the emulated instrument is the one the station says is on its bench: its package's sensors
        rig = settings.rig.model_copy(update={"instrument": settings.rig.instrument.model_copy(
            update={"package": config.instrument.package})})
        self.rig = EmulatedRig(rig, self.time_scale, seed, start_s)
        # which rig table the device configured as each table drives: its own, unless they are exchanged
        self.drives = {"pitch": "roll", "roll": "pitch"} if settings.tables_exchanged else {}
        self.faults = {name: FaultInjector() for name in ("pitch", "roll", "dmm")}
        for spec in settings.faults:
            self.faults[spec.device].add(Fault(**spec.model_dump(exclude={"device"})))
        self.servers: dict[str, tuple[list[str], str, Server]] = {}  # bus → (devices, protocol, server)
        self._pty_folder: Path | None = None  # made for the first pty:NAME link
        try:
            for bus, names in self._buses(config).items():
                self.servers[bus] = self._serve(config, names)
        except BaseException:
            self.close()
            raise
        self.station_config = config.model_copy(update={
            name: settings.model_copy(update={"port": None, "tcp": None,
                                              **self.servers[settings.bus][2].endpoint.settings_update()})
            for name, settings in config.devices().items()})

    @staticmethod
    def _buses(config: StationFile) -> dict[str, list[str]]:
        buses: dict[str, list[str]] = {}
        for name, settings in config.devices().items():
            buses.setdefault(settings.bus, []).append(name)
        return buses

    def _own_pty(self, name: str, settings: LinkSettings) -> LinkSettings:
        """``port = "pty:NAME"`` → the path of NAME in this emulation's own temporary folder."""
        link = (settings.port or "").removeprefix(PTY_PREFIX)
        if not link or "/" in link or link in (".", ".."):
            raise LabcalError(f"{name}: port = \"{settings.port}\" must name the pty's link, e.g. "
                              f"\"{PTY_PREFIX}tables\" (a name, no folder: the emulators choose the folder)")
        if self._pty_folder is None:
            self._pty_folder = Path(tempfile.mkdtemp(prefix="labcal-emulator-"))
        return settings.model_copy(update={"port": str(self._pty_folder / link)})

    def _serve(self, config: StationFile, names: list[str]) -> tuple[list[str], str, Server]:
        first: LinkSettings = config.devices()[names[0]]
        if (first.port or "").startswith(PTY_PREFIX):
            first = self._own_pty(names[0], first)
        endpoint = Endpoint.of(names[0], first)
        try:
            if isinstance(first, AzSettings):
                units = {s.unit: AzUnit(self.drives.get(n, n), s.steps_per_degree, s.wrap)
                         for n, s in ((n, config.devices()[n]) for n in names) if isinstance(s, AzSettings)}
                server: Server = AzServer(AzDrives(self.rig, units), endpoint, self.faults)
                protocol = "Modbus TCP" if endpoint.kind == "tcp" else "Modbus RTU"
            elif isinstance(first, Smc100Settings):
                controllers = {s.address: Positioner(self.drives.get(n, n), limits=s.limits_deg or NO_LIMITS)
                               for n, s in ((n, config.devices()[n]) for n in names)
                               if isinstance(s, Smc100Settings)}
                server = LineServer(Smc100Emulator(self.rig, controllers), endpoint, self.faults)
                protocol = "Newport SMC100 ASCII"
            else:
                dmm = config.dmm
                wiring: dict[int, int | str] = dict(zip(dmm.channels, config.instrument.axes, strict=True))
                if dmm.temperature_channel:
                    wiring[dmm.temperature_channel] = "temp"
                serial_line = endpoint.kind == "pty"
                meter = Keysight34970AEmulator(self.rig, wiring, serial_line=serial_line)
                # RS-232 carries 10 bits a character (8N1), in the rig's time
                char_s = 10 / dmm.baudrate / self.time_scale if serial_line else 0.0
                server = LineServer(meter, endpoint, self.faults, char_s=char_s)
                protocol = "Keysight 34970A SCPI"
        except OSError as exc:
            raise LabcalError(f"{', '.join(names)}: cannot serve {endpoint} ({exc.strerror or exc}); "
                              "is another emulator (labcal sim serve) already using it?") from None
        return names, protocol, server

    def endpoints(self) -> list[dict]:
        """What listens where, for people and for `--json`."""
        return [{"devices": names, "protocol": protocol, "address": server.address}
                for names, protocol, server in self.servers.values()]

    def hooks(self) -> dict[str, Callable]:
        """What a station on these emulators tells the rig: the operator's remounts, and which
        point is measured (the rig draws each point's noise from it, so a resume measures alike)."""
        def at_point(key: str) -> None:
            with self.rig.lock:
                self.rig.rig.at_point(key)
        return {"remounted": self.rig.set_mount, "at_point": at_point}

    def truth(self) -> dict:
        """The emulated instrument and rig, as a run records them."""
        rig = self.rig.rig
        return {"coefficients": rig.instrument.X.tolist(), "misalignment_deg": rig.misalignment.degrees(),
                "seed": rig.seed, "time_scale": self.time_scale, "endpoints": self.endpoints()}

    def close(self) -> None:
        for _, _, server in self.servers.values():
            server.close()
        self.servers.clear()
        if self._pty_folder is not None:  # its links went with their ptys; the folder is ours alone
            shutil.rmtree(self._pty_folder, ignore_errors=True)
            self._pty_folder = None

    def __enter__(self) -> Emulation:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

"""The devices a station file names, opened: one link per bus, one driver per device."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

from labcal.config.run_metadata import DeviceIdentity
from labcal.config.station import (
    AzSettings,
    DmmSettings,
    LinkSettings,
    Smc100Settings,
    StationFile,
    tcp_address,
)
from labcal.devices.station import Clock, CriticalSection, Station, SystemClock
from labcal.drivers.axis import IndexAxis
from labcal.drivers.errors import DriverError
from labcal.drivers.keysight_34970a import EOL as SCPI_EOL
from labcal.drivers.keysight_34970a import Keysight34970A
from labcal.drivers.modbus import ModbusLink
from labcal.drivers.newport_smc100 import EOL as SMC_EOL
from labcal.drivers.newport_smc100 import Smc100Axis
from labcal.drivers.oriental_az import AzAxis
from labcal.drivers.transport import LineTransport, SerialStream, TcpStream
from labcal.drivers.visa import VisaLink
from labcal.lazy import lazy

if TYPE_CHECKING:
    from pyvisa import constants
else:
    constants = lazy("pyvisa.constants")  # start-up without numpy, pyvisa

Link = TypeVar("Link", ModbusLink, LineTransport)


def line_transport(settings: LinkSettings, eol: bytes) -> LineTransport:
    """An ASCII link on the port or TCP address the settings name (opened on first use)."""
    if settings.tcp:
        host, port = tcp_address(settings.tcp)
        return LineTransport(settings.where, lambda: TcpStream(host, port, settings.timeout_s), eol=eol,
                             timeout_s=settings.timeout_s, reconnect_s=settings.reconnect_s)
    url = settings.port
    assert url is not None
    return LineTransport(settings.where, lambda: SerialStream(
        url, baudrate=settings.baudrate, bytesize=settings.bytesize, parity=settings.parity,
        stopbits=settings.stopbits, xonxoff=settings.xonxoff, timeout_s=settings.timeout_s),
        eol=eol, timeout_s=settings.timeout_s, reconnect_s=settings.reconnect_s)


def dmm_link(settings: DmmSettings) -> LineTransport | VisaLink:
    """The DMM's link: a VISA resource when the station names one, else a port or TCP address."""
    if settings.visa is None:
        return line_transport(settings, SCPI_EOL)
    serial = {}
    if settings.serial_line:  # an ASRL resource takes the station's line settings
        serial = {
            "baud_rate": settings.baudrate,
            "data_bits": settings.bytesize,
            "parity": {"N": constants.Parity.none, "E": constants.Parity.even, "O": constants.Parity.odd}[
                settings.parity
            ],
            "stop_bits": {1: constants.StopBits.one, 2: constants.StopBits.two}[settings.stopbits],
            # the 34970A's RS-232 factory setting is XON/XOFF (User's Guide p.192): without it
            # the unit's XOFF is read as data and a long reply overruns its buffer
            "flow_control": constants.ControlFlow.xon_xoff
            if settings.xonxoff
            else constants.ControlFlow.none,
        }
    return VisaLink(settings.visa, library=settings.visa_library, eol=SCPI_EOL.decode(),
                    timeout_s=settings.timeout_s, reconnect_s=settings.reconnect_s, serial=serial)


def modbus_link(settings: LinkSettings) -> ModbusLink:
    if settings.tcp:
        host, port = tcp_address(settings.tcp)
        return ModbusLink.tcp(host, port, timeout_s=settings.timeout_s, retries=settings.retries,
                              reconnect_s=settings.reconnect_s)
    assert settings.port is not None
    return ModbusLink.serial(settings.port, baudrate=settings.baudrate, bytesize=settings.bytesize,
                             parity=settings.parity, stopbits=settings.stopbits, timeout_s=settings.timeout_s,
                             retries=settings.retries, reconnect_s=settings.reconnect_s)


def dmm_identity(idn: str) -> DeviceIdentity:
    """A 34970A-family ``*IDN?`` answer (maker, model, serial number, firmware) by field."""
    maker, model, serial, firmware = (field.strip() for field in idn.split(",", 3))
    return DeviceIdentity(model=f"{maker} {model}", identity=idn, maker=maker, serial=serial,
                          firmware=firmware)


def axis_identity(axis: IndexAxis) -> DeviceIdentity:
    """A table's identity by field, as far as its manual documents one: the SMC100 answers ``ID?``
    (the stage) and ``VE`` (controller and firmware); the AZ register map has no product, serial
    or version register, so an AZ drive is named by its model and unit (confirmed by a status read)."""
    maker, _, model = axis.model.rpartition(" ")
    if isinstance(axis, Smc100Axis):
        return DeviceIdentity(model=axis.model, identity=axis.identify(), maker=maker, stage=axis.ask("ID?"),
                              firmware=axis.ask("VE"))
    return DeviceIdentity(model=axis.model, identity=axis.identify(), maker=maker)


class Bench:
    """Drivers for a station file. Nothing is opened until a device is first asked something;
    `close` releases every port."""

    def __init__(self, config: StationFile, clock: Clock | None = None):
        self.config = config
        self.clock = clock or SystemClock()
        self._links: dict[str, ModbusLink | LineTransport | VisaLink] = {}
        # who answered, as each device says it (read by `prepare`): a run journals these in its
        # metadata ("device_identity") and a resume as an event, for the certificate's traceability
        self.identities: dict[str, DeviceIdentity] = {}
        self.pitch = self._axis("pitch", config.pitch)
        self.roll = self._axis("roll", config.roll)
        dmm = config.dmm
        self._links[dmm.bus] = link = dmm_link(dmm)  # the DMM shares its link with nothing
        self.dmm = Keysight34970A("dmm", link,
                                  channels=dmm.channels, temperature_channel=dmm.temperature_channel,
                                  temperature_probe=dmm.temperature_probe, nplc=dmm.nplc, range_v=dmm.range_v,
                                  line_hz=dmm.line_hz, retries=dmm.retries, serial_line=dmm.serial_line,
                                  baudrate=dmm.baudrate, axes=config.instrument.axes)

    def _link(self, settings: LinkSettings, kind: type[Link], make: Callable[[], Link]) -> Link:
        """The one link of the settings' bus, made for its first device."""
        if settings.bus not in self._links:
            self._links[settings.bus] = make()
        link = self._links[settings.bus]
        assert isinstance(link, kind)  # StationFile gives the devices sharing a bus one driver
        return link

    def _axis(self, name: str, s: AzSettings | Smc100Settings) -> IndexAxis:
        if isinstance(s, AzSettings):
            return AzAxis(name, self._link(s, ModbusLink, lambda: modbus_link(s)), s.unit, self.clock,
                          steps_per_degree=s.steps_per_degree, speed_dps=s.speed_dps, accel_dps2=s.accel_dps2,
                          wrap=s.wrap, limits_deg=s.limits_deg, tolerance_arcsec=s.in_position_arcsec,
                          poll_s=s.poll_s, cable_wrap_deg=s.wrap_deg)
        return Smc100Axis(name, self._link(s, LineTransport, lambda: line_transport(s, SMC_EOL)), s.address,
                          self.clock, speed_dps=s.speed_dps, accel_dps2=s.accel_dps2,
                          home_timeout_s=s.home_timeout_s, retries=s.retries, limits_deg=s.limits_deg,
                          tolerance_arcsec=s.in_position_arcsec, poll_s=s.poll_s, cable_wrap_deg=s.wrap_deg)

    @property
    def axes(self) -> tuple[IndexAxis, IndexAxis]:
        return self.pitch, self.roll

    def prepare(self, say: Callable[[str], None] = lambda text: None) -> None:
        """Read every device's identity (`identities`), home and enable the tables where their
        controllers need it, and configure the DMM."""
        for axis in self.axes:
            self.identities[axis.name] = identity = axis_identity(axis)
            say(f"preparing the {axis.name} table ({identity.identity})")
            axis.prepare()
        self.identities["dmm"] = dmm_identity(self.dmm.identify())
        self.dmm.configure()

    def check(self, reset_alarms: bool = False) -> list[dict[str, Any]]:
        """Ask every device who it is and how it is, without moving anything: tables their status
        and position, the DMM one scan. One report per device; ``problem`` says what failed."""
        reports = []
        for axis in self.axes:
            report: dict[str, Any] = {"device": axis.name, "model": axis.model, "link": axis.device,
                                      "problem": None}
            try:
                report["identity"] = axis.identify()
                if reset_alarms and isinstance(axis, AzAxis) and axis.stop_input_on():
                    axis.release_stop()  # left on by a stop whose release never arrived
                    report["stop_released"] = True
                status = axis.status()
                if status.fault and reset_alarms and isinstance(axis, AzAxis):
                    axis.reset_alarm()
                    report["alarm_reset"] = True
                    status = axis.status()
                homing = status.needs_homing  # not a problem: a run homes the table first
                report.update(status=status.words + (" (a run homes it first)" if homing else ""),
                              position_deg=axis.position(), problem=None if homing else status.fault)
            except DriverError as exc:
                report["problem"] = str(exc)
            reports.append(report)
        report = {"device": "dmm", "model": self.dmm.model, "link": self.dmm.device, "problem": None}
        try:
            report["identity"] = self.dmm.identify()
            self.dmm.configure()
            scan = self.dmm.read(1)
            # null for a sensor the package lacks (it has no channel): JSON has no NaN
            report["volts"] = [None if math.isnan(v) else v for v in scan.volts[0].tolist()]
            report["temp_c"] = None if scan.temp_c is None else float(scan.temp_c[0])
        except DriverError as exc:
            report["problem"] = str(exc)
        reports.append(report)
        return reports

    def guard_exchanges(self, critical: CriticalSection | None) -> None:
        """Make every exchange on every link a critical section of the run (None: no run)."""
        for link in self._links.values():
            link.critical = critical

    def station(self, **hooks: Callable[..., None]) -> Station:
        """The drivers as the sequencer's station; ``hooks`` (``remounted``, ``at_point``) tell an
        emulated rig what the operator did. Real hardware needs neither."""
        return Station(pitch=self.pitch, roll=self.roll, dmm=self.dmm, clock=self.clock,
                       description=self.config.description or "hardware station",
                       guard_exchanges=self.guard_exchanges, **hooks)

    def close(self) -> None:
        for link in self._links.values():
            link.close()
        self._links.clear()

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

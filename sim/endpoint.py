"""Where an emulator listens, read from the link a station file gives its device.

- ``tcp = "127.0.0.1:5025"`` → a TCP listener (Modbus TCP for an AZ drive, raw lines otherwise);
- ``port = "socket://127.0.0.1:5021"`` → a TCP listener speaking the serial protocol (Modbus RTU
  frames for an AZ drive), as a serial-device server would;
- ``port = "/tmp/labcal-sim/tables"`` → a pty pair whose driver end is linked at that path.

Port 0 means "any free port"; the emulator reports the one it got. Emulators only listen on
loopback: a station that names another host describes real hardware.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from labcal.config.station import LinkSettings, tcp_address
from labcal.errors import LabcalError

LOOPBACK = ("127.0.0.1", "localhost", "::1")


@dataclass(frozen=True)
class Endpoint:
    kind: Literal["pty", "tcp", "socket"]
    host: str = ""
    port: int = 0
    link: str = ""

    @classmethod
    def of(cls, name: str, settings: LinkSettings) -> Endpoint:
        if getattr(settings, "visa", None) is not None:
            raise LabcalError(f"{name}: emulators serve a pty or a TCP port, not a VISA resource; emulate "
                              "the station with tcp = \"127.0.0.1:PORT\" and reach it through VISA as "
                              "visa = \"TCPIP0::127.0.0.1::PORT::SOCKET\" from another station file")
        if settings.tcp is not None:
            host, port = tcp_address(settings.tcp)
            return cls("tcp", host, port).checked(name)
        url = settings.port or ""
        if url.startswith("socket://"):
            host, port = tcp_address(url.removeprefix("socket://").split("?")[0])
            return cls("socket", host, port).checked(name)
        if "://" in url:
            raise LabcalError(f"{name}: cannot emulate a device on {url}; emulators serve a pty path, "
                              "tcp = \"127.0.0.1:PORT\" or port = \"socket://127.0.0.1:PORT\"")
        if url.startswith("/dev/"):
            raise LabcalError(f"{name}: {url} is a real device; emulators link their ptys elsewhere, "
                              "e.g. port = \"/tmp/labcal-sim/tables\"")
        if settings.parity != "N":
            raise LabcalError(f"{name}: a pty cannot carry parity {settings.parity}; "
                              "set parity = \"N\" to emulate it on a pty")
        return cls("pty", link=url)

    def checked(self, name: str) -> Endpoint:
        if self.host not in LOOPBACK:
            raise LabcalError(f"{name}: emulators listen on loopback only, not {self.host}; "
                              "use 127.0.0.1 in the station file")
        return self

    def bound(self, port: int) -> Endpoint:
        return replace(self, port=port)

    def settings_update(self) -> dict[str, str]:
        """What a station file must say to reach this endpoint (once bound)."""
        if self.kind == "tcp":
            return {"tcp": f"{self.host}:{self.port}"}
        if self.kind == "socket":
            return {"port": f"socket://{self.host}:{self.port}"}
        return {"port": self.link}

    def __str__(self) -> str:
        return {"tcp": f"tcp {self.host}:{self.port}", "socket": f"socket://{self.host}:{self.port}",
                "pty": f"pty {self.link}"}[self.kind]

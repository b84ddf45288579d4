"""The lab-wide configuration file: what belongs to the laboratory, not to a bench or a folder.

One file per site holds the lab database's location, the laboratory's name, address and
accreditation, and the default tolerances and usage envelope of its certificates. Without it the
database would be `runs/labcal.sqlite` under whatever folder a command was started in, and
`cd /tmp && labcal history ACC-0042` would find nothing.

Where it is: $LABCAL_CONFIG, else the user's configuration folder (`$XDG_CONFIG_HOME/labcal/lab.toml`,
`~/Library/Application Support/labcal/lab.toml` on macOS, `%APPDATA%\\labcal\\lab.toml` on Windows),
else the first `labcal/lab.toml` in $XDG_CONFIG_DIRS (default /etc/xdg: one file for every user of
the lab's PC). No file is fine: every value has a default that does not depend on the current
folder. A relative `database` is relative to the file that names it.

Example::

    database = "/srv/lab/labcal.sqlite"   # or postgresql://labcal@labserver:5432/lab
    journal = "/var/lib/labcal/journal.sqlite"   # with a server: this station's own journal
    station = "bench-2"   # this station's name in the lab database
    notify = ["mailto://user:app-password@example.com"]  # apprise URLs: remounts, pauses, run ends
    server_url = "https://lab.example.org"   # the lab server: notifications link to each run's page

    [laboratory]
    name = "Example Calibration Laboratory"
    address = "1 Metrology Way, Springfield"
    accreditation_id = "UKAS 0000"
    country_code = "GB"

    [certificate]          # defaults; a station's [certificate] and the command line go over them
    attitude_u95_max_deg = 0.05
    usage_pitch_deg = [-60, 60]
"""

from __future__ import annotations

import os
import socket
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import parse_qsl, urlencode

from pydantic import BaseModel, ConfigDict, Field, model_validator

from labcal.config.files import parse_model, read_text
from labcal.config.settings import CertificateSettings
from labcal.errors import LabcalError
from labcal.lazy import lazy

if TYPE_CHECKING:
    from importlib import util

    from labcal.config import numbering
else:
    numbering = lazy("labcal.config.numbering")  # start-up without 3 more modules
    util = lazy("importlib.util")  # start-up without importlib

CONFIG_ENV = "LABCAL_CONFIG"
DB_ENV = "LABCAL_DB"
NOTIFY_ENV = "LABCAL_NOTIFY"
JOURNAL_ENV = "LABCAL_JOURNAL"
STATION_ENV = "LABCAL_STATION"
FILE_NAME = "lab.toml"
DB_NAME = "labcal.sqlite"
JOURNAL_NAME = "journal.sqlite"


class Laboratory(BaseModel):
    """The issuing laboratory as a certificate names it (ISO/IEC 17025 §7.8.2.1 b)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(default="", description="the laboratory's name")
    address: str = Field(default="", description="where the calibration was performed")
    accreditation_id: str = Field(default="", description="accreditation body and number, if accredited")
    country_code: str = Field(default="", pattern="^([A-Z]{2})?$", description="ISO 3166-1 alpha-2, e.g. DE "
                              "(the Digital Calibration Certificate needs it)")
    code: str = Field(default="", pattern=r"^[A-Za-z0-9._-]*$",
                      description="the laboratory's short code, {lab} in certificate_number")
    certificate_number: str = Field(default="", description="the lab's certificate numbers, e.g. "
                                    "\"{lab}-{year}-{seq:04d}\": {seq} the lab-wide sequence (each year anew "
                                    "where {year} is in it), {year} the calibration's, {lab} the code; "
                                    "empty: labcal's own identifier")

    @model_validator(mode="after")
    def _numbering(self):
        """A numbering format that makes a number: known fields only, {seq} among them, {lab} only with a
        code (checked at load, so a typo is one line now, not a failed certificate after a run)."""
        if not self.certificate_number:
            return self
        problem = numbering.number_problem(self.certificate_number, self.code)
        if problem:
            raise ValueError(f"certificate_number {self.certificate_number!r}: {problem}")
        return self

    @property
    def stated(self) -> str:
        """Name and address in one line, as printed; empty when the file states neither."""
        return ", ".join(part for part in (self.name, self.address) if part)


class CorrectionLimits(BaseModel):
    """When a device correction (a plan's ``[device_correction]``) expires: past this age of the estimate
    it took, or after this many runs have used it. Its u grows with age at the rate the device's history
    shows (`analysis.device_ageing`); past these limits the device is identified again instead."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_age_days: float = Field(default=90.0, gt=0, allow_inf_nan=False,
                                description="days from the estimate's calibration after which it is not used")
    max_uses: int = Field(default=20, ge=1, description="runs that may correct from one estimate")


class InstrumentsSection(BaseModel):
    """The lab file's ``[instruments]``: what a run does with a serial the register does not hold."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    allow_adhoc: bool = Field(default=False,
                              description="let a run certify a serial the instrument register does not "
                                          "hold without asking (with --yes or in a script, too)")


class LabFile(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    database: str | None = Field(default=None,
                                 description="the lab database: a SQLite file (relative: to this file), "
                                             "sqlite:///PATH, or postgresql://USER@HOST:PORT/DBNAME")
    journal: str | None = Field(default=None,
                                description="with a PostgreSQL lab database, this station's local journal "
                                            "(SQLite; relative: to this file)")
    station: str | None = Field(default=None,
                                description="this station's name in the lab database (default: the "
                                            "computer's name)")
    server_key: str | None = Field(default=None,
                                   description="the lab server's private key (PEM; relative: to this file) "
                                               "for approvals, when `labcal serve` is given no --key; "
                                               "registered with `labcal certificate approvers add "
                                               "--role \"lab server\"`")
    laboratory: Laboratory = Field(default_factory=Laboratory)
    certificate: CertificateSettings = Field(default_factory=CertificateSettings,
                                             description="default tolerances and usage envelope")
    device_correction: CorrectionLimits = Field(default_factory=CorrectionLimits,
                                                description="when a device correction expires")
    instruments: InstrumentsSection = Field(default_factory=InstrumentsSection)
    notify: list[str] = Field(default_factory=list,
                              description="apprise URLs told of each remount, pause and run's end "
                                          "; $LABCAL_NOTIFY goes over it")
    server_url: str | None = Field(default=None, pattern=r"^https?://[^\s/]+(/\S*)?$",
                                   description="the lab server's address as people reach it "
                                               "(https://lab.example.org): notifications link to each "
                                               "run's page there")


@dataclass(frozen=True)
class LabConfig:
    """The lab file as read, with where it came from (``path`` None: no file, defaults)."""

    path: Path | None
    searched: tuple[Path, ...]
    file: LabFile

    @property
    def laboratory(self) -> Laboratory:
        return self.file.laboratory

    @property
    def certificate(self) -> CertificateSettings:
        """The certificate defaults, with the laboratory's name and address as the printed line."""
        if self.laboratory.stated and not self.file.certificate.laboratory:
            return self.file.certificate.model_copy(update={"laboratory": self.laboratory.stated})
        return self.file.certificate

    def notify_urls(self) -> tuple[tuple[str, ...], str]:
        """Where a run's notifications go, and who said so (for a one-line refusal): $LABCAL_NOTIFY
        (comma-separated) when it is set, even empty (which turns the lab file's off for one
        command), else the lab file's ``notify``."""
        if NOTIFY_ENV in os.environ:
            urls = os.environ[NOTIFY_ENV].split(",")
            return tuple(u.strip() for u in urls if u.strip()), f"${NOTIFY_ENV}"
        return tuple(u.strip() for u in self.file.notify if u.strip()), f"{self.path or FILE_NAME}: notify"

    def database(self, option: str | Path | None = None) -> Path | ServerDatabase:
        """The lab database: --db, else $LABCAL_DB, else this file's `database`, else the user's
        data folder — never a path relative to the current folder unless one was given."""
        if option:
            return database_location(str(option), "--db")
        if os.environ.get(DB_ENV):
            return database_location(os.environ[DB_ENV], f"${DB_ENV}")
        if self.file.database:
            given = database_location(self.file.database, f"{self.path or FILE_NAME}: database")
            return given if isinstance(given, ServerDatabase) else self._relative(given)
        return data_home() / "labcal" / DB_NAME

    def server_key(self) -> Path | None:
        """The lab server's signing key as this file names it (None: it names none)."""
        return None if not self.file.server_key else self._relative(Path(self.file.server_key))

    def journal(self) -> Path:
        """Where this station journals its runs when the lab database is a server: $LABCAL_JOURNAL,
        else this file's `journal`, else the user's data folder. Every reading is on this disk
        before the server sees it, so a run never waits for the server (`labcal.store.sync`)."""
        if os.environ.get(JOURNAL_ENV):
            return Path(os.environ[JOURNAL_ENV]).expanduser()
        if self.file.journal:
            return self._relative(Path(self.file.journal))
        return data_home() / "labcal" / JOURNAL_NAME

    def station(self) -> str:
        """This station's name in the lab database: $LABCAL_STATION, else this file's `station`, else
        the computer's name (one station per computer unless told otherwise)."""
        return os.environ.get(STATION_ENV) or self.file.station or socket.gethostname()

    def _relative(self, given: Path) -> Path:
        given = given.expanduser()
        return given if given.is_absolute() or self.path is None else self.path.parent / given


SERVER_SCHEMES = ("postgresql", "postgres", "postgresql+psycopg")
DRIVER_HINT = "pip install 'labcal[lab]'"


@dataclass(frozen=True)
class ServerDatabase:
    """A lab database on a PostgreSQL server, as given (``postgresql://USER@HOST:PORT/DBNAME``)."""

    url: str
    source: str  # where it was given (--db, $LABCAL_DB, the lab file), for the messages

    @property
    def sqlalchemy_url(self) -> str:
        """The URL SQLAlchemy opens it with: psycopg 3, whatever the scheme's spelling."""
        return "postgresql+psycopg://" + self.url.partition("://")[2]

    def __str__(self) -> str:
        """The URL without a password (it is printed, and may be logged)."""
        return redacted(self.url)


SECRET_PARAMETERS = ("password", "passwd", "pwd", "secret", "token", "key")  # libpq's sslpassword too


def redacted(url: str) -> str:
    """``url`` as it may be shown or logged: the password of its user part and the value of every
    query parameter that names a secret (``?password=``, ``sslpassword=``, ``sslkey=``, a token)
    replaced by ``***``. The one place a URL loses its credentials."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        return url
    rest, hashmark, fragment = rest.partition("#")
    rest, question, query = rest.partition("?")
    who, at, where = rest.rpartition("@")
    if at and ":" in who:
        who = who.split(":", 1)[0] + ":***"
    if question:
        pairs = [(k, "***" if any(s in k.lower() for s in SECRET_PARAMETERS) else v)
                 for k, v in parse_qsl(query, keep_blank_values=True)]
        query = urlencode(pairs, safe="*/:")
    return f"{scheme}://{who}{at}{where}{question}{query}{hashmark}{'***' if fragment else ''}"


def database_location(location: str, source: str) -> Path | ServerDatabase:
    """What a database location names: a SQLite file (a path, or a URL `sqlite:///PATH`,
    SQLAlchemy's form: three slashes then the path, so `sqlite:////srv/lab.sqlite` is absolute), or
    a PostgreSQL server (`postgresql://USER@HOST:PORT/DBNAME`), refused in one line when its driver
    (psycopg 3) is not installed. Any other `SCHEME://` is refused in one line rather than taken for
    a folder name: it is a typing error."""
    scheme, sep, rest = location.partition("://")
    if not sep:
        return Path(location)
    if scheme == "sqlite":
        if not rest.startswith("/") or rest == "/":
            raise LabcalError(f"{source}: {location!r} names no file; write sqlite:///PATH (three slashes "
                              "and a relative path, or four and an absolute one)")
        return Path(rest[1:])
    if scheme in SERVER_SCHEMES:
        server = ServerDatabase(location, source)
        if not rest.partition("/")[2]:
            raise LabcalError(f"{source}: {server} names no database; write "
                              "postgresql://USER@HOST:PORT/DBNAME")
        if util.find_spec("psycopg") is None:
            raise LabcalError(f"{source}: {server} is a PostgreSQL server, and its driver (psycopg 3) is not "
                              f"installed; {DRIVER_HINT}")
        return server
    raise LabcalError(f"{source}: unknown database scheme {scheme!r} in {location!r}; give a path, "
                      "sqlite:///PATH or postgresql://USER@HOST:PORT/DBNAME")


def _home_dir(env: str, posix: str, mac: str, windows_env: str) -> Path:
    if os.environ.get(env):
        return Path(os.environ[env])
    if sys.platform == "win32" and os.environ.get(windows_env):
        return Path(os.environ[windows_env])
    if sys.platform == "darwin":
        return Path.home() / mac
    return Path.home() / posix


def config_home() -> Path:
    return _home_dir("XDG_CONFIG_HOME", ".config", "Library/Application Support", "APPDATA")


def data_home() -> Path:
    return _home_dir("XDG_DATA_HOME", ".local/share", "Library/Application Support", "LOCALAPPDATA")


def candidates() -> tuple[Path, ...]:
    """Where the lab file is looked for, in order (the first that exists wins)."""
    if os.environ.get(CONFIG_ENV):
        return (Path(os.environ[CONFIG_ENV]),)
    site = [Path(d) / "labcal" / FILE_NAME
            for d in (os.environ.get("XDG_CONFIG_DIRS") or "/etc/xdg").split(os.pathsep) if d]
    return (config_home() / "labcal" / FILE_NAME, *site)


def load_lab_config() -> LabConfig:
    """The lab file, validated (every mistake one line naming the file and the field). A file named
    by $LABCAL_CONFIG must exist: a typo there would otherwise silently drop the lab's settings."""
    searched = candidates()
    if os.environ.get(CONFIG_ENV) and not searched[0].is_file():
        raise LabcalError(f"{searched[0]}: no such lab configuration file (named by ${CONFIG_ENV}); "
                          f"create it or unset {CONFIG_ENV}")
    for path in searched:
        if path.is_file():
            return LabConfig(path, searched, parse_model(read_text(path, "lab configuration"), LabFile,
                                                         str(path)))
    return LabConfig(None, searched, LabFile())



def certificate_settings(station: CertificateSettings | None, source: str) -> CertificateSettings:
    """The lab file's certificate defaults with what a station file's ``[certificate]`` table sets
    explicitly over them (the command line goes over both, `CertificateSettings.overridden`)."""
    lab = load_lab_config().certificate
    if station is None:
        return lab
    return lab.overridden(source, **{name: getattr(station, name) for name in station.model_fields_set})

"""Starting the lab server: the settings from the command line, uvicorn on a socket of our own.

The socket is bound before uvicorn starts so that ``--port 0`` (a free port the system picks) can be
printed as a URL before the first request: tests and scripts read that line to find the server.

Transport: TLS directly (``--certfile``/``--keyfile``), or behind a reverse proxy that terminates it
(``--forwarded-allow-ips``: only those addresses' X-Forwarded-Proto and X-Forwarded-For are
believed). Either way the session cookie is then ``Secure`` and every answer carries HSTS
(`labcal.server.guards.SecurityHeaders`). Bound beyond this machine without either, the server says
so in one line: passwords and cookies would cross the lab's network in clear.
"""

from __future__ import annotations

import ipaddress
import logging
import socket
import ssl
from collections.abc import Callable
from dataclasses import dataclass

import uvicorn

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.app.server_approval import server_key
from labcal.app.station_state import Silence
from labcal.errors import LabcalError
from labcal.server.app import ServerSettings, create_app
from labcal.server.connections import BACKLOG, connection_limit, guarded_protocol
from labcal.server.sessions import IDLE_S, Sessions

GRACE_S = 2.0  # open event streams are cut this long after Ctrl-C
KEEP_ALIVE_S = 5  # an idle kept-alive connection is closed after this


@dataclass(frozen=True)
class Transport:
    certfile: str | None = None
    keyfile: str | None = None
    forwarded_allow_ips: str | None = None  # a proxy's addresses, comma-separated (its headers trusted)

    def __post_init__(self) -> None:
        if (self.certfile is None) != (self.keyfile is None):
            raise LabcalError("give {0} and {1} together (the certificate and its private key)", "certfile",
                              "keyfile")
        if self.certfile is not None and self.keyfile is not None:
            context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            try:
                context.load_cert_chain(self.certfile, self.keyfile)
            except (OSError, ssl.SSLError) as exc:
                raise LabcalError(f"{self.certfile}, {self.keyfile}: not a certificate and its unencrypted "
                                  f"private key in PEM ({exc.strerror or exc})") from None

    @property
    def tls(self) -> bool:
        return self.certfile is not None


def settings_for(db_option: str | None, key: str | None, poll_s: float = 0.5, names: tuple[str, ...] = (),
                 host: str = "127.0.0.1", session_idle_s: float = IDLE_S,
                 silent_after_s: float | None = None) -> ServerSettings:
    """Open the lab database (read only by the server: refused unless at this labcal's schema) and
    check the signing key (``key``: --key, else the lab file's ``server_key``) now rather than at the
    first approval. ``names``: the names the server is reached by, beyond ``host`` itself.
    ``silent_after_s``: the least silence after which a running bench is not heard from."""
    lab = open_lab(OpenLab(db_option, must_exist=True))
    silence = Silence() if silent_after_s is None else Silence(floor_s=silent_after_s)
    return ServerSettings(lab=lab, key=server_key(key), poll_s=poll_s, hosts=hosts_for(host, names),
                          sessions=Sessions(idle_s=session_idle_s), silence=silence)


def loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def hosts_for(host: str, names: tuple[str, ...]) -> tuple[str, ...]:
    """The Host headers the server answers: the address it listens on, ``names`` (--server-name),
    and for a loopback or wildcard address this machine's own names."""
    found = [host, *names]
    if loopback(host) or host in ("0.0.0.0", "::"):
        found += ["localhost", "127.0.0.1", "::1", "[::1]"]
    if host in ("0.0.0.0", "::"):
        found += [socket.gethostname(), socket.getfqdn()]
    return tuple(dict.fromkeys(f"[{h}]" if ":" in h and not h.startswith("[") else h for h in found))


def exposure_warning(host: str, transport: Transport) -> str | None:
    """One line when the server is reachable from other machines without TLS."""
    if loopback(host) or transport.tls or transport.forwarded_allow_ips:
        return None
    return (f"warning: listening on {host} without TLS: passwords and session cookies cross the network in "
            "clear; give --certfile/--keyfile, or put a TLS proxy in front (--forwarded-allow-ips)")


def listen(host: str, port: int) -> socket.socket:
    """The server's socket, bound before uvicorn starts (so that --port 0's choice can be printed).
    Made with IPPROTO_TCP named: asyncio sets TCP_NODELAY only on sockets whose proto says TCP, and
    without it every answer waited for the client's delayed ACK, 40 ms (benchmarks/lab_load.py)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
    except OSError as exc:
        sock.close()
        raise LabcalError(f"{host}:{port}: cannot listen there ({exc.strerror}); choose another {{0}} "
                          "(0: any free one)", "port") from None
    sock.listen(BACKLOG)
    return sock


def url_of(sock: socket.socket, tls: bool = False) -> str:
    host, port = sock.getsockname()[:2]
    return f"{'https' if tls else 'http'}://{f'[{host}]' if ':' in host else host}:{port}"


def log_to_stderr() -> None:
    """The server's own warnings (failed sign-ins, lockouts: `labcal.app.users`) on stderr, one line
    each with the time, beside uvicorn's."""
    logger = logging.getLogger("labcal.server")
    if not logger.handlers:
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s labcal serve: %(message)s"))
        logger.addHandler(handler)
        logger.setLevel(logging.WARNING)
        logger.propagate = False


def serve(settings: ServerSettings, host: str, port: int, listening: Callable[[str], None],
          transport: Transport = Transport()) -> None:
    """Serve until Ctrl-C; ``listening`` is told the URL once the socket is bound."""
    sock = listen(host, port)
    log_to_stderr()
    proxy = transport.forwarded_allow_ips
    config = uvicorn.Config(create_app(settings), log_level="warning", timeout_graceful_shutdown=int(GRACE_S),
                            proxy_headers=proxy is not None, forwarded_allow_ips=proxy or "127.0.0.1",
                            server_header=False, timeout_keep_alive=KEEP_ALIVE_S,
                            http=guarded_protocol(connection_limit()), backlog=BACKLOG,
                            ssl_certfile=transport.certfile, ssl_keyfile=transport.keyfile)
    server = uvicorn.Server(config)
    listening(url_of(sock, transport.tls))
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()
        settings.lab.close()

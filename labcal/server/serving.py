"""Starting the lab server: the settings from the command line, uvicorn on a socket of our own.

The socket is bound before uvicorn starts so that ``--port 0`` (a free port the system picks) can be
printed as a URL before the first request: tests and scripts read that line to find the server.
"""

from __future__ import annotations

import socket
from collections.abc import Callable

from labcal.app.labdatabase import OpenLab, open_lab
from labcal.app.server_approval import server_key
from labcal.errors import LabcalError
from labcal.server.app import ServerSettings, create_app

GRACE_S = 2.0  # open event streams are cut this long after Ctrl-C


def settings_for(db_option: str | None, key: str | None, poll_s: float = 0.5) -> ServerSettings:
    """Open the lab database (read only by the server: refused unless at this labcal's schema) and
    check the signing key (``key``: --key, else the lab file's ``server_key``) now rather than at the
    first approval."""
    lab = open_lab(OpenLab(db_option, must_exist=True))
    return ServerSettings(lab=lab, key=server_key(key), poll_s=poll_s)


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
        raise LabcalError(f"{host}:{port}: cannot listen there ({exc.strerror}); choose another --port "
                          "(0: any free one)") from None
    sock.listen(128)
    return sock


def url_of(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"http://{f'[{host}]' if ':' in host else host}:{port}"


def serve(settings: ServerSettings, host: str, port: int, listening: Callable[[str], None]) -> None:
    """Serve until Ctrl-C; ``listening`` is told the URL once the socket is bound."""
    import uvicorn

    sock = listen(host, port)
    config = uvicorn.Config(create_app(settings), log_level="warning", timeout_graceful_shutdown=int(GRACE_S),
                            proxy_headers=False, server_header=False)
    server = uvicorn.Server(config)
    listening(url_of(sock))
    try:
        server.run(sockets=[sock])
    finally:
        sock.close()
        settings.lab.close()

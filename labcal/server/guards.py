"""What keeps the lab server answering under attack, in memory: password failures per client
address, open event streams per user, and the headers every answer carries.

Per account, password guesses are throttled in the lab database (`labcal.app.users.check_password`,
through the audit trail: it survives a restart). Per client address they are throttled here: a
client guessing across many names is slowed without locking anybody out.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict, deque

from starlette.datastructures import MutableHeaders
from starlette.types import ASGIApp, Message, Receive, Scope, Send

CLIENT_FAILURES = 10  # failed password checks a client address may make…
CLIENT_WINDOW_S = 900.0  # …within this window; then it waits until the oldest leaves the window
CLIENTS_KEPT = 10_000  # addresses remembered (the least recently failing forgotten beyond this)
STREAMS_PER_USER = 8  # open event streams a user may hold (each polls the database)


class ClientThrottle:
    """Failed password checks per client address in a sliding window."""

    def __init__(self, failures: int = CLIENT_FAILURES, window_s: float = CLIENT_WINDOW_S) -> None:
        self.failures, self.window_s = failures, window_s
        self._failed: OrderedDict[str, deque[float]] = OrderedDict()
        self._noted: OrderedDict[str, float] = OrderedDict()
        self._lock = threading.Lock()

    def note_refusal(self, client: str, every_s: float = 60.0) -> bool:
        """Should a refusal (401, 403) to ``client`` (an address and a user) go into the audit trail?
        At most one a minute for each: a flood of wrong tokens is one row a minute, not a write per
        request."""
        now = time.monotonic()
        with self._lock:
            last = self._noted.get(client)
            if last is not None and now - last < every_s:
                return False
            self._noted[client] = now
            self._noted.move_to_end(client)
            while len(self._noted) > CLIENTS_KEPT:
                self._noted.popitem(last=False)
            return True

    def _recent(self, client: str, now: float) -> deque[float]:
        times = self._failed.get(client, deque())
        while times and now - times[0] > self.window_s:
            times.popleft()
        return times

    def wait_s(self, client: str) -> float:
        """How long ``client`` must wait before its next password is heard (0: now)."""
        now = time.monotonic()
        with self._lock:
            times = self._recent(client, now)
            return 0.0 if len(times) < self.failures else self.window_s - (now - times[0])

    def failed(self, client: str) -> None:
        now = time.monotonic()
        with self._lock:
            times = self._recent(client, now)
            times.append(now)
            self._failed[client] = times
            self._failed.move_to_end(client)
            while len(self._failed) > CLIENTS_KEPT:
                self._failed.popitem(last=False)


class TooManyStreams(Exception):
    """The user holds `STREAMS_PER_USER` open streams already."""


class StreamQuota:
    """Open event streams per user: each polls the lab database, so one viewer's 800 streams made
    every other user wait seconds."""

    def __init__(self, per_user: int = STREAMS_PER_USER) -> None:
        self.per_user = per_user
        self._open: dict[str, int] = {}
        self._lock = threading.Lock()

    def take(self, user: str) -> None:
        with self._lock:
            if self._open.get(user, 0) >= self.per_user:
                raise TooManyStreams(user)
            self._open[user] = self._open.get(user, 0) + 1

    def give_back(self, user: str) -> None:
        with self._lock:
            left = self._open.get(user, 0) - 1
            if left > 0:
                self._open[user] = left
            else:
                self._open.pop(user, None)


# Nothing is loaded from elsewhere and nothing runs inline: scripts, styles and images come from
# this server only. Inline style *attributes* are allowed (a progress bar's width is one); they
# cannot run code. No page may be framed (clickjacking), forms post only here.
CSP = ("default-src 'none'; script-src 'self'; style-src 'self'; style-src-attr 'unsafe-inline'; "
       "img-src 'self'; connect-src 'self'; form-action 'self'; frame-ancestors 'none'; base-uri 'none'")
HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff", "X-Frame-Options": "DENY",
           "Referrer-Policy": "no-referrer", "Cross-Origin-Opener-Policy": "same-origin"}
HSTS = "max-age=31536000"


class SecurityHeaders:
    """Every answer's security headers (OWASP ASVS 4.0.3 V14.4): those of `HEADERS`; ``Cache-Control:
    no-store`` unless the answer set its own (a page shown to one user must stay out of shared and
    browser caches); HSTS when the request came over HTTPS (directly, or through a trusted proxy)."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        https = scope.get("scheme") == "https"

        async def with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = MutableHeaders(scope=message)
                for name, value in HEADERS.items():
                    headers[name] = value
                if "cache-control" not in headers:
                    headers["Cache-Control"] = "no-store"
                if https:
                    headers["Strict-Transport-Security"] = HSTS
            await send(message)

        await self.app(scope, receive, with_headers)

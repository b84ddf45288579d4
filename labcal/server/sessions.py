"""Web sessions: a signed cookie naming a session the server holds, and its CSRF token.

The cookie carries only a random session id and its HMAC-SHA-256 under a secret the server draws at
start (``id.signature``): a forged or altered cookie is refused before any lookup, and nothing about
the user travels in it. It is HttpOnly (no script reads it), SameSite=Strict (no other site's page
sends it) and Secure when the request came over HTTPS. The sessions live in the server's memory: a
restart signs everybody out, and logging out ends the session on the server, not only in the browser.

Every form carries the session's CSRF token (a hidden field) and every POST is refused unless it
matches (compared in constant time) — the login form too, through a session opened, without a user,
when the form is shown. Signing in issues a new session id (an id known before sign-in is worthless
after it).

Sessions expire after `IDLE_S` without a request and `MAX_S` in all.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
import time
from dataclasses import dataclass, field

COOKIE = "labcal_session"
IDLE_S = 8 * 3600.0  # a shift
MAX_S = 24 * 3600.0
MAX_SESSIONS = 10_000  # the oldest go first beyond this: a flood of anonymous visits stays bounded


@dataclass
class Session:
    id: str
    csrf: str
    user: str | None = None
    created: float = field(default_factory=time.monotonic)
    seen: float = field(default_factory=time.monotonic)


class Sessions:
    """The server's open sessions."""

    def __init__(self, secret: bytes | None = None) -> None:
        self._secret = secret or secrets.token_bytes(32)
        self._open: dict[str, Session] = {}
        self._lock = threading.Lock()

    def _sign(self, sid: str) -> str:
        return hmac.new(self._secret, sid.encode("ascii"), hashlib.sha256).hexdigest()

    def cookie(self, session: Session) -> str:
        return f"{session.id}.{self._sign(session.id)}"

    def open(self, user: str | None = None) -> Session:
        session = Session(secrets.token_urlsafe(32), secrets.token_urlsafe(32), user)
        with self._lock:
            if len(self._open) >= MAX_SESSIONS:
                oldest = min(self._open.values(), key=lambda s: s.seen)
                del self._open[oldest.id]
            self._open[session.id] = session
        return session

    def get(self, cookie: str | None) -> Session | None:
        """The live session a cookie names, or None (absent, forged, ended or expired)."""
        if not cookie or "." not in cookie:
            return None
        sid, _, signature = cookie.rpartition(".")
        try:
            if not hmac.compare_digest(signature, self._sign(sid)):
                return None
        except (TypeError, UnicodeEncodeError):  # not ASCII: not ours
            return None
        now = time.monotonic()
        with self._lock:
            session = self._open.get(sid)
            if session is None:
                return None
            if now - session.seen > IDLE_S or now - session.created > MAX_S:
                del self._open[sid]
                return None
            session.seen = now
            return session

    def end(self, session: Session) -> None:
        with self._lock:
            self._open.pop(session.id, None)

    def sign_in(self, old: Session | None, user: str) -> Session:
        """A new session for ``user``; the anonymous one it replaces ends."""
        if old is not None:
            self.end(old)
        return self.open(user)

    def end_user(self, user: str) -> None:
        """End every session of ``user`` (disabled)."""
        with self._lock:
            for sid in [s.id for s in self._open.values() if s.user == user]:
                del self._open[sid]


def csrf_ok(session: Session | None, given: str | None) -> bool:
    """Does a form's CSRF token match its session's?"""
    return session is not None and bool(given) and hmac.compare_digest(session.csrf, str(given))

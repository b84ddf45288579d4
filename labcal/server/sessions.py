"""Web sessions: a signed cookie naming a session the server holds, and its CSRF token; and the
sign-in form's CSRF token, which needs no session.

The cookie carries only a random session id and its HMAC-SHA-256 under a secret the server draws at
start (``id.signature``): a forged or altered cookie is refused before any lookup, and nothing about
the user travels in it. It is HttpOnly (no script reads it), SameSite=Strict (no other site's page
sends it) and Secure when the request came over HTTPS. The sessions live in the server's memory: a
restart signs everybody out, and logging out ends the session on the server, not only in the browser.

Every form carries the session's CSRF token (a hidden field) and every POST is refused unless it
matches (compared in constant time). A session exists only once someone has signed in: the sign-in
form is protected by a signed double-submit token instead (`login_token`: a random nonce and its
HMAC, sent both as a cookie of its own and in the form; the POST must bring the two, equal and
signed by this server), so that anonymous visitors cost the server no memory and cannot crowd the
signed-in out of the session table. Signing in issues a new session id.

Sessions expire after `IDLE_S` without a request and `MAX_S` in all — OWASP ASVS 4.0.3 level 2
(3.3.2: re-authentication within 12 hours; 3.3.3 — 30 minutes idle, ASVS's own level-2 figure for
"a typical" application). A lab that wants a shift's idle time sets it (`labcal serve
--session-idle`) and says so in its risk assessment. Each user has at most `PER_USER` sessions.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import threading
import time
from dataclasses import dataclass, field

COOKIE = "labcal_session"
LOGIN_COOKIE = "labcal_login"  # the sign-in form's double-submit token
IDLE_S = 30 * 60.0
MAX_S = 12 * 3600.0
MAX_SESSIONS = 10_000  # the least recently seen go first beyond this
PER_USER = 20  # a user's oldest session ends when they open one more


@dataclass
class Session:
    id: str
    csrf: str
    user: str | None = None
    created: float = field(default_factory=time.monotonic)
    seen: float = field(default_factory=time.monotonic)


class Sessions:
    """The server's open sessions."""

    def __init__(self, secret: bytes | None = None, idle_s: float = IDLE_S, max_s: float = MAX_S) -> None:
        self._secret = secret or secrets.token_bytes(32)
        self._open: dict[str, Session] = {}
        self._lock = threading.Lock()
        self.idle_s, self.max_s = idle_s, max_s

    def _sign(self, sid: str) -> str:
        return hmac.new(self._secret, sid.encode("ascii"), hashlib.sha256).hexdigest()

    def cookie(self, session: Session) -> str:
        return f"{session.id}.{self._sign(session.id)}"

    def login_token(self, cookie: str | None = None) -> str:
        """The sign-in form's CSRF token: ``cookie`` again if it is one of ours, else a new one."""
        if cookie and self._signed(cookie, "login:"):
            return cookie
        nonce = secrets.token_urlsafe(32)
        return f"{nonce}.{self._sign('login:' + nonce)}"

    def login_token_ok(self, cookie: str | None, given: str | None) -> bool:
        """Does the sign-in form's token match its cookie, and did this server make it?"""
        return (bool(cookie) and bool(given) and hmac.compare_digest(str(cookie), str(given))
                and self._signed(str(cookie), "login:"))

    def _signed(self, value: str, purpose: str) -> bool:
        nonce, dot, signature = value.rpartition(".")
        try:
            return bool(dot) and hmac.compare_digest(signature, self._sign(purpose + nonce))
        except (TypeError, UnicodeEncodeError):  # not ASCII: not ours
            return False

    def open(self, user: str) -> Session:
        """A new session for ``user`` (signed in)."""
        session = Session(secrets.token_urlsafe(32), secrets.token_urlsafe(32), user)
        with self._lock:
            theirs = [s for s in self._open.values() if s.user == user]
            if len(theirs) >= PER_USER:
                del self._open[min(theirs, key=lambda s: s.seen).id]
            if len(self._open) >= MAX_SESSIONS:
                oldest = min(self._open.values(), key=lambda s: s.seen)
                del self._open[oldest.id]
            self._open[session.id] = session
        return session

    def get(self, cookie: str | None) -> Session | None:
        """The live session a cookie names, or None (absent, forged, ended or expired)."""
        if not cookie or "." not in cookie:
            return None
        if not self._signed(cookie, ""):
            return None
        sid = cookie.rpartition(".")[0]
        now = time.monotonic()
        with self._lock:
            session = self._open.get(sid)
            if session is None:
                return None
            if now - session.seen > self.idle_s or now - session.created > self.max_s:
                del self._open[sid]
                return None
            session.seen = now
            return session

    def end(self, session: Session) -> None:
        with self._lock:
            self._open.pop(session.id, None)

    def sign_in(self, old: Session | None, user: str) -> Session:
        """A new session for ``user``; the one it replaces (if any) ends."""
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

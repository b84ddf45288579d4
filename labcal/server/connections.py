"""Connections that cannot hold the server: a deadline for every request head, and a ceiling on
open connections below the process's open-file limit.

uvicorn times out an idle kept-alive connection (``timeout_keep_alive``) but not a connection that
has started a request and never finishes its head: 1,100 such connections used up the open-file
limit (1,024), after which the server accepted nothing more and logged a traceback per failed
``accept``. Here, as an h11 protocol of uvicorn's with two additions:

- a request head must arrive within `HEAD_S` of the connection opening (or of the previous answer),
  else the connection is closed;
- at most ``limit`` connections are open (`connection_limit`: the open-file limit less a reserve for
  the database, the templates and the logs). One more evicts the oldest connection still waiting
  for its head — a client that is sending a request gets in, however many half-open connections
  there are; only when every open connection is busy with a request is the newcomer closed.
"""

from __future__ import annotations

import asyncio
import resource
from collections import OrderedDict

from uvicorn.protocols.http.h11_impl import H11Protocol

HEAD_S = 10.0
BACKLOG = 64  # connections asyncio may accept in one go, before any of them is counted here
RESERVED_FILES = 128 + BACKLOG  # kept for the database, the templates, the static files and the logs,
# and for the connections accepted but not yet counted
WANTED_FILES = 65_536


def connection_limit() -> int:
    """How many connections the server may hold: the open-file limit raised as far as the system
    allows (up to `WANTED_FILES`) less `RESERVED_FILES`."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    wanted = WANTED_FILES if hard == resource.RLIM_INFINITY else min(WANTED_FILES, hard)
    if soft != resource.RLIM_INFINITY and soft < wanted:
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (wanted, hard))
            soft = wanted
        except (ValueError, OSError):
            pass
    files = WANTED_FILES if soft == resource.RLIM_INFINITY else soft
    return max(16, files - RESERVED_FILES)


def guarded_protocol(limit: int, head_s: float = HEAD_S) -> type[H11Protocol]:
    """uvicorn's h11 protocol with a head deadline and a ceiling of ``limit`` open connections."""
    waiting: OrderedDict[GuardedH11, None] = OrderedDict()  # connections waiting for a head, oldest first

    class GuardedH11(H11Protocol):
        _head_timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            if len(self.connections) > limit:
                if waiting:
                    oldest = next(iter(waiting))
                    oldest._drop()
                else:  # every connection is busy with a request: this one waits its turn outside
                    self._drop()
                    return
            self._await_head()

        def _await_head(self) -> None:
            waiting[self] = None
            self._head_timer = self.loop.call_later(head_s, self._drop)

        def _head_arrived(self) -> None:
            waiting.pop(self, None)
            if self._head_timer is not None:
                self._head_timer.cancel()
                self._head_timer = None

        def _drop(self) -> None:
            self._head_arrived()
            self.connections.discard(self)
            if not self.transport.is_closing():
                self.transport.close()

        def handle_events(self) -> None:
            before = self.cycle
            super().handle_events()
            if self.cycle is not before:  # a request's head was read
                self._head_arrived()

        def on_response_complete(self) -> None:
            before = self.cycle
            super().on_response_complete()
            if not self.transport.is_closing() and self.cycle is before and self not in waiting:
                self._await_head()  # kept alive: the next request's head has the same deadline

        def connection_lost(self, exc: Exception | None) -> None:
            self._head_arrived()
            super().connection_lost(exc)

    return GuardedH11

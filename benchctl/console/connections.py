"""The console server's connections, bounded, so that no flood of connections takes ALL OFF away.

uvicorn accepts every connection and waits for a request's headers without a deadline: round 4 held about 21,000
idle or trickling connections open until `accept` failed with EMFILE, and nothing answered, ALL OFF included. The
HTTP protocol here is uvicorn's h11 protocol with three rules added:
- at most `Limits.max_connections` connections are open at once (a quarter of the descriptors the process may open,
  at most MAX_CONNECTIONS): the rest stay free for the devices and files. One more displaces the oldest connection
  that has not yet sent a whole request's headers (nothing on it is authenticated yet), or is closed at once when
  every connection is busy with a request; connections are accepted BACKLOG at a time, so the descriptors in
  flight stay bounded too;
- a connection must have sent its whole request (headers and body) within `Limits.request_s` of opening or of its
  last response, else it is closed: a trickle of bytes holds nothing for long;
- a WebSocket, once upgraded (after the token and Origin checks), is neither displaced nor timed: the open page's
  socket is the console's reserved channel, and ALL OFF is sent over it (app.py), so it needs no new connection.
A connection refused or closed here costs its descriptor for microseconds. `benchctl laser off` from a shell needs no
connection at all (it signals the console, which switches emission off on a thread of its own).
"""

from __future__ import annotations

import asyncio
import resource
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

MAX_CONNECTIONS = 128  # a page needs its socket and a few requests at a time
# Connections waiting to be accepted, and so accepted at once in one burst (asyncio takes up to the backlog before
# any of them reaches the protocol, which then closes what is over the limit): it bounds the descriptors in flight.
BACKLOG = 64
REQUEST_S = 10.0  # from opening, or from the last response, to a whole request


@dataclass(frozen=True)
class Limits:
    """How many connections the server keeps open at once, and how long one may take to send a request."""

    max_connections: int
    request_s: float = REQUEST_S

    @classmethod
    def for_this_process(cls) -> Limits:
        """MAX_CONNECTIONS, or a quarter of the descriptors this process may open where that is fewer."""
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        available = soft if soft != resource.RLIM_INFINITY else 4 * MAX_CONNECTIONS
        return cls(max(8, min(MAX_CONNECTIONS, available // 4)))


def guarded_protocol(limits: Limits) -> type[asyncio.Protocol]:
    """uvicorn's h11 HTTP protocol with `limits` (see the module docstring), for `uvicorn.Config(http=...)`; each
    call makes a class of its own, whose connections count against each other only."""
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    waiting: OrderedDict[Guarded, None] = OrderedDict()  # open, not yet a whole request's headers: oldest first

    class Guarded(H11Protocol):
        refused = False
        deadline: asyncio.TimerHandle | None = None

        def connection_made(self, transport: Any) -> None:
            if len(self.server_state.connections) >= limits.max_connections and not _displace_one():
                self.refused = True
                transport.abort()
                return
            super().connection_made(transport)
            self._expect_request()

        def _expect_request(self) -> None:
            """From now on the client has `request_s` to send a whole request."""
            self._stop_timer()
            waiting[self] = None
            self.deadline = self.loop.call_later(limits.request_s, self._too_slow)

        def _stop_timer(self) -> None:
            if self.deadline is not None:
                self.deadline.cancel()
                self.deadline = None

        def _too_slow(self) -> None:
            self.deadline = None
            if self.conn.their_state not in (h11.DONE, h11.MUST_CLOSE) and not self.transport.is_closing():
                waiting.pop(self, None)
                self.transport.abort()

        def handle_events(self) -> None:
            super().handle_events()
            if self.conn.their_state is not h11.IDLE:  # the request's headers are in: no longer displaceable
                waiting.pop(self, None)

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing():
                self._expect_request()

        def handle_websocket_upgrade(self, event: h11.Request) -> None:
            waiting.pop(self, None)
            self._stop_timer()
            super().handle_websocket_upgrade(event)

        def connection_lost(self, exc: Exception | None) -> None:
            if self.refused:
                return
            waiting.pop(self, None)
            self._stop_timer()
            super().connection_lost(exc)

    def _displace_one() -> bool:
        """Close the oldest connection still waiting for its request's headers; False when there is none."""
        while waiting:
            oldest, _ = waiting.popitem(last=False)
            if not oldest.transport.is_closing():
                oldest.transport.abort()
                return True
        return False

    return Guarded

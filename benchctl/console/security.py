"""Who may use the console: a per-start token, and Host and Origin checked on every request and socket.

Three ways in are closed before anything reaches a device:
- *Another site* (cross-site request forgery): a web page on any site can send requests to 127.0.0.1. Browsers put
  the page's Origin on every such request and on every WebSocket handshake; one that is not the console's own is
  refused, and a request that can change a device (any method but GET and HEAD, and the WebSocket, whose messages
  keep the light on) must carry the console's Origin: a script sends it as it sends the token.
- *DNS rebinding*: a hostile name made to resolve to 127.0.0.1 arrives with its own name in the Host header, which
  must be an address the console serves on.
- *Another web server on this computer*: cookies ignore ports, so a token kept in a cookie would be sent to every
  local server (round 4 found it so). The token is never a cookie: the page is opened with it in its URL
  (`/?token=...`, as printed), reads it from there and sends it with each request as the `X-Benchctl-Token` header
  and in its WebSocket's URL; another origin can read neither. Every response says `Referrer-Policy: no-referrer`.
The page's static files (`/static/...`) hold nothing secret and are served without the token.
"""

from __future__ import annotations

import secrets
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from typing import Any
from urllib.parse import parse_qsl

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

TOKEN_PARAMETER = "token"
TOKEN_HEADER = "x-benchctl-token"
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
PUBLIC_PREFIX = "/static/"  # the page's own files: nothing secret, no device behind them


def new_token() -> str:
    """A fresh random token (256 bits), one per console start."""
    return secrets.token_urlsafe(32)


class Access:
    """The rules of one console start: its token, and the host names (with port) it answers to."""

    def __init__(self, token: str, port: int, hosts: Iterable[str] = LOOPBACK_NAMES) -> None:
        self.token = token
        self.port = port
        self.hosts = frozenset(f"{host}:{port}".lower() for host in hosts)
        self.origins = frozenset(f"http://{host}" for host in self.hosts)

    def valid_token(self, given: str | None) -> bool:
        return given is not None and secrets.compare_digest(given.encode(), self.token.encode())

    def refusal(self, headers: dict[str, str], query_token: str | None, *, changes: bool = False,
                public: bool = False) -> str | None:
        """Why a request with these (lower-case) headers is refused, or None when it may pass. `changes`: it can
        change a device (its Origin is then required); `public`: one of the page's static files (no token)."""
        host = headers.get("host", "").lower()
        if host not in self.hosts:
            return f"Host {host or '(none)'!r} is not this console's address"
        origin = headers.get("origin")
        if origin is not None and origin.lower() not in self.origins:
            return f"Origin {origin!r} is not this console's page"
        if public:
            return None
        if not any(self.valid_token(value) for value in (query_token, headers.get(TOKEN_HEADER))):
            return "no valid console token (open the URL the console printed)"
        if changes and origin is None:
            return ("a request that changes a device needs the Origin header of the console's page "
                    f"(scripts: Origin: http://127.0.0.1:{self.port})")
        return None


class AccessMiddleware:
    """Refuses (HTTP 403, or a WebSocket closed before its handshake) what `Access.refusal` refuses."""

    def __init__(self, app: ASGIApp, access: Access) -> None:
        self.app = app
        self.access = access

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {key.decode("latin-1").lower(): value.decode("latin-1") for key, value in scope["headers"]}
        query = parse_qsl(scope.get("query_string", b"").decode("latin-1"), keep_blank_values=True)
        query_token = next((value for key, value in query if key == TOKEN_PARAMETER), None)
        reading = scope["type"] == "http" and scope["method"] in ("GET", "HEAD")
        reason = self.access.refusal(headers, query_token, changes=not reading,
                                     public=reading and scope["path"].startswith(PUBLIC_PREFIX))
        if reason is not None:
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": reason[:120]})
            else:
                await _plain(send, 403, f"refused: {reason}\n")
            return
        await self.app(scope, receive, _no_referrer(send) if scope["type"] == "http" else send)


def _no_referrer(send: Send) -> Send:
    """`send` adding Referrer-Policy: no-referrer to the response (the page's URL holds the token)."""

    async def sending(message: Message) -> None:
        if message["type"] == "http.response.start":
            message["headers"] = [*message.get("headers", []), (b"referrer-policy", b"no-referrer")]
        await send(message)

    return sending


async def _plain(send: Send, status: int, text: str) -> None:
    body = text.encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"), (b"referrer-policy", b"no-referrer"),
                            (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})

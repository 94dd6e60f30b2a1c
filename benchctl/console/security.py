"""Who may use the console: a per-start token, and Host and Origin checked on every request and socket.

A web page on any site can send requests to 127.0.0.1 (cross-site request forgery), and DNS rebinding can make a
hostile name resolve to 127.0.0.1 so that its pages count as same-origin. Neither may switch a laser on, so an
ASGI middleware in front of every route refuses, before anything reaches a device:
- a request or WebSocket without the token: given once in the URL (`?token=...`), which sets a cookie
  (HttpOnly, SameSite=Strict) and redirects to the same URL without it; scripts may send it in an
  `X-Benchctl-Token` header instead;
- a Host header that is not the address the console serves on (a rebound name arrives with its own name);
- an Origin header that is not the console's own (browsers send one with every cross-site request and every
  WebSocket handshake; a client that sends none is not a browser page and still needs the token).
"""

from __future__ import annotations

import secrets
from collections.abc import Awaitable, Callable, Iterable, MutableMapping
from http.cookies import SimpleCookie
from typing import Any
from urllib.parse import parse_qsl, urlencode

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

TOKEN_PARAMETER = "token"
TOKEN_HEADER = "x-benchctl-token"
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")


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
        self.cookie = f"benchctl_console_{port}"  # cookies ignore ports: two consoles keep two cookies

    def valid_token(self, given: str | None) -> bool:
        return given is not None and secrets.compare_digest(given.encode(), self.token.encode())

    def refusal(self, headers: dict[str, str], query_token: str | None) -> str | None:
        """Why a request with these (lower-case) headers is refused, or None when it may pass."""
        host = headers.get("host", "").lower()
        if host not in self.hosts:
            return f"Host {host or '(none)'!r} is not this console's address"
        origin = headers.get("origin")
        if origin is not None and origin.lower() not in self.origins:
            return f"Origin {origin!r} is not this console's page"
        cookie = SimpleCookie()
        try:
            cookie.load(headers.get("cookie", ""))
        except Exception:  # a malformed cookie header carries no token
            cookie = SimpleCookie()
        given = [query_token, headers.get(TOKEN_HEADER), cookie[self.cookie].value if self.cookie in cookie else None]
        if not any(self.valid_token(value) for value in given):
            return "no valid console token (open the URL the console printed)"
        return None


class AccessMiddleware:
    """Refuses (HTTP 403, or a WebSocket closed before its handshake) what `Access.refusal` refuses; turns a valid
    token in the URL into a cookie and a redirect to the same URL without it."""

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
        reason = self.access.refusal(headers, query_token)
        if reason is not None:
            if scope["type"] == "websocket":
                await send({"type": "websocket.close", "code": 1008, "reason": reason[:120]})
            else:
                await _plain(send, 403, f"refused: {reason}\n")
            return
        if query_token is not None and scope["type"] == "http":
            rest = urlencode([(key, value) for key, value in query if key != TOKEN_PARAMETER])
            location = scope["path"] + (f"?{rest}" if rest else "")
            cookie = f"{self.access.cookie}={self.access.token}; Path=/; HttpOnly; SameSite=Strict"
            await _plain(send, 303, "", [(b"location", location.encode()), (b"set-cookie", cookie.encode())])
            return
        await self.app(scope, receive, send)


async def _plain(send: Send, status: int, text: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    body = text.encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/plain; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()), *(headers or [])]})
    await send({"type": "http.response.body", "body": body})

"""`benchctl console`: start the console's process, serve the page with uvicorn, and stop safely.

The server binds 127.0.0.1 unless told otherwise (another address is said loudly: anyone who can reach it and has
the token can switch the laser on). A termination signal (Ctrl-C, SIGTERM from `benchctl laser off` in another
shell) switches emission off and lets go of the laser at once, then the server stops and every device is closed.
"""

from __future__ import annotations

import ipaddress
import socket
import threading
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import Any

import uvicorn

from benchctl.console.app import create_app
from benchctl.console.connections import BACKLOG, Limits, guarded_protocol
from benchctl.console.core import Console
from benchctl.console.laser import DEADMAN_S
from benchctl.console.security import LOOPBACK_NAMES, Access, new_token
from benchctl.errors import BenchctlError
from benchctl.profiles import Profile

# torch threads in the console's process (the live view's light; holograms run in their own process). On a busy
# 2-core machine one thread recomputed the light twice as fast as two, which waited for each other (docs/console.md).
LIVE_VIEW_THREADS = 1
STOPPED_UNKNOWN = "emission state UNKNOWN, possibly ON: check the laser"


class _Server(uvicorn.Server):
    """uvicorn's server, switching emission off the moment a termination signal arrives (before shutting down)."""

    def __init__(self, config: uvicorn.Config, console: Console) -> None:
        super().__init__(config)
        self.console = console

    def handle_exit(self, sig: int, frame: FrameType | None) -> None:
        threading.Thread(target=self.console.emergency_off, name="console emission off").start()
        super().handle_exit(sig, frame)


def is_loopback(address: str) -> bool:
    try:
        return ipaddress.ip_address(address.strip("[]")).is_loopback
    except ValueError:
        return address == "localhost"


def url_host(name: str) -> str:
    """`name` as a URL and a Host header write it (an IPv6 address in brackets)."""
    name = name.strip("[]")
    return f"[{name}]" if ":" in name else name


def allowed_hosts(bind: str) -> tuple[str, ...]:
    """The names a browser may put in the Host header: the loopback names, and the address the console listens
    on; for every interface (0.0.0.0, ::) this computer's own names and addresses, as other computers reach it."""
    if is_loopback(bind):
        return LOOPBACK_NAMES
    try:
        everywhere = ipaddress.ip_address(bind.strip("[]")).is_unspecified
    except ValueError:
        everywhere = False
    if not everywhere:
        return (*LOOPBACK_NAMES, url_host(bind))
    names = {socket.gethostname(), socket.getfqdn()}
    try:
        names |= {str(info[4][0]) for info in socket.getaddrinfo(socket.gethostname(), None)}
    except OSError:  # a name that does not resolve: the names alone
        pass
    return (*LOOPBACK_NAMES, *sorted(url_host(name) for name in names))


def listen(bind: str, port: int) -> socket.socket:
    """A listening socket on `bind`:`port` (0: a free port); one line naming the address when it cannot be had."""
    family = socket.AF_INET6 if ":" in bind.strip("[]") else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((bind.strip("[]"), port))
    except OSError as exc:
        sock.close()
        raise BenchctlError(f"cannot listen on {bind}:{port}: {exc.strerror or exc} (choose another --port)") from None
    sock.listen(BACKLOG)
    return sock


def server_config(app: Any, limits: Limits | None = None) -> uvicorn.Config:
    """uvicorn's settings for the console: its connections bounded (`connections.Limits`, this process's by
    default), quiet, and a short graceful shutdown."""
    return uvicorn.Config(app, log_level="warning", lifespan="off", timeout_graceful_shutdown=2, backlog=BACKLOG,
                          http=guarded_protocol(limits or Limits.for_this_process()))


def serve(profile: Profile, *, port: int, bind: str = "127.0.0.1", out: Path = Path("runs"),
          procedures: Path | None = None, deadman_s: float = DEADMAN_S, say: Callable[[str], None] = print) -> None:
    """Run the console until a termination signal; every device is closed (emission off first) however it ends.
    BenchctlError (after the laser's own line) when emission could not be confirmed off."""
    import torch

    torch.set_num_threads(LIVE_VIEW_THREADS)
    sock = listen(bind, port)
    port = sock.getsockname()[1]
    access = Access(new_token(), port, allowed_hosts(bind))
    console = Console(profile, out, deadman_s=deadman_s, procedures_dir=procedures)
    try:
        console.start()
        for line in list(console.events):
            say(line)
        config = server_config(create_app(console, access))
        host = "127.0.0.1" if is_loopback(bind) else url_host(bind)
        if host.strip("[]") in ("0.0.0.0", "::"):
            host = url_host(socket.gethostname())
        if not is_loopback(bind):
            say(f"WARNING: the console listens on {bind}, not only on this computer: anyone who can reach "
                f"{bind}:{port} and has the token can switch the laser on")
        say(f"benchctl console on profile {profile.name!r}: open http://{host}:{port}/?token={access.token}")
        say("stop it with Ctrl-C (emission off, devices closed)")
        _Server(config, console).run(sockets=[sock])
    finally:
        sock.close()
        unknown = console.close()
        if unknown is not None:  # the last word is what is known, and the exit status says it went wrong
            say(f"laser: {unknown}")
            raise BenchctlError(f"console stopped: {STOPPED_UNKNOWN}") from None
        say("console stopped: emission off, devices closed")

"""The laser watchdog: a process that switches emission off when the process holding the laser dies without doing it.

Python's clean-up (finally blocks, `with`, the signal handlers of benchctl.devices.safety) cannot run when the
holder is killed with SIGKILL (the kernel's out-of-memory killer sends it) or crashes in native code (a camera
library's SIGSEGV). So before a Laser first switches emission on, it starts this watchdog: a child process in a
session of its own (Ctrl-C and a closed terminal do not reach it) that holds the reading end of a pipe, whose
writing end only the holder has (and children it forks, which share its port and locks too: the pipe ends when the
last of them does). An orderly close writes "disarm" and the watchdog exits. If instead the pipe reaches its end
with nothing written, the holder is gone: the kernel has closed its ports and released its device locks, and the
watchdog connects to the laser with the holder's own
configuration, driver and port, which switches emission off on every channel and reads it back (Laser.open), then
says on its standard error (the holder's terminal) what it found and did.

Why a watchdog rather than capturing in a child process: the laser is held by runs, `laser on` and the console, and
what kills the holder may be any native library in it (the camera's, OpenCV, X11, torch) or the kernel itself; a
process that outlives the holder covers every way it can die, through the same switch-off and read-back as every
other path. Capturing in a child would cover the camera only, copy every frame between processes, and still leave
emission on when the holder itself is killed.

Until the holder dies the watchdog is a bare interpreter waiting on the pipe: it imports the laser drivers only when
it has to act.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from typing import Any

DISARM = b"disarm\n"
PORT_WAIT_S = 15.0  # how long the watchdog waits for the port (another command may hold it a moment)


class Watchdog:
    """A running watchdog for the laser configured by `config_json` (LaserConfig as JSON); `disarm` before an
    orderly exit."""

    def __init__(self, config_json: bytes) -> None:
        read_end, write_end = os.pipe()
        try:
            self._process = subprocess.Popen([sys.executable, "-m", __name__, str(os.getpid())], stdin=read_end,
                                             stdout=subprocess.DEVNULL, start_new_session=True)
        except BaseException:
            os.close(write_end)
            raise
        finally:
            os.close(read_end)
        self._fd: int | None = write_end
        os.write(write_end, config_json + b"\n")

    def disarm(self) -> None:
        """Tell the watchdog this process has let go of the laser as it should, and let it end."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            os.write(fd, DISARM)
        finally:
            os.close(fd)
        try:
            self._process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            pass  # it ends on its own once it reads the pipe


def _switch_off(config_json: bytes, holder: str) -> int:
    """Connect to the laser (which switches every channel off and reads it back) once the port is free; the exit
    status: 0 when emission is off."""
    import msgspec

    from benchctl.devices.errors import DeviceBusy
    from benchctl.devices.laser import open_laser
    from benchctl.devices.laser.base import UNKNOWN_EMISSION
    from benchctl.devices.lock import set_command
    from benchctl.errors import BenchctlError
    from benchctl.profiles import LaserConfig

    set_command("benchctl laser watchdog")
    said = f"benchctl laser watchdog: the process that held the laser ({holder}) ended without switching it off"
    give_up = time.monotonic() + PORT_WAIT_S
    while True:
        try:
            with open_laser(msgspec.json.decode(config_json, type=LaserConfig)) as laser:
                found = laser.connect_report()
            print(f"{said}; emission off on every channel ({'; '.join(found) or 'none was emitting'})",
                  file=sys.stderr, flush=True)
            return 0
        except DeviceBusy as exc:
            if time.monotonic() < give_up:
                time.sleep(0.1)
                continue
            failure: Any = exc
        except BenchctlError as exc:
            failure = exc
        print(f"{said}, and the watchdog could not switch it off: {failure}; {UNKNOWN_EMISSION}", file=sys.stderr,
              flush=True)
        return 1


def main(argv: list[str]) -> int:
    """The watchdog process: the configuration line, then wait for "disarm" or the end of the pipe."""
    for sig in (signal.SIGINT, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    pipe = sys.stdin.buffer
    config_json = pipe.readline().rstrip(b"\n")
    if pipe.read() == DISARM or not config_json:
        return 0
    return _switch_off(config_json, f"pid {argv[1]}" if len(argv) > 1 else "pid ?")


if __name__ == "__main__":
    sys.exit(main(sys.argv))

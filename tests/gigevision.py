"""GigE Vision scenarios against Aravis's fake GigE Vision camera (`arv-fake-gv-camera-0.8 -i 127.0.0.1`), run by
tests/test_genicam_gv.py inside a network namespace of their own (`unshare -rn`): there the only network is
loopback, so GigE Vision discovery, which broadcasts on every interface, reaches nothing else.

    python tests/gigevision.py SCENARIO JSON_ARGS    (prints one JSON line: what the test asserts on)
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

SERIAL = "GV01"


def fake_camera(lost_per_thousand: int = 0) -> subprocess.Popen[bytes]:
    """The fake GigE Vision camera on 127.0.0.1, started and answering discovery."""
    process = subprocess.Popen(["arv-fake-gv-camera-0.8", "-i", "127.0.0.1", "-s", SERIAL, "-r",
                                str(lost_per_thousand)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    from benchctl.devices.camera.aravis import genicam_cameras

    deadline = time.monotonic() + 20
    while not any(c.serial == SERIAL for c in genicam_cameras()):
        if time.monotonic() > deadline or process.poll() is not None:
            raise SystemExit("the fake GigE Vision camera did not start")
        time.sleep(0.1)
    return process


def mono8_ramp(frame_id: int, height: int, width: int) -> np.ndarray:
    """What the fake camera puts in a Mono8 frame at exposure 10 ms, gain 0: (x + y + frame id) mod 255."""
    y, x = np.mgrid[0:height, 0:width]
    return (x + y + frame_id) % 255


def streaming(args: dict[str, Any]) -> dict[str, Any]:
    """Discovery, then `frames` Mono8 captures through the driver; each kept frame compared with the ramp."""
    import rawpy

    from benchctl.devices.camera.aravis import genicam_cameras
    from benchctl.devices.camera.genicam import GenicamCamera
    from benchctl.profiles import CameraConfig

    camera = fake_camera(args["lost_per_thousand"])
    try:
        found = [[c.device_id, c.serial, c.protocol, c.address] for c in genicam_cameras()]
        config = CameraConfig(driver="genicam", serial=SERIAL, pixel_format="Mono8", region=(0, 0, 64, 24),
                              exposure_s=0.01, gain=0.0, image_timeout_s=args["image_timeout_s"],
                              frame_retries=args["frame_retries"])
        kept, refused, error = [], [], None
        with GenicamCamera(config) as driver:
            try:
                for frame in driver.capture(frames=args["frames"]):
                    with rawpy.imread(frame.path or __import__("io").BytesIO(frame.data)) as raw:
                        exact = bool(np.array_equal(raw.raw_image, mono8_ramp(frame.metadata["frame_id"], 24, 64)))
                    kept.append(exact)
                    refused += frame.metadata["incomplete_refused"]
            except Exception as exc:  # noqa: BLE001 - the test asserts on what was raised
                error = f"{type(exc).__name__}: {exc}"
        return {"found": found, "kept_exact": kept, "refused": refused, "error": error}
    finally:
        camera.kill()
        camera.wait()


def killed_run(args: dict[str, Any]) -> dict[str, Any]:
    """`benchctl run` of a power sweep on a profile whose camera is the fake GigE Vision camera; the camera is
    killed once the first sweep level is done; then `benchctl run --resume` with the camera back."""
    profile, procedure, out = args["profile"], args["procedure"], Path(args["out"])
    camera = fake_camera()
    run = subprocess.Popen([sys.executable, "-m", "benchctl", "run", procedure, "--profile", profile, "--out",
                            str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not _done(out, "sweep/green/0"):
        if time.monotonic() > deadline or run.poll() is not None:
            raise SystemExit(f"the run ended before its first sweep level: {run.communicate()}")
        time.sleep(0.005)
    camera.kill()
    camera.wait()
    stdout, stderr = run.communicate(timeout=240)
    (folder,) = out.iterdir()
    first = {path.name: path.read_bytes() for path in sorted((folder / "raw").rglob("*.dng"))}
    status = subprocess.run([sys.executable, "-m", "benchctl", "laser", "status", "--profile", profile],
                            capture_output=True, text=True, timeout=120)
    camera = fake_camera()
    try:
        resumed = subprocess.run([sys.executable, "-m", "benchctl", "run", "--resume", str(folder)],
                                 capture_output=True, text=True, timeout=240)
    finally:
        camera.kill()
        camera.wait()
    after = {str(path.relative_to(folder)): path.read_bytes() for path in sorted((folder / "raw").rglob("*.dng"))}
    events = [json.loads(line) for line in (folder / "steps.jsonl").read_text().splitlines()]
    return {"code": run.returncode, "stderr": stderr.strip().splitlines(), "laser_status": status.stdout,
            "first_files": sorted(first), "unchanged": [name for name in sorted(first)
                                                        if any(path.endswith(name) and data == first[name]
                                                               for path, data in after.items())],
            "resumed_code": resumed.returncode, "resumed_stderr": resumed.stderr.strip().splitlines(),
            "started": [e["step"] for e in events if e["event"] == "start"],
            "done": [e["step"] for e in events if e["event"] == "done"]}


def _done(out: Path, key: str) -> bool:
    for log in out.glob("*/steps.jsonl"):
        for line in log.read_text().splitlines():
            if line.endswith("}") and json.loads(line).get("event") == "done" and json.loads(line).get("step") == key:
                return True
    return False


SCENARIOS: dict[str, Callable[[dict[str, Any]], dict[str, Any]]] = {"streaming": streaming, "killed_run": killed_run}

if __name__ == "__main__":
    os.environ["BENCHCTL_ARAVIS_INTERFACES"] = "GigEVision"
    print(json.dumps(SCENARIOS[sys.argv[1]](json.loads(sys.argv[2]))))

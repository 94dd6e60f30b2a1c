"""Hardware profiles: one TOML file per bench, validated against a declared schema, loaded as frozen dataclasses.

The schema (SCHEMA below) lists every section and key with its type and bounds in one place; adding a section
means adding an entry there and a dataclass. Validation is strict: an unknown key (a misspelt `pitch` for
`pitch_um`) is an error that suggests the closest known key, never silently ignored. Every error is a
BenchctlError naming the file, the key path (`laser.channels[1].wavelength_nm`) and the bad value.
"""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from benchctl.dng import CFA_LAYOUTS
from benchctl.errors import BenchctlError
from benchctl.limits import check_pixels
from benchctl.schema import Field, check_table, fail

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

PROFILE_ENV = "BENCHCTL_PROFILE"
PROFILE_DIR = "hardware_profiles"
DEFAULT_PROFILE = "simulated"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")


_CHANNEL = {
    "name": Field("str"),
    # The laser unit's own channel number, as drivers address it; defaults to the position in the list, from 1.
    "index": Field("int", required=False, ge=0),
    "wavelength_nm": Field("float", ge=100, le=20000),  # the wavelengths optics.setup accepts (100 nm .. 20 um)
    "max_power_mw": Field("float", gt=0),
    "setpoint_mw": Field("float", ge=0),
    # Single-wavelength heads (cobolt, obis) have one serial port each; overrides laser.port.
    "port": Field("str", required=False),
}

LASER_DRIVERS = ("template", "cobolt", "obis")
SLM_DRIVERS = ("sim", "framebuffer")
CAMERA_DRIVERS = ("sim", "ptp", "gphoto2")

# The commands of a multi-channel laser unit with a simple line protocol ("template" driver). Placeholders:
# {channel} the channel's index, {mw} / {w} the power in mW / W. Replies with a power are read in `power_unit`.
_PROTOCOL = {
    "line_ending": Field("str", required=False, default="\r\n"),
    "set_power": Field("str"),
    "get_power": Field("str"),
    "enable": Field("str"),
    "disable": Field("str"),
    "get_measured": Field("str", required=False),
    "get_emission": Field("str", required=False),
    "get_status": Field("str", required=False),
    "identify": Field("str", required=False),
    "ok_reply": Field("str", required=False, default="OK"),
    "error_prefix": Field("str", required=False, default="ERR"),
    "echo": Field("bool", required=False, default=False),
    "power_unit": Field("str", required=False, default="mW", choices=("mW", "W")),
}

# The simulated bench's physics (docs/simulated_bench.md). Every key is optional; the defaults live in the Sim*Config
# dataclasses below, the one place that states them (the [sim] block of hardware_profiles/simulated.toml lists them).
_SIM = {
    "seed": Field("int", required=False, ge=0),
    "slm": Field("table", required=False, fields={
        "two_pi_nm": Field("float", required=False, gt=0),
        "gamma": Field("float", required=False, gt=0),
        "zero_order": Field("float", required=False, ge=0, le=1),
        "crosstalk_px": Field("float", required=False, ge=0),
    }),
    "beam": Field("table", required=False, fields={
        "waist_mm": Field("float", required=False, ge=0),
        "offset_mm": Field("float_pair", required=False),
        "tilt_mrad": Field("float_pair", required=False),
        "efficiency": Field("float", required=False, gt=0, le=1),
    }),
    "imaging": Field("table", required=False, fields={
        "magnification": Field("float", required=False, gt=0),
        "rotation_deg": Field("float", required=False),
        "offset_px": Field("float_pair", required=False),
        "stray_light": Field("float", required=False, ge=0, le=1),
    }),
    # Per laser channel: Zernike wavefront error at the SLM in waves (optics.aberration.ZERNIKE_TERMS' names).
    "aberration": Field("table_map", required=False, fields={
        name: Field("float", required=False) for name in ("astigmatism_oblique", "defocus", "astigmatism_vertical",
                                                          "coma_vertical", "coma_horizontal", "spherical")}),
    "sensor": Field("table", required=False, fields={
        "model": Field("str", required=False),
        "shape": Field("int_pair", required=False, gt=0),
        "margin": Field("int_pair", required=False, ge=0),
        "pixel_um": Field("float", required=False, gt=0),
        "cfa": Field("str", required=False, choices=tuple(CFA_LAYOUTS)),
        "bit_depth": Field("int", required=False, ge=8, le=16),
        "black_level": Field("int", required=False, ge=0),
        "full_well_e": Field("float", required=False, gt=0),
        "base_iso": Field("int", required=False, gt=0),
        "read_noise_e": Field("float", required=False, ge=0),
        "exposure_s": Field("float", required=False, gt=0),
        "iso": Field("int", required=False, gt=0),
        "readout_s": Field("float", required=False, ge=0),
        "response": Field("triple_map", required=False, ge=0),
    }),
}

SCHEMA: Mapping[str, Field] = {
    "name": Field("str", required=False),
    "description": Field("str", required=False, default=""),
    "optics": Field("table", required=False, fields={
        "distance_mm": Field("float", gt=0),
        "roi": Field("int_pair", gt=0),
        "iris_fraction": Field("float", required=False, gt=0),
        "model": Field("str", required=False),
    }),
    "slm": Field("table", required=False, fields={
        "driver": Field("str", required=False, default="sim", choices=SLM_DRIVERS),
        "device": Field("str", required=False),
        "width": Field("int", gt=0),
        "height": Field("int", gt=0),
        "pitch_um": Field("float", ge=0.1, le=1000),  # the pitches optics.setup accepts (0.1 um .. 1 mm)
        "bit_depth": Field("int", ge=1, le=16),
        "settle_ms": Field("float", required=False, default=100.0, ge=0),
        "flip_x": Field("bool", required=False, default=False),
        "flip_y": Field("bool", required=False, default=False),
        "phase_offset_rad": Field("float", required=False, default=0.0),
        "two_pi_gray": Field("float", required=False, gt=0),
        "grating_period_px": Field("float_pair", required=False, default=(0.0, 0.0)),
        "lut": Field("str_map", required=False, default={}),
    }),
    "laser": Field("table", required=False, fields={
        "driver": Field("str", required=False, default="template", choices=LASER_DRIVERS),
        "port": Field("str", required=False),
        "baudrate": Field("int", required=False, default=115200, gt=0),
        "timeout_s": Field("float", required=False, default=1.0, gt=0),
        "write_delay_s": Field("float", required=False, default=0.0, ge=0),
        "protocol": Field("table", required=False, fields=_PROTOCOL),
        "channels": Field("tables", fields=_CHANNEL, min_items=1),
    }),
    "camera": Field("table", required=False, fields={
        "driver": Field("str", required=False, default="sim", choices=CAMERA_DRIVERS),
        "model": Field("str", required=False, default=""),
        "usb_id": Field("str", required=False, default="04a9:32a0"),
        "transport": Field("str", required=False, default="usb", choices=("usb", "sim")),
        "exposure_s": Field("float", required=False, gt=0),
        "iso": Field("int", required=False, gt=0),
        "frames": Field("int", required=False, default=1, ge=1),
        "write_properties": Field("bool", required=False, default=False),
        "image_timeout_s": Field("float", required=False, default=90.0, gt=0),
        "gphoto2_path": Field("str", required=False, default="gphoto2"),
    }),
    "sim": Field("table", required=False, fields=_SIM),
}
SECTIONS = ("optics", "slm", "laser", "camera")


@dataclass(frozen=True)
class OpticsConfig:
    """Propagation geometry: SLM-to-target distance and the centred target region (ROI) in SLM pixels."""

    distance_mm: float
    roi: tuple[int, int]  # (rows, cols), centred in the SLM grid
    # Fourier-plane iris of the relay: radius as a fraction of the SLM's Nyquist frequency (None: no iris).
    # A physical iris of diameter D behind a lens of focal length f gives D * pitch / (wavelength * f).
    iris_fraction: float | None = None
    # A fitted optical model (optical-model.json of model calibration): None uses the ideal model. Calibration sets
    # it from calibration/<profile>/ for runs when the profile names none.
    model: Path | None = None

    @property
    def distance_m(self) -> float:
        return self.distance_mm * 1e-3


@dataclass(frozen=True)
class SLMConfig:
    """Phase SLM: grid, pitch, bit depth, and how phases become the gray levels it displays."""

    width: int
    height: int
    pitch_um: float
    bit_depth: int
    driver: str = "sim"
    device: str | None = None  # framebuffer device, e.g. /dev/fb1
    settle_ms: float = 100.0  # wait after showing a frame before the image is trusted
    flip_x: bool = False
    flip_y: bool = False
    phase_offset_rad: float = 0.0
    two_pi_gray: float | None = None  # gray level of 2 pi for the linear lookup table (default 2^bit_depth)
    grating_period_px: tuple[float, float] = (0.0, 0.0)  # blazed carrier (rows, cols); 0 = none on that axis
    lut: Mapping[str, Path] = field(default_factory=dict)  # channel name -> gray-to-phase table file

    @property
    def pitch_m(self) -> float:
        return self.pitch_um * 1e-6

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W), the shape of fields and holograms."""
        return self.height, self.width


@dataclass(frozen=True)
class LaserChannel:
    """One wavelength of the laser unit, with its power limit and the setpoint the bench uses."""

    name: str
    index: int
    wavelength_nm: float
    max_power_mw: float
    setpoint_mw: float
    port: str | None = None

    @property
    def wavelength_m(self) -> float:
        return self.wavelength_nm * 1e-9


@dataclass(frozen=True)
class TemplateProtocol:
    """Command templates of a multi-channel laser unit with a line protocol (see _PROTOCOL for the keys)."""

    set_power: str
    get_power: str
    enable: str
    disable: str
    line_ending: str = "\r\n"
    get_measured: str | None = None
    get_emission: str | None = None
    get_status: str | None = None
    identify: str | None = None
    ok_reply: str = "OK"
    error_prefix: str = "ERR"
    echo: bool = False
    power_unit: str = "mW"


@dataclass(frozen=True)
class LaserConfig:
    """The laser: which driver, where it is connected, and its channels."""

    channels: tuple[LaserChannel, ...]
    driver: str = "template"
    port: str | None = None
    baudrate: int = 115200
    timeout_s: float = 1.0
    write_delay_s: float = 0.0  # pause after each write (some USB-serial adapters need it)
    protocol: TemplateProtocol | None = None

    def port_of(self, channel: LaserChannel) -> str:
        """The serial port (pyserial URL or device path) that reaches `channel`."""
        port = channel.port or self.port
        assert port is not None  # guaranteed by validation
        return port


@dataclass(frozen=True)
class CameraConfig:
    """The camera: driver, how to find it, and the capture settings benchctl may apply."""

    driver: str = "sim"  # "sim" | "ptp" | "gphoto2"
    model: str = ""
    usb_id: str = "04a9:32a0"  # vendor:product the ptp driver looks for (Canon EOS M10)
    transport: str = "usb"  # ptp: "usb" (pyusb) or "sim" (the simulated EOS body, for tests and demos)
    exposure_s: float | None = None  # None: leave the camera's own setting
    iso: int | None = None
    frames: int = 1  # frames to average per capture
    # Property writes (ISO, shutter, RAW format) freeze the EOS M10: set exposure on the body and leave this off.
    write_properties: bool = False
    image_timeout_s: float = 90.0  # longest wait for the image after the shutter
    gphoto2_path: str = "gphoto2"


@dataclass(frozen=True)
class SimSLMConfig:
    """The simulated SLM's own gray -> phase response, which calibration has to find (the profile's lookup
    tables are only benchctl's belief): phase(g) = 2 pi (two_pi_nm / wavelength_nm) (g / 2^bit_depth)^gamma."""

    two_pi_nm: float = 600.0  # wavelength at which the full gray range spans 2 pi; depth scales as 1 / wavelength
    gamma: float = 1.05  # slight non-linearity of the liquid crystal
    # Amplitude fraction of each pixel that is not modulated (inter-pixel gaps): field = (1 - f) e^(i phase) + f.
    zero_order: float = 0.02
    # Fringing fields: the driven phase is blurred by a Gaussian of this many pixels (sigma) before it modulates.
    crosstalk_px: float = 0.0


@dataclass(frozen=True)
class SimBeamConfig:
    """The light arriving at the SLM (one fibre-combined beam for every colour)."""

    waist_mm: float = 0.0  # 1/e^2 intensity radius of a Gaussian beam; 0: uniform, exactly filling the panel
    offset_mm: tuple[float, float] = (0.0, 0.0)  # [rows, cols] from the panel's centre to the beam's centre
    tilt_mrad: tuple[float, float] = (0.0, 0.0)  # [rows, cols] angle of incidence: moves the image z tan(angle)
    # Fraction of the laser's photons that reach the sensor (fibre, beam splitter, ND filters, lenses).
    efficiency: float = 1e-3


@dataclass(frozen=True)
class SimImagingConfig:
    """How the target plane is imaged onto the sensor (the homography a registration has to recover)."""

    magnification: float = 2.5  # optical, target plane -> sensor
    rotation_deg: float = 0.4  # positive turns the image clockwise as displayed (rows down, columns right)
    # [rows, cols] sensor pixels from the centre of the active area to the image of the SLM grid's centre.
    offset_px: tuple[float, float] = (14.0, -22.0)
    # Fraction of the light at the target plane scattered evenly over the grid's image (veiling glare).
    stray_light: float = 0.0


@dataclass(frozen=True)
class SimSensorConfig:
    """The camera's sensor (defaults: a Canon EOS M10) and the body's own exposure settings."""

    model: str = "Canon EOS M10 (benchctl simulation)"  # written as the DNG's camera model
    shape: tuple[int, int] = (3528, 5280)  # [rows, cols] of the raw frame, masked margins included
    margin: tuple[int, int] = (52, 72)  # [rows, cols] of masked (optical black) pixels at the top and left
    pixel_um: float = 4.3
    cfa: str = "RGGB"  # Bayer layout of the top-left 2 x 2 pixels
    bit_depth: int = 14  # white level 2^bit_depth - 1
    black_level: int = 2048
    full_well_e: float = 26000.0  # electrons that reach the white level at base_iso (saturation capacity)
    base_iso: int = 100
    read_noise_e: float = 8.0  # Gaussian, input-referred
    exposure_s: float = 0.01  # the body's settings, used where the capture does not give them
    iso: int = 100
    readout_s: float = 0.0  # time from shutter release to the file being ready (an EOS M10 takes about 1 s)
    # Quantum efficiency [R, G, B] (electrons per photon in each filter colour) per laser channel name;
    # channels not listed use a typical Bayer-sensor curve at their wavelength.
    response: Mapping[str, tuple[float, float, float]] = field(default_factory=dict)

    @property
    def white_level(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def active_area(self) -> tuple[int, int, int, int]:
        """(top, left, bottom, right) of the exposed pixels in the raw frame, as DNG's ActiveArea."""
        return self.margin[0], self.margin[1], self.shape[0], self.shape[1]


@dataclass(frozen=True)
class SimConfig:
    """The simulated bench's physics ([sim]; docs/simulated_bench.md). Every profile has one: the defaults
    when the section is absent, so any profile can be rendered by the simulated camera."""

    seed: int = 0  # frame n of a run is drawn from (seed, n): successive frames differ, runs repeat
    slm: SimSLMConfig = field(default_factory=SimSLMConfig)
    beam: SimBeamConfig = field(default_factory=SimBeamConfig)
    imaging: SimImagingConfig = field(default_factory=SimImagingConfig)
    sensor: SimSensorConfig = field(default_factory=SimSensorConfig)
    # Laser channel -> Zernike term -> waves of wavefront error at the SLM (none: a perfect wavefront).
    aberration: Mapping[str, Mapping[str, float]] = field(default_factory=dict)


@dataclass(frozen=True)
class Profile:
    """A validated hardware profile."""

    path: Path
    name: str
    description: str
    optics: OpticsConfig | None
    slm: SLMConfig | None
    laser: LaserConfig | None
    camera: CameraConfig | None = None
    sim: SimConfig = field(default_factory=SimConfig)

    @property
    def channels(self) -> tuple[LaserChannel, ...]:
        """The laser channels (none if the profile has no [laser] section)."""
        return self.laser.channels if self.laser else ()

    def require(self, *sections: str) -> Profile:
        """This profile, or a BenchctlError naming the first of `sections` it lacks."""
        for section in sections:
            if getattr(self, section) is None:
                raise BenchctlError(f"{self.path}: this needs a [{section}] section, which the profile lacks")
        return self

    def channel(self, name: str) -> LaserChannel:
        """The laser channel called `name`."""
        self.require("laser")
        for ch in self.channels:
            if ch.name == name:
                return ch
        known = ", ".join(ch.name for ch in self.channels)
        raise BenchctlError(f"{self.path}: no laser channel {name!r}; known channels: {known}")

    def describe(self) -> str:
        """Multi-line summary for people: each device section with its settings."""
        slm, optics, laser = self.slm, self.optics, self.laser
        lines = [f"Hardware profile {self.name!r} ({self.path})"]
        if self.description:
            lines.append(f"  {self.description}")
        if slm:
            flips = [name for name, on in (("x", slm.flip_x), ("y", slm.flip_y)) if on]
            lines += [
                f"  SLM           {slm.driver}{' ' + slm.device if slm.device else ''}: {slm.height} x {slm.width} px "
                f"(rows x cols), pitch {slm.pitch_um:g} um, {slm.bit_depth} bit, settle {slm.settle_ms:g} ms",
                f"  SLM encoding  lookup tables: {', '.join(f'{k}={v}' for k, v in slm.lut.items()) or 'linear'}; "
                f"flip {'/'.join(flips) or 'none'}; offset {slm.phase_offset_rad:g} rad; "
                f"carrier period {slm.grating_period_px[0]:g} x {slm.grating_period_px[1]:g} px",
            ]
        if optics:
            iris = f"{optics.iris_fraction:g} x Nyquist" if optics.iris_fraction is not None else "none"
            lines += [
                f"  Distance      {optics.distance_mm:g} mm",
                f"  ROI           {optics.roi[0]} x {optics.roi[1]} px (rows x cols), centred",
                f"  Iris          {iris}",
            ]
        if laser:
            where = f" on {laser.port}" if laser.port else ""
            lines.append(f"  Laser         {laser.driver}{where}, {laser.baudrate} baud, timeout {laser.timeout_s:g} s")
            width = max(len(ch.name) for ch in laser.channels)
            for ch in laser.channels:
                share = 100.0 * ch.setpoint_mw / ch.max_power_mw
                port = f"  port {ch.port}" if ch.port else ""
                lines.append(
                    f"    {ch.name:<{width}}  #{ch.index}  {ch.wavelength_nm:g} nm  max {ch.max_power_mw:g} mW  "
                    f"setpoint {ch.setpoint_mw:g} mW ({share:.0f} %){port}"
                )
        if self.camera:
            cam = self.camera
            exposure = f"{cam.exposure_s:g} s" if cam.exposure_s else "as set on the body"
            lines.append(f"  Camera        {cam.driver} {cam.model}".rstrip() + f": exposure {exposure}, "
                         f"ISO {cam.iso or 'as set on the body'}, {cam.frames} frame(s) per capture")
        return "\n".join(lines)


def resolve_profile_path(path_or_name: str | Path | None = None) -> Path:
    """Where a profile lives: a path, a bare name (hardware_profiles/<name>.toml) or None for the default.

    None means $BENCHCTL_PROFILE if set, else the simulated bench. Bare names are looked up in
    ./hardware_profiles first, then in the hardware_profiles folder of the repository next to the package.
    """
    origin = ""
    if path_or_name is None:
        env = os.environ.get(PROFILE_ENV)
        path_or_name = env or DEFAULT_PROFILE
        origin = f" (from ${PROFILE_ENV})" if env else ""
    text = str(path_or_name)
    if isinstance(path_or_name, Path) or text.endswith(".toml") or "/" in text or os.sep in text:
        return Path(path_or_name)
    file_name = f"{text}.toml"
    candidates = [Path(PROFILE_DIR) / file_name, Path(__file__).resolve().parents[1] / PROFILE_DIR / file_name]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    searched = ", ".join(str(c) for c in candidates)
    raise BenchctlError(f"hardware profile {text!r}{origin} not found (looked for {searched})")


def load_profile(path_or_name: str | Path | None = None) -> Profile:
    """Read, validate and return a hardware profile (see resolve_profile_path for how it is found)."""
    path = resolve_profile_path(path_or_name)
    try:
        with path.open("rb") as f:
            raw = tomllib.load(f)
    except FileNotFoundError:
        raise BenchctlError(f"{path}: hardware profile not found") from None
    except OSError as exc:
        raise BenchctlError(f"{path}: cannot read hardware profile: {exc.strerror or exc}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise BenchctlError(f"{path}: TOML syntax error: {exc}") from None
    return _build(path, check_table(raw, SCHEMA, "", path))


def _build(path: Path, data: Mapping[str, Any]) -> Profile:
    """Cross-key checks the schema cannot express, then the dataclasses."""
    if not any(section in data for section in SECTIONS):
        raise fail(path, "(top level)", f"no device section: give at least one of {', '.join(SECTIONS)}")
    name = data.get("name", path.stem)
    if not _NAME.fullmatch(name):
        raise fail(path, "name", f"{name!r} must be letters, digits, '_', '-' or '.' and start with a letter or digit "
                                 "(it names the profile's calibration folder)")
    slm = _build_slm(path, data["slm"]) if "slm" in data else None
    optics = None
    if "optics" in data:
        model = data["optics"].get("model")
        optics = OpticsConfig(**{**data["optics"], "model": (path.parent / model).resolve() if model else None})
    if optics and slm and (optics.roi[0] > slm.height or optics.roi[1] > slm.width):
        raise fail(
            path, "optics.roi",
            f"{list(optics.roi)} is larger than the SLM grid {slm.height} x {slm.width} (slm.height x slm.width)",
        )
    laser = _build_laser(path, data["laser"]) if "laser" in data else None
    if slm and laser:
        names = {ch.name for ch in laser.channels}
        for name in slm.lut:
            if name not in names:
                raise fail(path, f"slm.lut.{name}", f"no laser channel {name!r} (known: {', '.join(sorted(names))})")
    camera = CameraConfig(**data["camera"]) if "camera" in data else None
    sim = _build_sim(path, data.get("sim", {}), laser)
    return Profile(path=path, name=name, description=data["description"],
                   optics=optics, slm=slm, laser=laser, camera=camera, sim=sim)


def _build_sim(path: Path, data: Mapping[str, Any], laser: LaserConfig | None) -> SimConfig:
    """The [sim] section: masked margins inside the frame and even (the Bayer pattern starts on the exposed
    area as on the frame), black below white, spectral responses only for known channels."""
    sensor = SimSensorConfig(**data.get("sensor", {}))
    for axis, name in enumerate(("rows", "cols")):
        margin, size = sensor.margin[axis], sensor.shape[axis]
        if margin % 2 or margin + 2 > size:
            raise fail(path, "sim.sensor.margin",
                        f"{name} margin {margin} must be even and leave exposed pixels in {size} {name}")
    if sensor.black_level >= sensor.white_level:
        raise fail(path, "sim.sensor.black_level", f"{sensor.black_level} is not below the white level "
                    f"{sensor.white_level} of a {sensor.bit_depth}-bit sensor")
    names = {ch.name for ch in laser.channels} if laser else set()
    for section, entries in (("sensor.response", sensor.response), ("aberration", data.get("aberration", {}))):
        for name in entries:
            if name not in names:
                raise fail(path, f"sim.{section}.{name}",
                            f"no laser channel {name!r} (known: {', '.join(sorted(names)) or 'none'})")
    parts = {"slm": SimSLMConfig, "beam": SimBeamConfig, "imaging": SimImagingConfig}
    built = {key: cls(**data[key]) for key, cls in parts.items() if key in data}
    return SimConfig(**{**data, **built, "sensor": sensor})


def _build_slm(path: Path, data: Mapping[str, Any]) -> SLMConfig:
    """The SLM section: lookup-table paths are relative to the profile's folder."""
    luts = {name: (path.parent / file).resolve() for name, file in data.get("lut", {}).items()}
    slm = SLMConfig(**{**data, "lut": luts})
    check_pixels(f"{path}: slm.height x slm.width", slm.height, slm.width)
    if slm.driver == "framebuffer" and not slm.device:
        raise fail(path, "slm.device", "the framebuffer driver needs a device, e.g. device = \"/dev/fb1\"")
    return slm


def _build_laser(path: Path, data: Mapping[str, Any]) -> LaserConfig:
    """The laser section: channels unique by name and index, setpoints within limits, every channel reachable."""
    channels = []
    first_seen: dict[tuple[str, Any], str] = {}
    for i, entry in enumerate(data["channels"]):
        key = f"laser.channels[{i}]"
        channel = LaserChannel(**{"index": i + 1, **entry})
        if not channel.name.strip():
            raise fail(path, f"{key}.name", f"channel name must not be empty, got {channel.name!r}")
        for attr in ("name", "index"):
            value = getattr(channel, attr)
            if (attr, value) in first_seen:
                also = first_seen[attr, value]
                raise fail(path, f"{key}.{attr}", f"duplicate channel {attr} {value!r} (also {also})")
            first_seen[attr, value] = f"{key}.{attr}"
        if channel.setpoint_mw > channel.max_power_mw:
            raise fail(
                path, f"{key}.setpoint_mw",
                f"{channel.setpoint_mw:g} mW is above max_power_mw {channel.max_power_mw:g} mW",
            )
        if channel.port is None and "port" not in data:
            raise fail(path, f"{key}.port", "no serial port: set laser.port or a port for this channel")
        channels.append(channel)
    protocol = data.get("protocol")
    if data["driver"] == "template" and protocol is None:
        raise fail(path, "laser.protocol", "the template driver needs a [laser.protocol] section with its commands")
    if data["driver"] != "template" and protocol is not None:
        raise fail(path, "laser.protocol", f"only the template driver uses [laser.protocol], not {data['driver']!r}")
    fields = {k: v for k, v in data.items() if k not in ("channels", "protocol")}
    return LaserConfig(channels=tuple(channels), protocol=TemplateProtocol(**protocol) if protocol else None, **fields)

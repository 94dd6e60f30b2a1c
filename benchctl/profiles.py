"""Hardware profiles: one TOML file per bench, decoded into one typed model per section.

Each section is a `Model` (benchctl.schema: a frozen msgspec Struct that forbids unknown keys) below; its
annotations are the one statement of every key's type, bounds, choices and unit, and its defaults the only
defaults. Decoding is strict: an unknown key (a misspelt `pitch` for `pitch_um`) is an error that suggests the
closest known key, never silently ignored. Every error is a BenchctlError naming the file, the key path
(`laser.channels[1].wavelength_nm`) and the bad value. Checks across keys (ROI inside the SLM grid, setpoints
under their limits, channel names unique, ...) follow the decoding, in `_checked`.
"""

from __future__ import annotations

import os
import re
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal, overload

import msgspec
from msgspec import Meta

from benchctl import SOURCE_ROOT
from benchctl.dng import CFA_LAYOUTS
from benchctl.drivers import driver_names
from benchctl.errors import BenchctlError, did_you_mean
from benchctl.files import read_capped
from benchctl.limits import check_pixels
from benchctl.optics.geometry import Geometry
from benchctl.schema import Model, decode, fail

if sys.version_info >= (3, 11):
    import tomllib
else:
    import tomli as tomllib

PROFILE_ENV = "BENCHCTL_PROFILE"
PROFILE_DIR = "hardware_profiles"
DEFAULT_PROFILE = "simulated"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]*")
SECTIONS = ("optics", "slm", "laser", "camera", "focus")

Positive = Annotated[float, Meta(gt=0)]
NonNegative = Annotated[float, Meta(ge=0)]
# A liquid crystal settles within a second; a minute or more is a unit slip (seconds or microseconds as ms) that would
# leave a run waiting for days after every frame.
SettleMs = Annotated[float, Meta(ge=0, le=60_000)]
Fraction = Annotated[float, Meta(ge=0, le=1)]
PositiveInt = Annotated[int, Meta(gt=0)]
NonNegativeInt = Annotated[int, Meta(ge=0)]
RowsCols = tuple[float, float]  # [rows, cols]
if TYPE_CHECKING:  # choices listed at run time, in the modules named below: plain strings to a type checker
    CFALayout = str
    LaserDriver = str
    SLMDriver = str
    CameraDriver = str
    FocusDriver = str
else:
    CFALayout = Literal[tuple(CFA_LAYOUTS)]  # the layouts benchctl.dng writes
    # The drivers of each kind (benchctl.drivers lists them once).
    LaserDriver = Literal[driver_names("laser")]
    SLMDriver = Literal[driver_names("slm")]
    CameraDriver = Literal[driver_names("camera")]
    FocusDriver = Literal[driver_names("focus")]
# The Zernike terms of optics.aberration.ZERNIKE_TERMS (not imported: it imports torch; a test keeps them equal).
ZernikeTerm = Literal["tilt_vertical", "tilt_horizontal", "astigmatism_oblique", "defocus", "astigmatism_vertical",
                      "coma_vertical", "coma_horizontal", "spherical"]


class OpticsConfig(Model, kw_only=True):
    """Propagation geometry ([optics]): SLM-to-target distance and the centred target region (ROI) in SLM pixels."""

    distance_mm: Positive
    roi: tuple[PositiveInt, PositiveInt]  # (rows, cols), centred in the SLM grid
    # Fourier-plane iris of the relay: radius as a fraction of the SLM's Nyquist frequency (None: no iris).
    # A physical iris of diameter D behind a lens of focal length f gives D * pitch / (wavelength * f).
    iris_fraction: Positive | None = None
    # A fitted optical model (optical-model.json of model calibration), relative to the profile's folder: None uses
    # the ideal model. Calibration sets it from calibration/<profile>/ for runs when the profile names none.
    model: Path | None = None
    # (near, far): the distances from the SLM along the axis between which the bench can show a scene with depth
    # (where its camera or eyepiece can focus). None: the bench shows one plane only, and refuses RGB-D targets.
    depth_range_mm: tuple[Positive, Positive] | None = None

    @property
    def distance_m(self) -> float:
        return self.distance_mm * 1e-3

    @property
    def depth_range_m(self) -> tuple[float, float] | None:
        """`depth_range_mm` in metres."""
        if self.depth_range_mm is None:
            return None
        return self.depth_range_mm[0] * 1e-3, self.depth_range_mm[1] * 1e-3


class SLMConfig(Model, kw_only=True):
    """Phase SLM ([slm]): grid, pitch, bit depth, and how phases become the gray levels it displays."""

    driver: SLMDriver = "sim"
    device: str | None = None  # framebuffer device, e.g. /dev/fb1
    width: PositiveInt
    height: PositiveInt
    pitch_um: Annotated[float, Meta(ge=0.1, le=1000)]  # the pitches optics.setup accepts (0.1 um .. 1 mm)
    bit_depth: Annotated[int, Meta(ge=1, le=16)]
    settle_ms: SettleMs = 100.0  # wait after showing a frame before the image is trusted
    flip_x: bool = False
    flip_y: bool = False
    phase_offset_rad: float = 0.0
    two_pi_gray: Positive | None = None  # gray level of 2 pi for the linear lookup table (default 2^bit_depth)
    grating_period_px: RowsCols = (0.0, 0.0)  # blazed carrier (rows, cols); 0 = none on that axis
    # Channel name -> gray-to-phase table file, relative to the profile's folder.
    lut: dict[str, Path] = msgspec.field(default_factory=dict)
    # display: the desktop output showing the SLM, by its EDID (monitor name, serial) and/or connector name
    edid_name: str | None = None
    edid_serial: str | None = None
    output: str | None = None  # RandR output name, e.g. HDMI-A-1
    x_display: str | None = None  # X display, e.g. ":0" (None: $DISPLAY)

    @property
    def pitch_m(self) -> float:
        return self.pitch_um * 1e-6

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W), the shape of fields and holograms."""
        return self.height, self.width


class LaserChannel(Model, kw_only=True):
    """One wavelength of the laser unit ([[laser.channels]]), with its power limit and the bench's setpoint."""

    name: str
    # The laser unit's own channel number, as drivers address it. None only as written: a loaded profile numbers
    # the channels that give none by their position in the list, from 1.
    index: NonNegativeInt | None = None
    wavelength_nm: Annotated[float, Meta(ge=100, le=20000)]  # the wavelengths optics.setup accepts (100 nm .. 20 um)
    max_power_mw: Positive
    setpoint_mw: NonNegative
    port: str | None = None  # single-wavelength heads (cobolt, obis) have one serial port each; overrides laser.port

    @property
    def wavelength_m(self) -> float:
        return self.wavelength_nm * 1e-9


class TemplateProtocol(Model, kw_only=True):
    """The commands of a multi-channel laser unit with a simple line protocol ([laser.protocol], "template"
    driver). Placeholders: {channel} the channel's index, {mw} / {w} the power in mW / W. Replies with a power are
    read in `power_unit`."""

    line_ending: str = "\r\n"
    set_power: str
    get_power: str
    enable: str
    disable: str
    get_measured: str | None = None
    get_emission: str | None = None
    get_status: str | None = None
    identify: str | None = None
    ok_reply: str = "OK"
    error_prefix: str = "ERR"
    echo: bool = False
    power_unit: Literal["mW", "W"] = "mW"


class LaserConfig(Model, kw_only=True):
    """The laser ([laser]): which driver, where it is connected, and its channels."""

    driver: LaserDriver = "template"
    port: str | None = None
    baudrate: PositiveInt = 115200
    timeout_s: Positive = 1.0
    write_delay_s: NonNegative = 0.0  # pause after each write (some USB-serial adapters need it)
    protocol: TemplateProtocol | None = None
    channels: Annotated[tuple[LaserChannel, ...], Meta(min_length=1)]

    def port_of(self, channel: LaserChannel) -> str:
        """The serial port (pyserial URL or device path) that reaches `channel`."""
        port = channel.port or self.port
        assert port is not None  # guaranteed by validation
        return port


class CameraConfig(Model, kw_only=True):
    """The camera ([camera]): driver, how to find it, and the capture settings benchctl may apply."""

    driver: CameraDriver = "sim"
    model: str = ""  # gphoto2: the camera's model as libgphoto2 names it; genicam: its model name
    usb_id: str = "04a9:32a0"  # vendor:product the ptp driver looks for (Canon EOS M10)
    transport: Literal["usb", "sim"] = "usb"  # ptp: "usb" (pyusb) or "sim" (the simulated EOS body)
    exposure_s: Positive | None = None  # None: leave the camera's own setting
    iso: PositiveInt | None = None
    frames: Annotated[int, Meta(ge=1)] = 1  # frames to average per capture
    # Property writes (ISO, shutter, RAW format) freeze the EOS M10: set exposure on the body and leave this off.
    write_properties: bool = False
    image_timeout_s: Positive = 90.0  # longest wait for the image after the shutter
    # genicam: which camera (every key given must match; none: the only one found). device_id is Aravis's id
    # or the camera's IP address (opened directly, without a discovery broadcast).
    device_id: str | None = None
    serial: str | None = None
    user_id: str | None = None  # DeviceUserID, a name the lab gave the camera
    vendor: str | None = None  # with `model`: the camera's vendor and model names as it reports them
    pixel_format: str | None = None  # PFNC name, e.g. BayerRG12 (None: the camera's current one)
    region: tuple[NonNegativeInt, NonNegativeInt, PositiveInt, PositiveInt] | None = None  # [x, y, width, height]
    gain: NonNegative | None = None  # in the camera's unit (usually dB); None: leave it
    black_level: float | None = None  # the camera's BlackLevel, where offered; None: leave it
    frame_retries: NonNegativeInt = 2  # incomplete frames (lost packets) re-triggered before the capture fails


class FocusConfig(Model, kw_only=True):
    """The camera's focus ([focus]; docs/focus.md): which driver moves it and how it is reached. A step is the
    driver's own unit (a stage's microstep, a lens's smallest DriveLens step); the focus calibration relates steps to
    depth."""

    driver: FocusDriver = "zaber"
    port: str | None = None  # zaber: serial port (pyserial URL or device path)
    baudrate: PositiveInt = 115200
    timeout_s: Positive = 1.0
    device: Annotated[int, Meta(ge=1, le=99)] = 1  # zaber: device number in the daisy chain
    axis: Annotated[int, Meta(ge=1, le=9)] = 1  # zaber: axis of that device
    microstep_um: Positive = 0.047625  # zaber: stage travel per microstep (the stage's datasheet)
    drive_size: Literal[1, 2, 3] = 1  # eos: DriveLens step size (Near/Far 1, 2 or 3) that one step drives
    home_drives: PositiveInt = 60  # eos: DriveLens Near 3 commands that surely reach the near end stop
    settle_ms: NonNegative = 100.0  # wait after a move before a frame is trusted
    move_timeout_s: Positive = 30.0  # longest wait for one move or homing to end


# The simulated bench's physics ([sim]; docs/simulated_bench.md). Every key is optional; the [sim] block of
# hardware_profiles/simulated.toml lists the defaults.


class SimSLMConfig(Model, kw_only=True):
    """The simulated SLM's own gray -> phase response, which calibration has to find (the profile's lookup
    tables are only benchctl's belief): phase(g) = 2 pi (two_pi_nm / wavelength_nm) (g / 2^bit_depth)^gamma."""

    two_pi_nm: Positive = 600.0  # wavelength at which the full gray range spans 2 pi; depth scales as 1 / wavelength
    gamma: Positive = 1.05  # slight non-linearity of the liquid crystal
    # Amplitude fraction of each pixel that is not modulated (inter-pixel gaps): field = (1 - f) e^(i phase) + f.
    zero_order: Fraction = 0.02
    # Fringing fields: the driven phase is blurred by a Gaussian of this many pixels (sigma) before it modulates.
    crosstalk_px: NonNegative = 0.0


# A Gaussian beam narrower than this many SLM pixels (1/e^2 radius) lights a few hundred pixels at most: no hologram
# can use it, and far below it the beam's profile underflows to no light at all (a unit slip: metres written as mm).
MIN_WAIST_PX = 10.0


def waist_problem(waist_mm: float, slm: SLMConfig) -> str | None:
    """Why a Gaussian beam of `waist_mm` (0: uniform light) cannot light the panel of `slm`; None if it can."""
    least = MIN_WAIST_PX * slm.pitch_um * 1e-3
    if 0 < waist_mm < least:
        return (f"must be 0 (uniform light) or at least {least:g} mm ({MIN_WAIST_PX:g} SLM pixels), got {waist_mm!r}: "
                "a narrower beam lights almost none of the panel")
    return None


class SimBeamConfig(Model, kw_only=True):
    """The light arriving at the SLM (one fibre-combined beam for every colour)."""

    waist_mm: NonNegative = 0.0  # 1/e^2 intensity radius of a Gaussian beam; 0: uniform, exactly filling the panel
    offset_mm: RowsCols = (0.0, 0.0)  # [rows, cols] from the panel's centre to the beam's centre
    tilt_mrad: RowsCols = (0.0, 0.0)  # [rows, cols] angle of incidence: moves the image z tan(angle)
    # Fraction of the laser's photons that reach the sensor (fibre, beam splitter, ND filters, lenses).
    efficiency: Annotated[float, Meta(gt=0, le=1)] = 1e-3


class SimImagingConfig(Model, kw_only=True):
    """How the target plane is imaged onto the sensor (the homography a registration has to recover)."""

    magnification: Positive = 2.5  # optical, target plane -> sensor
    rotation_deg: float = 0.4  # positive turns the image clockwise as displayed (rows down, columns right)
    # [rows, cols] sensor pixels from the centre of the active area to the image of the SLM grid's centre.
    offset_px: RowsCols = (14.0, -22.0)
    # Fraction of the light at the target plane scattered evenly over the grid's image (veiling glare).
    stray_light: Fraction = 0.0


class SimSensorConfig(Model, kw_only=True):
    """The camera's sensor (defaults: a Canon EOS M10) and the body's own exposure settings."""

    model: str = "Canon EOS M10 (benchctl simulation)"  # written as the DNG's camera model
    shape: tuple[PositiveInt, PositiveInt] = (3528, 5280)  # [rows, cols] of the raw frame, masked margins included
    # [rows, cols] of masked (optical black) pixels at the top and left
    margin: tuple[NonNegativeInt, NonNegativeInt] = (52, 72)
    pixel_um: Positive = 4.3
    cfa: CFALayout = "RGGB"  # Bayer layout of the top-left 2 x 2 pixels
    bit_depth: Annotated[int, Meta(ge=8, le=16)] = 14  # white level 2^bit_depth - 1
    black_level: NonNegativeInt = 2048
    full_well_e: Positive = 26000.0  # electrons that reach the white level at base_iso (saturation capacity)
    base_iso: PositiveInt = 100
    read_noise_e: NonNegative = 8.0  # Gaussian, input-referred
    exposure_s: Positive = 0.01  # the body's settings, used where the capture does not give them
    iso: PositiveInt = 100
    readout_s: NonNegative = 0.0  # time from shutter release to the file being ready (an EOS M10 takes about 1 s)
    # Quantum efficiency [R, G, B] (electrons per photon in each filter colour) per laser channel name;
    # channels not listed use a typical Bayer-sensor curve at their wavelength.
    response: dict[str, tuple[NonNegative, NonNegative, NonNegative]] = msgspec.field(default_factory=dict)

    @property
    def white_level(self) -> int:
        return (1 << self.bit_depth) - 1

    @property
    def active_area(self) -> tuple[int, int, int, int]:
        """(top, left, bottom, right) of the exposed pixels in the raw frame, as DNG's ActiveArea."""
        return self.margin[0], self.margin[1], self.shape[0], self.shape[1]


class SimFocusConfig(Model, kw_only=True):
    """The simulated focus mechanism (a Zaber stage on sim://, or the simulated EOS body's lens): its hidden mechanics
    and where it focuses the camera, which focus calibration has to recover (docs/focus.md)."""

    # Depth (from the SLM) of the camera's focus plane with the mechanism at start_steps; None: optics.distance_mm.
    plane_mm: Positive | None = None
    mm_per_step: float = 4.7625e-5  # focus-plane shift per step the mechanism truly makes (signed)
    range_steps: PositiveInt = 252000  # travel between the end stops, in steps (12 mm: a depth range and a margin)
    start_steps: NonNegative = 126000  # where the mechanism is at power-on (state never saved yet)
    backlash_steps: NonNegative = 630.0  # lost motion on each reversal of direction
    step_spread: Fraction = 0.0  # relative standard deviation of each step's true size
    seed: NonNegativeInt = 0  # the step-size spread's random stream


class SimConfig(Model, kw_only=True):
    """The simulated bench's physics ([sim]; docs/simulated_bench.md). Every profile has one: the defaults
    when the section is absent, so any profile can be rendered by the simulated camera."""

    seed: NonNegativeInt = 0  # frame n of a run is drawn from (seed, n): successive frames differ, runs repeat
    slm: SimSLMConfig = msgspec.field(default_factory=SimSLMConfig)
    beam: SimBeamConfig = msgspec.field(default_factory=SimBeamConfig)
    imaging: SimImagingConfig = msgspec.field(default_factory=SimImagingConfig)
    # Laser channel -> Zernike term -> waves of wavefront error at the SLM (none: a perfect wavefront).
    aberration: dict[str, dict[ZernikeTerm, float]] = msgspec.field(default_factory=dict)
    sensor: SimSensorConfig = msgspec.field(default_factory=SimSensorConfig)
    focus: SimFocusConfig = msgspec.field(default_factory=SimFocusConfig)


class ProfileFile(Model, kw_only=True):
    """What a profile file says: its top-level keys and sections (at least one of SECTIONS)."""

    name: str | None = None  # default: the file's name without .toml
    description: str = ""
    optics: OpticsConfig | None = None
    slm: SLMConfig | None = None
    laser: LaserConfig | None = None
    camera: CameraConfig | None = None
    focus: FocusConfig | None = None
    sim: SimConfig = msgspec.field(default_factory=SimConfig)


class Profile(ProfileFile, kw_only=True):
    """A loaded, checked hardware profile: what its file says, and where the file is."""

    name: str
    path: Path

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

    @overload
    def section(self, name: Literal["optics"]) -> OpticsConfig: ...
    @overload
    def section(self, name: Literal["slm"]) -> SLMConfig: ...
    @overload
    def section(self, name: Literal["laser"]) -> LaserConfig: ...
    @overload
    def section(self, name: Literal["camera"]) -> CameraConfig: ...
    @overload
    def section(self, name: Literal["focus"]) -> FocusConfig: ...

    def section(self, name: str) -> Model:
        """Device section `name` of this profile, or the BenchctlError of `require` if the profile lacks it."""
        found: Model = getattr(self.require(name), name)
        return found

    def channel(self, name: str) -> LaserChannel:
        """The laser channel called `name`."""
        self.require("laser")
        for ch in self.channels:
            if ch.name == name:
                return ch
        known = ", ".join(ch.name for ch in self.channels)
        raise BenchctlError(f"{self.path}: no laser channel {name!r}; known channels: {known}")

    def geometry(self, channel: str) -> Geometry:
        """The optical geometry of laser channel `channel` in SI units: the one conversion from the profile's
        units, for everything that computes, calibrates or caches for this bench."""
        slm, optics = self.section("slm"), self.section("optics")
        return Geometry(wavelength_m=self.channel(channel).wavelength_m, pitch_m=(slm.pitch_m, slm.pitch_m),
                        distance_m=optics.distance_m, shape=slm.shape, roi=optics.roi, aperture=optics.iris_fraction)

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
            if optics.depth_range_mm is not None:
                near, far = optics.depth_range_mm
                lines.append(f"  Depth range   {near:g} .. {far:g} mm from the SLM")
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
            body = "as set on the camera" if cam.driver == "genicam" else "as set on the body"
            exposure = f"{cam.exposure_s:g} s" if cam.exposure_s else body
            if cam.driver == "genicam":  # a machine-vision camera has a pixel format and gain, not ISO
                gain = body if cam.gain is None else f"{cam.gain:g}"
                sensor = f"{cam.pixel_format or 'pixel format ' + body}, gain {gain}"
            else:
                sensor = f"ISO {cam.iso or body}"
            lines.append(f"  Camera        {cam.driver} {cam.model}".rstrip() + f": exposure {exposure}, {sensor}, "
                         f"{cam.frames} frame(s) per capture")
        if self.focus:
            where = f" on {self.focus.port}" if self.focus.port else " (the camera's lens)"
            lines.append(f"  Focus         {self.focus.driver}{where}, settle {self.focus.settle_ms:g} ms")
        return "\n".join(lines)


def resolve_profile_path(path_or_name: str | Path | None = None) -> Path:
    """Where a profile lives: a path, a bare name (hardware_profiles/<name>.toml) or None for the default.

    None means $BENCHCTL_PROFILE if set, else the simulated bench. Bare names are looked up in
    ./hardware_profiles first, then in the hardware_profiles folder of the repository next to the package, then as a
    file of that name (which load_profile then says is not a TOML profile, if it is not).
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
    candidates = [Path(PROFILE_DIR) / file_name, SOURCE_ROOT / PROFILE_DIR / file_name]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    if Path(text).is_file():  # -p README.md: read, to be told what it is not
        return Path(text)
    searched = ", ".join(str(c) for c in candidates)
    known = {p.stem for folder in {c.parent for c in candidates} if folder.is_dir() for p in folder.glob("*.toml")}
    raise BenchctlError(f"hardware profile {text!r}{origin} not found{did_you_mean(text, known)} (looked for "
                        f"{searched})")


def load_profile(path_or_name: str | Path | None = None) -> Profile:
    """Read, decode and check a hardware profile (see resolve_profile_path for how it is found)."""
    path = resolve_profile_path(path_or_name)
    try:
        raw = tomllib.loads(read_capped(path, "hardware profile").decode("utf-8"))
    except FileNotFoundError:
        known = [str(p) for p in path.parent.glob("*.toml")] if path.parent.is_dir() else []
        hint = did_you_mean(str(path), known, key=lambda name: Path(name).name)
        raise BenchctlError(f"{path}: hardware profile not found{hint}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        if path.suffix.lower() != ".toml":
            raise BenchctlError(f"{path}: not a hardware profile (a TOML file such as "
                                f"hardware_profiles/simulated.toml): {exc}") from None
        raise BenchctlError(f"{path}: TOML syntax error: {exc}") from None
    return _checked(path, decode(raw, ProfileFile, path))


def _checked(path: Path, file: ProfileFile) -> Profile:
    """The checks across keys that types cannot express; the profile, with its channels numbered."""
    if all(getattr(file, section) is None for section in SECTIONS):
        raise fail(path, "(top level)", f"no device section: give at least one of {', '.join(SECTIONS)}")
    name = path.stem if file.name is None else file.name
    if not _NAME.fullmatch(name):
        raise fail(path, "name", f"{name!r} must be letters, digits, '_', '-' or '.' and start with a letter or digit "
                                 "(it names the profile's calibration folder)")
    slm, optics = file.slm, file.optics
    if file.camera and file.camera.driver == "genicam" and file.camera.iso is not None:
        raise fail(path, "camera.iso", "a GenICam camera has gain, not ISO: set camera.gain instead")
    if file.camera and file.camera.region is not None:
        check_pixels(f"{path}: camera.region height x width", file.camera.region[3], file.camera.region[2])
    if slm:
        check_pixels(f"{path}: slm.height x slm.width", slm.height, slm.width)
        if slm.driver == "framebuffer" and not slm.device:
            raise fail(path, "slm.device", "the framebuffer driver needs a device, e.g. device = \"/dev/fb1\"")
        if slm.driver == "display" and slm.edid_name is None and slm.edid_serial is None and slm.output is None:
            raise fail(path, "slm.driver", "the display driver needs the SLM's output: slm.edid_name, slm.edid_serial "
                                           "or slm.output (`benchctl devices` lists them)")
    if optics and slm and (optics.roi[0] > slm.height or optics.roi[1] > slm.width):
        raise fail(
            path, "optics.roi",
            f"{list(optics.roi)} is larger than the SLM grid {slm.height} x {slm.width} (slm.height x slm.width)",
        )
    _check_focus(path, file)
    if optics and optics.depth_range_mm is not None and not optics.depth_range_mm[0] < optics.depth_range_mm[1]:
        raise fail(path, "optics.depth_range_mm", f"{list(optics.depth_range_mm)} must be [near, far] with near < far")
    laser = _checked_laser(path, file.laser) if file.laser else None
    names = {ch.name for ch in laser.channels} if laser else set()
    known = ", ".join(sorted(names)) or "none"
    for section, entries in (("slm.lut", slm.lut if slm else {}), ("sim.sensor.response", file.sim.sensor.response),
                             ("sim.aberration", file.sim.aberration)):
        for channel in entries:
            if channel not in names:
                raise fail(path, f"{section}.{channel}", f"no laser channel {channel!r} (known: {known})")
    _check_sensor(path, file.sim.sensor)
    beam = waist_problem(file.sim.beam.waist_mm, slm) if slm else None
    if beam:
        raise fail(path, "sim.beam.waist_mm", beam)
    fields = {key: getattr(file, key) for key in file.__struct_fields__}
    return Profile(**{**fields, "name": name, "laser": laser, "path": path})


def _check_focus(path: Path, file: ProfileFile) -> None:
    """A focus driver has what reaches it: the zaber stage a port, the EOS lens a ptp camera to drive it through."""
    focus = file.focus
    if focus is None:
        return
    if focus.driver == "zaber" and not focus.port:
        raise fail(path, "focus.port", "the zaber driver needs a serial port, e.g. port = \"/dev/ttyUSB1\"")
    if focus.driver == "eos" and (file.camera is None or file.camera.driver != "ptp"):
        raise fail(path, "focus.driver", "the eos driver drives the lens through the camera: it needs "
                                         "[camera] driver = \"ptp\"")
    sim = file.sim.focus
    if sim.start_steps > sim.range_steps:
        raise fail(path, "sim.focus.start_steps", f"{sim.start_steps:g} is beyond the range of {sim.range_steps} steps")


def _check_sensor(path: Path, sensor: SimSensorConfig) -> None:
    """Within the pixel limit (the simulator renders every pixel), masked margins inside the frame and even (the
    Bayer pattern starts on the exposed area as on the frame), black below white."""
    check_pixels(f"{path}: sim.sensor.shape", *sensor.shape)
    for axis, name in enumerate(("rows", "cols")):
        margin, size = sensor.margin[axis], sensor.shape[axis]
        if margin % 2 or margin + 2 > size:
            raise fail(path, "sim.sensor.margin",
                       f"{name} margin {margin} must be even and leave exposed pixels in {size} {name}")
    if sensor.black_level >= sensor.white_level:
        raise fail(path, "sim.sensor.black_level", f"{sensor.black_level} is not below the white level "
                   f"{sensor.white_level} of a {sensor.bit_depth}-bit sensor")


def _checked_laser(path: Path, laser: LaserConfig) -> LaserConfig:
    """Channels numbered, unique by name and index, setpoints within limits, every channel reachable; the
    protocol section exactly where the driver uses one."""
    channels = []
    first_seen: dict[tuple[str, object], str] = {}
    for i, given in enumerate(laser.channels):
        key = f"laser.channels[{i}]"
        channel = given if given.index is not None else msgspec.structs.replace(given, index=i + 1)
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
        if channel.port is None and laser.port is None:
            raise fail(path, f"{key}.port", "no serial port: set laser.port or a port for this channel")
        channels.append(channel)
    if laser.driver == "template" and laser.protocol is None:
        raise fail(path, "laser.protocol", "the template driver needs a [laser.protocol] section with its commands")
    if laser.driver != "template" and laser.protocol is not None:
        raise fail(path, "laser.protocol", f"only the template driver uses [laser.protocol], not {laser.driver!r}")
    return msgspec.structs.replace(laser, channels=tuple(channels))

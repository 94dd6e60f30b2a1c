"""Checkpoints of trained hologram networks: one file per method holding one model per colour (laser channel).

A checkpoint (`torch.save` of plain dicts and tensors, read back with `weights_only=True`) holds:
- `method`, `benchctl_version`, `torch_version`, `created_unix`;
- per colour: the full optical geometry it was trained for (`Geometry.to_dict`), its validation metrics
  and its weights (float32, or float16 to keep shipped files small; always loaded back as float32);
- `training`: loss, lr, epochs, steps, batch size, seed, data description, processes, the equivalent command;
- for `--resume` only (the `.resume.pt` file written next to it): Adam's state per colour and where training
  stands (epoch, batch within it, step).

Using a checkpoint for a geometry other than its own is refused, naming every difference. Shipped checkpoints
live in `checkpoints/<profile name>/<method>.pt` (in the working folder or the repository next to the
package, like hardware profiles); `find_checkpoint` finds them, and `learned_method` turns one into the
runnable form of a registered method that needs a checkpoint.
"""

from __future__ import annotations

import functools
import io
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

import benchctl
from benchctl import SOURCE_ROOT
from benchctl.calibration.geometry import geometry_differences
from benchctl.cgh import Method, get_method
from benchctl.cgh.learned.models import LEARNED_METHODS, build_model
from benchctl.errors import BadValueError, BenchctlError
from benchctl.files import atomic_write_bytes, write_json
from benchctl.optics.geometry import Geometry
from benchctl.optics.setup import OpticalSetup
from benchctl.profiles import Profile

FORMAT = "benchctl.learned-checkpoint"
FORMAT_VERSION = 1
CHECKPOINT_DIR = "checkpoints"
WEIGHT_DTYPES = {"float32": torch.float32, "float16": torch.float16}
RESUME_SUFFIX = ".resume.pt"


@dataclass
class Checkpoint:
    """A method's trained models, one per colour, with what they were trained for and how."""

    method: str
    geometry: dict[str, Geometry]  # colour (laser channel name) -> the geometry it was trained for
    weights: dict[str, dict[str, torch.Tensor]]  # colour -> state dict (float32 in memory)
    training: dict[str, Any] = field(default_factory=dict)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)  # colour -> validation metrics
    benchctl_version: str = benchctl.__version__
    torch_version: str = str(torch.__version__)
    created_unix: float = field(default_factory=time.time)
    weights_dtype: str = "float32"
    optimisers: dict[str, dict[str, Any]] | None = None  # resume state only
    position: dict[str, int] | None = None  # resume state only: epoch, batch (within it), step
    averages: dict[str, dict[str, Any]] | None = None  # resume state only, with --ema: each colour's weight average
    path: Path | None = None

    @property
    def colours(self) -> list[str]:
        return list(self.geometry)

    def metadata(self) -> dict[str, Any]:
        """Everything but the tensors, JSON-ready (written next to the checkpoint as <method>.json)."""
        return {
            "format": FORMAT, "format_version": FORMAT_VERSION, "method": self.method,
            "benchctl_version": self.benchctl_version, "torch_version": self.torch_version,
            "created_unix": round(self.created_unix, 3), "weights_dtype": self.weights_dtype,
            "colours": {c: {"geometry": self.geometry[c].to_dict(), "metrics": self.metrics.get(c, {})}
                        for c in self.geometry},
            "training": self.training,
        }

    def to_bytes(self, weights_dtype: str = "float32", *, resume: bool = False) -> bytes:
        """The checkpoint file's bytes; `resume` adds the optimiser state and position (weights stay float32)."""
        dtype = WEIGHT_DTYPES[weights_dtype if not resume else "float32"]
        weights = {}
        for colour, state in self.weights.items():
            converted = {k: v.detach().to("cpu", dtype) if v.is_floating_point() else v.detach().cpu()
                         for k, v in state.items()}
            bad = [k for k, v in converted.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
            if bad:
                raise BenchctlError(f"{self.method} {colour}: weights {', '.join(bad[:3])} are not finite as "
                                    f"{weights_dtype}; store them as float32")
            weights[colour] = converted
        data = self.metadata() | {"weights_dtype": "float32" if resume else weights_dtype, "weights": weights}
        if resume:
            data |= {"optimisers": self.optimisers, "position": self.position, "averages": self.averages}
        buffer = io.BytesIO()
        torch.save(data, buffer)
        return buffer.getvalue()

    def save(self, path: Path, weights_dtype: str = "float32") -> Path:
        """Write the checkpoint atomically, plus <stem>.json with its metadata; returns the path."""
        path = Path(path)
        atomic_write_bytes(path, self.to_bytes(weights_dtype))
        write_json(path.with_suffix(".json"), self.metadata() | {"weights_dtype": weights_dtype})
        return path

    def save_resume(self, path: Path) -> Path:
        """Write the resume state (float32 weights, optimisers, position) atomically to `path`."""
        return atomic_write_bytes(Path(path), self.to_bytes(resume=True))

    def model(self, colour: str, device: torch.device | str = "cpu") -> torch.nn.Module:
        """The trained network for `colour`, float32, in eval mode, on `device`."""
        model = build_model(self.method, OpticalSetup.of(self.geometry[colour]))
        try:
            model.load_state_dict(self.weights[colour])
        except RuntimeError as exc:
            raise BenchctlError(f"{self.path}: the {colour} weights do not fit {self.method}: {exc}") from None
        return model.to(device).eval()

    def differences(self, geometries: Mapping[str, Geometry], where: str) -> list[str]:
        """What keeps this checkpoint from serving `geometries` (colour -> geometry); empty when it fits.

        Differences shared by every colour are listed once, others with their colour's name.
        """
        missing = [c for c in geometries if c not in self.geometry]
        if missing:
            has = ", ".join(self.geometry)
            return [f"no model for colour {', '.join(map(repr, missing))} (the checkpoint has {has})"]
        per_colour = {c: geometry_differences(self.geometry[c], g, where) for c, g in geometries.items()}
        lists = [d for d in per_colour.values() if d]
        if not lists:
            return []
        if all(d == lists[0] for d in per_colour.values()):
            return lists[0]
        return [f"{c}: {'; '.join(d)}" for c, d in per_colour.items() if d]

    def check(self, geometries: Mapping[str, Geometry], where: str) -> None:
        """Refuse (BenchctlError naming each difference) unless this checkpoint fits `geometries`."""
        problems = self.differences(geometries, where)
        if problems:
            raise BenchctlError(f"checkpoint {self.path or '(unsaved)'} ({self.method}) does not fit {where}: "
                                + "; ".join(problems))

    def colour_for(self, geometry: Geometry) -> str:
        """The colour whose recorded geometry is exactly `geometry`; else a BenchctlError naming the differences
        from the colour of nearest wavelength."""
        for colour, recorded in self.geometry.items():
            if not geometry_differences(recorded, geometry, ""):
                return colour
        nearest = min(self.geometry, key=lambda c: abs(self.geometry[c].wavelength_m - geometry.wavelength_m))
        actual = geometry
        problems = geometry_differences(self.geometry[nearest], actual, "this optical setup")
        raise BenchctlError(f"checkpoint {self.path} ({self.method}) has no model for this optical setup; "
                            f"nearest is {nearest}: {'; '.join(problems)}")


def _require(data: Mapping[str, Any], key: str, path: Path) -> Any:
    if key not in data:
        raise BenchctlError(f"{path}: not a benchctl learned-method checkpoint (no {key!r})")
    return data[key]


def read_checkpoint(path: Path | str) -> Checkpoint:
    """Load and validate a checkpoint (or a .resume.pt file); weights come back as float32."""
    path = Path(path)
    try:
        with path.open("rb") as handle:
            if handle.read(4) != b"PK\x03\x04":  # torch.save writes zip archives
                raise BenchctlError(f"checkpoint {path}: not a checkpoint (not a file written by torch.save)")
        data = torch.load(path, map_location="cpu", weights_only=True)
    except BenchctlError:
        raise
    except FileNotFoundError:
        raise BenchctlError(f"checkpoint {path}: no such file") from None
    except IsADirectoryError:
        raise BenchctlError(f"checkpoint {path}: is a folder, expected a .pt file") from None
    except Exception as exc:  # noqa: BLE001  (zip, pickle and torch errors: not a checkpoint we can read)
        first_line = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise BenchctlError(f"checkpoint {path}: not a checkpoint benchctl can read ({first_line})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise BenchctlError(f"{path}: not a benchctl learned-method checkpoint")
    if int(_require(data, "format_version", path)) > FORMAT_VERSION:
        raise BenchctlError(f"{path}: checkpoint format {data['format_version']} is newer than this benchctl "
                            f"({benchctl.__version__}) reads ({FORMAT_VERSION}); update benchctl")
    method = _require(data, "method", path)
    if method not in LEARNED_METHODS:
        raise BenchctlError(f"{path}: unknown method {method!r} (known: {', '.join(LEARNED_METHODS)})")
    colours = _require(data, "colours", path)
    weights = _require(data, "weights", path)
    if set(colours) != set(weights) or not colours:
        raise BenchctlError(f"{path}: colours {sorted(colours)} and weights {sorted(weights)} do not agree")
    try:
        geometry = {c: Geometry.from_dict(v["geometry"]) for c, v in colours.items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise BenchctlError(f"{path}: a recorded optical geometry is not one benchctl reads ({exc})") from None
    return Checkpoint(
        method=method,
        geometry=geometry,
        weights={c: {k: v.float() if v.is_floating_point() else v for k, v in weights[c].items()} for c in colours},
        training=dict(data.get("training", {})),
        metrics={c: dict(v.get("metrics", {})) for c, v in colours.items()},
        benchctl_version=str(data.get("benchctl_version", "?")),
        torch_version=str(data.get("torch_version", "?")),
        created_unix=float(data.get("created_unix", 0.0)),
        weights_dtype=str(data.get("weights_dtype", "float32")),
        optimisers=data.get("optimisers"),
        position=data.get("position"),
        averages=data.get("averages"),
        path=path,
    )


CACHE_SIZE = 6  # checkpoints (and models) kept read: a procedure's few methods and colours


def _file_key(path: Path) -> tuple[str, int, int]:
    """A checkpoint file's version: its resolved path, modification time and size."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        raise BenchctlError(f"checkpoint {path}: no such file") from None
    return str(path.resolve()), stat.st_mtime_ns, stat.st_size


@functools.lru_cache(maxsize=CACHE_SIZE)
def _read(path: str, mtime_ns: int, size: int) -> Checkpoint:
    return read_checkpoint(path)


@functools.lru_cache(maxsize=CACHE_SIZE)
def _model(path: str, mtime_ns: int, size: int, colour: str, device: str) -> torch.nn.Module:
    model = _read(path, mtime_ns, size).model(colour, device)
    if device == "cpu":  # oneDNN's convolutions, transposed ones above all, run faster on channels-last weights
        model = model.to(memory_format=torch.channels_last)  # type: ignore[call-overload]  # documented, not typed
    return model


def cached_checkpoint(path: Path | str) -> Checkpoint:
    """`read_checkpoint`, remembered per version of the file, for repeated use."""
    return _read(*_file_key(Path(path)))


def cached_model(path: Path | str, colour: str, device: torch.device | str = "cpu") -> torch.nn.Module:
    """The eval-mode model of `colour` in checkpoint `path` on `device`, built once per (file, colour, device)."""
    return _model(*_file_key(Path(path)), colour, str(torch.device(device)))


def find_checkpoint(method: str, profile: Profile) -> Path | None:
    """The shipped (or user-placed) checkpoint of `method` for `profile`: checkpoints/<profile name>/<method>.pt
    in the working folder, else in the repository next to the package; None if there is none.

    Found by name only: whether its geometry fits the profile is checked when it is used (`checkpoint_problem`).
    """
    if method not in LEARNED_METHODS:
        raise BadValueError(f"{method!r} is not a learned method (learned: {', '.join(LEARNED_METHODS)})")
    relative = Path(CHECKPOINT_DIR) / profile.name / f"{method}.pt"
    for candidate in (relative, SOURCE_ROOT / relative):
        if candidate.is_file():
            return candidate
    return None


def profile_geometries(profile: Profile, channels: Sequence[str] | None = None) -> dict[str, Geometry]:
    """The optical geometry of each named laser channel of `profile` (all channels by default)."""
    names = list(channels) if channels is not None else [c.name for c in profile.channels]
    return {name: profile.geometry(name) for name in names}


def checkpoint_problem(path: Path, profile: Profile, channels: Sequence[str] | None = None) -> str | None:
    """Why checkpoint `path` cannot serve `profile` (its channels, or the named ones), or None if it can."""
    try:
        checkpoint = cached_checkpoint(path)
    except BenchctlError as exc:
        return str(exc)
    problems = checkpoint.differences(profile_geometries(profile, channels), f"profile {profile.name!r}")
    return "; ".join(problems) or None


def learned_method(name: str, checkpoint_path: Path | str) -> Method:
    """Registered method `name` (learned, or a refined `<learned>+sgd`) running the trained models of
    `checkpoint_path`, which must hold that network. It serves any optical setup one of the checkpoint's
    colours was trained for, exactly; any other setup is refused with the differences named."""
    method, path = get_method(name), Path(checkpoint_path)
    checkpoint = cached_checkpoint(path)
    if method.network is None:
        raise BadValueError(f"method {name!r} is not a learned method and takes no checkpoint (got {path})")
    if checkpoint.method != method.network:
        raise BadValueError(f"checkpoint {path} holds a {checkpoint.method} model, not {method.network}")

    def networks(setup: OpticalSetup, device: torch.device) -> torch.nn.Module:
        return cached_model(path, cached_checkpoint(path).colour_for(setup.geometry), device)

    return method.trained(networks, str(path))

"""Holograms for a calibrated bench: a scene's holograms and scores (`scene`, `depth`), the cache a run and the
console share (`cache`), `benchctl generate` (`generate`), and the learned methods' checkpoint files and the one
search rule for them (`checkpoints`, `checkpoint_notes`).

The face: what a run, the console and the benchmarks ask of this floor. Importing it loads torch.
"""

from benchctl.holograms.cache import Hologram, hologram
from benchctl.holograms.checkpoints import Checkpoint, find_checkpoint, read_checkpoint
from benchctl.holograms.depth import compute_depth_scene
from benchctl.holograms.scene import compute_scene, resolve_method, usable_methods

__all__ = ["Checkpoint", "Hologram", "compute_depth_scene", "compute_scene", "find_checkpoint", "hologram",
           "read_checkpoint", "resolve_method", "usable_methods"]

"""How much memory one training step needs, estimated before training starts, and whether this machine has it.

A training step's peak (forward, propagation, ROI loss, backward, Adam; batch 1) grows with the grid's pixels.
BYTES_PER_PIXEL holds, per network, the largest peak per pixel that `benchctl bench learned --grids` measured
on the paper's grids (docs/reproduction.md, "What fits in 24 GiB"); a method not measured takes the measured
network of its family and DCM factor. The estimate scales it by the grid and the batch.
"""

from __future__ import annotations

from benchctl.cgh.learned.models import VARIANTS
from benchctl.errors import BadValueError
from benchctl.limits import available_memory

BYTES_PER_PIXEL = {  # the largest per pixel, at 1088 x 1920 for all of them (fixed costs weigh most there)
    "holonet": 4323,
    "holonet-dcm2": 2511,
    "holonet-dcm4": 921,
    "holonet-pyramid": 2860,
    "ccnn": 526,
    "ccnn-dcm4": 490,
}
MEASURED_AS = {("holonet", 1): "holonet", ("holonet", 2): "holonet-dcm2", ("holonet", 4): "holonet-dcm4",
               ("ccnn", 1): "ccnn", ("ccnn", 4): "ccnn-dcm4"}


def step_bytes(method: str, grid: tuple[int, int], batch_size: int = 1) -> int:
    """Estimated peak bytes of one training step of `method` on `grid` with `batch_size` images."""
    variant = VARIANTS[method]
    measured = method if method in BYTES_PER_PIXEL else MEASURED_AS[(variant.family, variant.factor)]
    return BYTES_PER_PIXEL[measured] * grid[0] * grid[1] * batch_size


def check_training_memory(method: str, grid: tuple[int, int], batch_size: int) -> int:
    """The estimate for one step; BadValueError (one line, with both figures) if it exceeds what is available."""
    needed = step_bytes(method, grid, batch_size)
    available = available_memory()
    if available is not None and needed > available:
        raise BadValueError(f"training {method} on {grid[0]}x{grid[1]} with batch {batch_size} needs about "
                            f"{needed / 2**30:.1f} GiB per step, and this machine has {available / 2**30:.1f} GiB "
                            "available: use a smaller --size or --batch-size, or a DCM variant")
    return needed

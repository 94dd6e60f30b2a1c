#!/bin/sh
# Divide-conquer-and-merge in 3D on one GPU (docs/depth-learned.md): the peak CUDA memory of one training step (a
# 5-plane focal stack; torch.cuda.max_memory_allocated during the step minus before it) and the inference time
# (CUDA-synchronised, median of 5 after a warm-up) of holonet3d, holonet3d-dcm2 and holonet3d-dcm4 at 1088x1920 and
# 2176x3840, all in one process, with the ratios against holonet3d. About a minute on an H100.
#
#   PYTHONPATH=. sh docs/gpu/depth3d.sh          # from the repository root; writes $OUT/learned_device.csv, depth3d.txt
#   PYTHONPATH=. sh docs/gpu/depth3d.sh --tiny   # 64x128 and 128x256: checks the script runs (CPU or GPU)
set -eu
cd "$(dirname "$0")/../.."
OUT="${OUT:-$PWD/gpu-out}"
mkdir -p "$OUT"
GRIDS="1088x1920,2176x3840"
[ "${1:-}" = "--tiny" ] && GRIDS="64x128,128x256"
export PYTHONPATH="${PYTHONPATH:-.}" PYTHONUNBUFFERED=1
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || echo "no nvidia-smi"; } > "$OUT/gpu.txt"
status=0
"${PYTHON:-python3}" - "$OUT" "$GRIDS" > "$OUT/depth3d.txt" 2>&1 <<'PY' || status=$?
import sys
import time

import torch

from benchctl.benchmarks.learned import run_device_table
from benchctl.cgh.learned import DEPTH_METHODS
from benchctl.profiles import load_profile

out_dir, grids = sys.argv[1], [tuple(int(v) for v in g.split("x")) for g in sys.argv[2].split(",")]
start = time.perf_counter()
print(f"torch {torch.__version__}, Python {sys.version.split()[0]}, CUDA {torch.version.cuda}")
run_device_table(load_profile("simulated"), grids=grids, methods=DEPTH_METHODS, repeats=5, out_dir=out_dir)
print(f"total {time.perf_counter() - start:.1f} s")
PY
cat "$OUT/depth3d.txt"
exit "$status"

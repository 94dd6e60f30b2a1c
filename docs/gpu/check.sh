#!/usr/bin/env bash
# The GPU check of issue 36 (docs/gpu/README.md): run from the repository root on a machine with one CUDA GPU.
# Writes check.log and what it measured under $OUT (default ./gpu-out). Takes about 4-5 minutes on one H100.
# GPU_CHECK_DEVICE=cpu (with small GPU_CHECK_SIZE / GPU_CHECK_GRIDS / GPU_CHECK_STEPS) is the dry run for a
# machine without a GPU, so the script itself is tested before it spends GPU time.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT="${OUT:-$PWD/gpu-out}"
mkdir -p "$OUT"
export OUT PYTHONUNBUFFERED=1
PYTHON="${PYTHON:-python3}"
# benchctl runs from this source tree (pip install would pull torch 2.13 over the machine's CUDA build); the
# packages the machine lacks come as wheels in .whl/ (docs/gpu/README.md says how they were downloaded).
SITE="${GPU_CHECK_SITE:-/tmp/benchctl-site}"
if [ "${GPU_CHECK_WHEELS:-1}" = 1 ] && compgen -G ".whl/*.whl" >/dev/null; then
    "$PYTHON" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl \
        || { echo "installing .whl/ failed" | tee "$OUT/check.log"; exit 1; }
    export PYTHONPATH="$PWD:$SITE"
else
    export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
fi
{ nvidia-smi 2>&1 || echo "no nvidia-smi"; } > "$OUT/nvidia-smi.txt"
timeout "${GPU_CHECK_TIMEOUT:-340}" "$PYTHON" docs/gpu/check.py 2>&1 | tee "$OUT/check.log"
status=${PIPESTATUS[0]}
[ "$status" = 124 ] && echo "check.py stopped at its time limit" | tee -a "$OUT/check.log"
exit "$status"

#!/usr/bin/env bash
# The GPU run of 27 Nov 2026 (docs/gpu/README.md, 'Measured on one H100'), from the repository root: the learned networks' training-step memory and inference time per grid (3D and 2D, one
# process each), then the issue-36 check (docs/gpu/check.sh). Everything lands in $OUT/results.tgz.
set -u
R="${OUT:?}"
W=/tmp/gpurun; rm -rf "$W"; mkdir -p "$W/depth3d" "$W/table2d" "$W/check"
SITE=/tmp/benchctl-site
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$SITE" .whl/*.whl \
    || echo "wheel install failed"
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$W/gpu.txt"
GRIDS="${GRIDS:-1088x1920,2176x3840}"
if [ -z "${SKIP_TABLES:-}" ]; then
( PYTHONPATH="$PWD:$SITE" OUT="$W/depth3d" timeout 150 sh docs/gpu/depth3d.sh ${TINY:+--tiny} ) \
    ; echo "depth3d rc=$?"
( PYTHONPATH="$PWD:$SITE" PYTHONUNBUFFERED=1 timeout 120 python3 - "$W/table2d" "$GRIDS" <<'PY'
import sys, time, torch
from benchctl.benchmarks.learned import run_device_table
from benchctl.profiles import load_profile
out_dir, grids = sys.argv[1], [tuple(int(v) for v in g.split("x")) for g in sys.argv[2].split(",")]
start = time.perf_counter()
run_device_table(load_profile("simulated"), grids=grids, out_dir=out_dir, repeats=5,
                 methods=["holonet", "holonet-dcm2", "holonet-dcm4", "holonet-pyramid", "ccnn", "ccnn-dcm4"])
print(f"total {time.perf_counter() - start:.1f} s")
PY
) > "$W/table2d/table2d.txt" 2>&1; echo "table2d rc=$?"; cat "$W/table2d/table2d.txt"
fi
OUT="$W/check" GPU_CHECK_SITE="$SITE" GPU_CHECK_WHEELS=0 PYTHONPATH="$PWD:$SITE" GPU_CHECK_TIMEOUT="${CHECK_TIMEOUT:-260}" \
    bash docs/gpu/check.sh > "$W/check/stdout.txt" 2>&1; echo "check rc=$?"
tail -n 60 "$W/check/check.log" 2>/dev/null
tar czf "$R/results.tgz" -C "$W" .

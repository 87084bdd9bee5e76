#!/bin/bash
# Every GPU check of issue 42 in one go, for a short stint on a machine with an NVIDIA GPU (docs/gpu.md):
# the CUDA kernels' tests against the CPU's on the real GPU, then analysis/bench/gpu.py's figures.
# Run from the repository root; logs and figures go to $OUT (default gpu-out). Usage:
#   OUT=gpu-out bash analysis/bench/gpu_check.sh [--quick]
set -u
OUT=${OUT:-gpu-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/ensemble-numba-cache}
export NUMBA_CUDA_LOW_OCCUPANCY_WARNINGS=${NUMBA_CUDA_LOW_OCCUPANCY_WARNINGS:-0}
PYTHON=${PYTHON:-python3}
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1 | tee "$OUT/gpu.txt"
$PYTHON -c "import numba, numba_cuda; print('numba', numba.__version__, 'numba-cuda', numba_cuda.__version__)" \
    2>&1 | tee -a "$OUT/gpu.txt"
ENSEMBLE_TEST_GPU=1 NUMBA_ENABLE_CUDASIM=0 timeout 200 $PYTHON -m pytest -q -n 8 -p no:cacheprovider \
    tests/test_gpu.py 2>&1 | tee "$OUT/tests.log" | tail -40
timeout 300 $PYTHON analysis/bench/gpu.py "$@" --json "$OUT/gpu.json" 2>&1 | tee "$OUT/bench.log"

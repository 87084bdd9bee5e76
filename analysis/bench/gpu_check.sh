#!/bin/bash
# Every GPU check of issue 42, for a short stint on a machine with an NVIDIA GPU (docs/gpu.md). Run from the
# repository root; logs, figures and charts go to $OUT (default gpu-out). Stages, in the order given (default:
# all four; a device call is at most 10 minutes, so split them over two calls: `tests kernels`, then
# `whole float32`):
#   tests    the CUDA kernels' tests against the CPU's, on the real GPU             (up to 200 s)
#   kernels  analysis/bench/gpu.py's rates, crossover and float32 error (--quick:   (up to 300 s)
#            fewer sizes)
#   whole    a whole `ensemble run --device cuda` of 10^7 tops against its kernel   (up to 240 s)
#   float32  runs/work_precision_top.toml in float64 and float32, their table       (up to 150 s)
#            (the results come back in $OUT: chart them where matplotlib is, with
#            ensemble work-precision OUT/wp_float64.nc OUT/wp_float32.nc --charts DIR)
# Usage:
#   OUT=gpu-out bash analysis/bench/gpu_check.sh [--quick] [tests] [kernels] [whole] [float32]
set -u
OUT=${OUT:-gpu-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/ensemble-numba-cache}
export NUMBA_CUDA_LOW_OCCUPANCY_WARNINGS=${NUMBA_CUDA_LOW_OCCUPANCY_WARNINGS:-0}
PYTHON=${PYTHON:-python3}
QUICK=""
STAGES=()
for arg in "$@"; do
    case $arg in
        --quick) QUICK=--quick ;;
        tests|kernels|whole|float32) STAGES+=("$arg") ;;
        *) echo "gpu_check.sh: unknown argument $arg (stages: tests kernels whole float32; --quick)" >&2; exit 2 ;;
    esac
done
[ ${#STAGES[@]} -eq 0 ] && STAGES=(tests kernels whole float32)
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm --format=csv 2>&1 | tee -a "$OUT/gpu.txt"
$PYTHON -c "import numba, numba_cuda; print('numba', numba.__version__, 'numba-cuda', numba_cuda.__version__)" \
    2>&1 | tee -a "$OUT/gpu.txt"
for stage in "${STAGES[@]}"; do
    echo "== $stage $(date -u +%H:%M:%S)"
    case $stage in
        tests)
            ENSEMBLE_TEST_GPU=1 NUMBA_ENABLE_CUDASIM=0 timeout 200 $PYTHON -m pytest -q -n 8 -p no:cacheprovider \
                tests/test_gpu.py 2>&1 | tee "$OUT/tests.log" | tail -40 ;;
        kernels)
            timeout 300 $PYTHON analysis/bench/gpu.py $QUICK --only kernels --json "$OUT/gpu.json" 2>&1 \
                | tee "$OUT/bench.log" ;;
        whole)
            timeout 240 $PYTHON analysis/bench/gpu.py --only whole --json "$OUT/whole.json" 2>&1 \
                | tee "$OUT/whole.log" ;;
        float32)
            for precision in float64 float32; do
                timeout 70 $PYTHON -m ensemble run runs/work_precision_top.toml --device cuda --quiet --force \
                    --precision $precision -o "$OUT/wp_$precision.nc" 2>&1 | tee -a "$OUT/float32.log"
            done
            $PYTHON -m ensemble work-precision "$OUT/wp_float64.nc" "$OUT/wp_float32.nc" --charts "$OUT" 2>&1 \
                | tee -a "$OUT/float32.log" ;;
    esac
done

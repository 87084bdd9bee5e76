#!/bin/bash
# Every GPU check and benchmark (docs/gpu.md), for one short stint on a machine with an NVIDIA GPU: about 9.5
# minutes for all stages, in one device call. Run from the repository root; the log (log.txt, tests.log) and the
# figures (JSON, and the work-precision results) go to $OUT (default gpu-out), seven files in all. Stages, in the order given (default: all, in this order), each under its own time limit:
#   lorenz   the Lorenz yardstick, 2^23 systems: rk4 and dopri5 kernels in float64 and float32, and the  (130 s)
#            whole `ensemble run runs/lorenz.toml --device cuda` in each precision
#   rates    analysis/bench/gpu.py's kernel rates (quick sizes): chains of 16 to 1024 masses, (190 s)
#            in both layouts from 32 on (a block of threads, one thread per chain), tops up to 10^8
#   whole    `ensemble run --device cuda` of 10^7 tops (10^6 steps, 11 samples) against its kernel      (90 s)
#   tests    the CUDA kernels' tests against the CPU's, on the real GPU. It times nothing, so it runs   (360 s)
#            beside the stages after it
#   float32  runs/work_precision_top.toml in float64 and float32, their table (chart them where          (120 s)
#            matplotlib is: ensemble work-precision OUT/wp_float64.nc OUT/wp_float32.nc --charts DIR)
#   cache    a small run twice, each in a new process with one fresh cache: the second loads its      (40 s)
#            kernels (cuda.jit(cache=True))
#   kernels  the full kernel figures of gpu.py: rates, crossover and float32's error (not in the     (300 s)
#            default: a call of its own)
#   events   analysis/bench/event_cost.py on the GPU: 2^22 tops with events that never fire against   (300 s)
#            none, and 2^18 chains of 16 masses (issue 52's cost); then 10^7 tops keeping one tilt event
#            and no samples, written to NetCDF and to Zarr (not in the default)
# Usage:
#   OUT=gpu-out bash analysis/bench/gpu_check.sh [stage ...]
#   TOPS="100000000" RATES_SECONDS=80 bash analysis/bench/gpu_check.sh rates     # tops of these sizes alone
set -u
OUT=${OUT:-gpu-out}
mkdir -p "$OUT"
export PYTHONUNBUFFERED=1 PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH}
export NUMBA_CACHE_DIR=${NUMBA_CACHE_DIR:-/tmp/ensemble-numba-cache}
export NUMBA_CUDA_LOW_OCCUPANCY_WARNINGS=${NUMBA_CUDA_LOW_OCCUPANCY_WARNINGS:-0}
PYTHON=${PYTHON:-python3}
STAGES=()
for arg in "$@"; do
    case $arg in
        lorenz|rates|whole|tests|float32|cache|kernels|events) STAGES+=("$arg") ;;
        *) echo "gpu_check.sh: unknown stage $arg (lorenz rates whole tests float32 cache kernels events)" >&2
           exit 2 ;;
    esac
done
[ ${#STAGES[@]} -eq 0 ] && STAGES=(lorenz rates whole tests float32 cache)
{
    nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.max.sm,power.max_limit,pci.bus_id --format=csv
    nvidia-smi -q | grep -i -E "product name|form factor|board part|product brand" | sort -u
    $PYTHON -c "import numba, numba_cuda; print('numba', numba.__version__, 'numba-cuda', numba_cuda.__version__)"
} 2>&1 | tee -a "$OUT/log.txt"
$PYTHON - <<'EOF' 2>&1 | tee -a "$OUT/log.txt"  # a minute's check before the stages: a CUDA kernel compiles and runs
import numpy as np
from numba import cuda

@cuda.jit
def one_more(a):
    a[cuda.grid(1)] += 1

a = cuda.to_device(np.zeros(64))
one_more[2, 32](a)
assert a.copy_to_host().sum() == 64
print("numpy", np.__version__, "and numba-cuda compile and run a kernel")
EOF
[ "${PIPESTATUS[0]}" -eq 0 ] || { echo "gpu_check.sh: numba-cuda cannot compile here; stopping" | tee -a "$OUT/log.txt"; exit 1; }
TESTS=""
for stage in "${STAGES[@]}"; do
    echo "== $stage $(date -u +%H:%M:%S)"
    case $stage in
        lorenz)
            timeout ${LORENZ_SECONDS:-130} $PYTHON analysis/bench/gpu.py --only lorenz --repeats 5 --json "$OUT/lorenz.json" 2>&1 \
                | tee -a "$OUT/log.txt" ;;
        rates)
            timeout ${RATES_SECONDS:-190} $PYTHON analysis/bench/gpu.py --quick --only rates --target 0.2 \
                ${TOPS:+--tops $TOPS} --json "$OUT/rates.json" 2>&1 | tee -a "$OUT/log.txt" ;;
        whole)
            timeout 90 $PYTHON analysis/bench/gpu.py --only whole --whole-steps 1000000 --whole-samples 11 \
                --json "$OUT/whole.json" 2>&1 | tee -a "$OUT/log.txt" ;;
        tests)
            ENSEMBLE_TEST_GPU=1 NUMBA_ENABLE_CUDASIM=0 timeout ${TESTS_SECONDS:-360} $PYTHON -m pytest -q -n 14 -p no:cacheprovider \
                tests/test_gpu.py > "$OUT/tests.log" 2>&1 &
            TESTS=$! ;;
        float32)
            for precision in float64 float32; do
                timeout 60 $PYTHON -m ensemble run runs/work_precision_top.toml --device cuda --quiet --force \
                    --precision $precision -o "$OUT/wp_$precision.nc" 2>&1 | tee -a "$OUT/log.txt"
            done
            $PYTHON -m ensemble work-precision "$OUT/wp_float64.nc" "$OUT/wp_float32.nc" 2>&1 \
                | tee -a "$OUT/log.txt" ;;
        cache)
            fresh=$(mktemp -d)
            sed -e 's/members = 8388608/members = 100000/' -e "s#\.\./examples#$PWD/examples#" runs/lorenz.toml \
                > "$fresh/small.toml"
            for try in first second; do
                start=$(date +%s%N)
                NUMBA_CACHE_DIR=$fresh/numba ENSEMBLE_KERNEL_DIR=$fresh/kernels timeout 40 $PYTHON -m ensemble run \
                    "$fresh/small.toml" --device cuda --force -o "$fresh/small.nc" 2>&1 | tail -3
                echo "cache: $try run $(( ($(date +%s%N) - start) / 1000000 )) ms in all"
            done 2>&1 | tee -a "$OUT/log.txt"
            echo "cache: $(find "$fresh/numba" -name '*.nbi' | wc -l) index files, $(find "$fresh/numba" -name '*.nbc' \
                | wc -l) data files" | tee -a "$OUT/log.txt" ;;
        kernels)
            timeout 300 $PYTHON analysis/bench/gpu.py --only kernels --json "$OUT/gpu.json" 2>&1 \
                | tee -a "$OUT/log.txt" ;;
        events)
            timeout 150 $PYTHON analysis/bench/event_cost.py --device cuda --members 4194304 --repeats 3 --t-end 5 \
                2>&1 | tee -a "$OUT/log.txt"
            timeout 60 $PYTHON analysis/bench/event_cost.py --device cuda --sites 16 --methods verlet rk4 \
                --members 262144 --repeats 3 --t-end 5 2>&1 | tee -a "$OUT/log.txt"
            fresh=$(mktemp -d)  # 10^7 prolate tops keeping the time their tilt rises through 0.6 rad, no samples
            cat > "$fresh/tip.toml" <<'TOML'
scene = "top"
method = "rk4"
dt = 1e-3
t_end = 5.0
save_dt = 5.0
save = []
members = 10000000
seed = 7

[parameters]
lambda1 = 1.0e-3
lambda3 = 0.5e-3
c = 1.0e-4
spin0 = 60.0
tilt0 = { uniform = [0.5, 0.6] }
azimuth0 = { uniform = [0.0, 6.283185307179586] }

[events.tip]
of = "tilt"
value = 0.6
direction = "up"
TOML
            for out in tip.nc tip.zarr; do  # the Zarr store's path on the GPU too
                start=$(date +%s%N)
                timeout 90 $PYTHON -m ensemble run "$fresh/tip.toml" --device cuda --quiet -o "$fresh/$out" 2>&1 | tail -3
                echo "events: 10^7 tops, 5000 rk4 steps, a tilt event, no samples, to $out:" \
                    "$(( ($(date +%s%N) - start) / 1000000 )) ms in all, $(du -sb "$fresh/$out" | cut -f1) bytes"
                $PYTHON -c "import sys, xarray as x; d = x.open_dataset(sys.argv[1], engine=None if sys.argv[1]\
.endswith('nc') else 'zarr'); print('  tip_count sum', int(d.tip_count.sum()), 'tip_time median',\
float(d.tip_time.median()))" "$fresh/$out"
            done 2>&1 | tee -a "$OUT/log.txt" ;;
    esac
done
if [ -n "$TESTS" ]; then
    wait "$TESTS"
    echo "== tests (exit $?)"
    tail -30 "$OUT/tests.log"
fi
echo "== done $(date -u +%H:%M:%S)"

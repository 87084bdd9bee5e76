"""The host line every benchmark prints first: kernel speed depends on the CPU, its vectors and the threads."""
from __future__ import annotations

import os
import platform
from pathlib import Path

#: The hand-written C kernels beside the checkout: the machine's limit (python ../shared/limit/limit.py).
LIMIT = Path(__file__).resolve().parents[2] / "shared" / "limit" / "limit.py"


def quiet_openmp() -> None:
    """Let OpenMP's threads sleep when a C call ends, unless the environment says otherwise: by default they spin
    for milliseconds, beside the kernel timed next in the same process. Set before the C library loads."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def limit_module():
    """limit.py imported as a module (its kernels compiled with gcc on first use; OpenMP quiet, see
    quiet_openmp), or None without it. limit.py links its library with -ffast-math, which sets flush-to-zero
    for the whole process when it loads: a process that loads it times kernels, and must not check results."""
    if not LIMIT.exists():
        return None
    import importlib.util

    quiet_openmp()

    spec = importlib.util.spec_from_file_location("limit", LIMIT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def host() -> str:
    """CPU model, widest vector extension and Numba's thread count."""
    model, flags = platform.processor() or "unknown CPU", set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
            elif line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
    except OSError:
        pass
    widest = next((f for f in ("avx512f", "avx2", "avx", "sse4_2", "neon") if f in flags), "unknown")
    threads = os.environ.get("NUMBA_NUM_THREADS") or str(os.cpu_count())
    return f"host: {model}, widest vectors {widest}, {threads} threads"


def force_chain_block(block: int, adaptive_only: bool = False) -> None:
    """Run the chains' kernels (with adaptive_only, their adaptive ones alone) in blocks of `block` members instead
    of the block ensemble.scenes.chain.kernels.block_size picks for this host. Call it before any chain kernel is
    built: Numba caches each block size's kernel apart (a closure constant)."""
    from ensemble.scenes.chain import kernels

    choose = kernels.block_size
    kernels.block_size = lambda constants, method: (block if method.adaptive or not adaptive_only
                                                    else choose(constants, method))

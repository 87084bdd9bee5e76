"""The host line every benchmark prints first: kernel speed depends on the CPU, its vectors and the threads."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

#: The hand-written C kernels beside the checkout: the machine's limit (python ../shared/limit/limit.py).
LIMIT = Path(__file__).resolve().parents[3] / "shared" / "limit" / "limit.py"


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


_SERVE = """
import sys
sys.path.insert(0, {folder!r})
from hostinfo import limit_module
limit = limit_module()


def rate(name):
    if name == "top rk4":
        return limit.top_rk4_rate(repeats=3)
    return limit.chain_verlet_rate(N=int(name.split("N=")[1]), repeats=3)[0]


seen = set()
for line in sys.stdin:
    name = line.strip()
    if name not in seen:  # a kernel's first call in this process is slower: not a measurement
        seen.add(name)
        rate(name)
    print(rate(name), flush=True)
"""


class CBeside:
    """limit.py's C kernels in a process of their own, timed when asked: rate("top rk4") in member-steps/s,
    rate("chain verlet N=16") in mass-steps/s at its best block, as limit.py measures them but from the median
    of 3 timed calls where limit.py takes 5 (after an untimed first call). A benchmark asks right after each of
    its own timed calls, so that its ratios to the C are taken round by round, not against a C measured minutes
    before. A process apart, since limit.py's -ffast-math library sets flush-to-zero for the process that loads
    it. `available` is False without limit.py."""

    def __init__(self):
        self.available = LIMIT.exists()
        self._process = None
        if self.available:
            quiet_openmp()
            self._process = subprocess.Popen([sys.executable, "-c", _SERVE.format(folder=str(Path(__file__).parent))],
                                             stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)

    def rate(self, name: str) -> float:
        """The C kernel `name`'s rate now."""
        self._process.stdin.write(name + "\n")
        self._process.stdin.flush()
        answer = self._process.stdout.readline()
        if not answer:
            raise RuntimeError(f"limit.py stopped while timing {name}")
        return float(answer)

    def close(self) -> None:
        if self._process is not None:
            self._process.stdin.close()
            self._process.wait()
            self._process = None


def host() -> str:
    """CPU model, widest vector extension and Numba's thread count."""
    from ensemble.tuning import cpu

    model, flags = cpu()
    widest = next((f for f in ("avx512f", "avx2", "avx", "sse4_2", "neon") if f in flags), "unknown")
    threads = os.environ.get("NUMBA_NUM_THREADS") or str(os.cpu_count())
    return f"host: {model}, widest vectors {widest}, {threads} threads"


def force_chain_block(block: int, adaptive_only: bool = False) -> None:
    """Run the chains' kernels (with adaptive_only, their adaptive ones alone) in blocks of `block` members instead
    of the block ensemble.engine.sites.block_size picks for this host (each block's kernel is a file of its
    own: ensemble.engine.kernels)."""
    from ensemble.engine import sites

    choose = sites.block_size
    sites.block_size = lambda constants, method, tuning: (block if method.adaptive or not adaptive_only
                                                            else choose(constants, method, tuning))

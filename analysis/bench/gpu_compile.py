"""Every generated CUDA kernel compiled for a real GPU, with no GPU here (docs/gpu.md, "Testing"): NVVM turns each
into PTX for a compute capability, and ptxas (from the cuda extra's wheels) reports what one thread uses: registers,
stack frame (local memory), spills, and the block's shared memory. The simulator the tests use runs the kernels as
Python and type-checks nothing; this is the check that the real compiler takes them all.

    pip install ".[cuda]"                       # numba-cuda with its CUDA 12 wheels: NVVM and ptxas
    python analysis/bench/gpu_compile.py        # every scene, method, chain layout and precision
    python analysis/bench/gpu_compile.py --cc 8.0 --precision float64
    python analysis/bench/gpu_compile.py --only events  # the event kernels alone

Exit status 1 when any kernel does not compile.
"""
from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import types
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(Path(__file__).parent))
CHAINS = (16, 128, 1024)  # masses: registers, one thread per chain, and the block layouts


def without_a_gpu(cc: tuple[int, int]) -> None:
    """Device functions ask the current GPU for its compute capability when they compile; with none here, they
    are told `cc`. (Kernels are given theirs: cuda.compile_ptx(..., cc=cc).)"""
    import numba.cuda.dispatcher as dispatcher

    dispatcher.get_current_device = lambda: types.SimpleNamespace(compute_capability=cc)


def signature(adaptive: bool, precision: str) -> tuple:
    """The argument types GpuLaunch passes: (rows, members) float64 inputs, samples in the run's precision, then
    the events' arrays (ensemble.engine.events: empty where a kernel has none)."""
    from numba import typeof

    rows, one = typeof(np.zeros((2, 2))), typeof(np.zeros(2))
    head = (rows, rows) + ((rows, typeof(1.0)) if adaptive else (typeof(1.0), typeof(1)))
    head += (typeof(np.zeros(2, dtype=precision)), typeof(np.zeros((2, 2, 2), dtype=precision)))
    events = tuple(typeof(np.zeros((2,) * dims)) for dims in (2, 3, 2, 2, 4))  # spec, times, counts, stopped, states
    return (head + ((rows,) if adaptive else ()) + (typeof(np.zeros(2, np.int8)), one, rows, typeof(1), typeof(1))
            + events)


def ptxas() -> str | None:
    try:
        import nvidia.cuda_nvcc

        found = Path(nvidia.cuda_nvcc.__path__[0]) / "bin" / "ptxas"
        return str(found) if found.exists() else shutil.which("ptxas")
    except ImportError:
        return shutil.which("ptxas")


def resources(ptx: str, cc: tuple[int, int], assembler: str | None) -> str:
    """ptxas's account of the kernel: registers, stack frame, spills, shared memory (one line); RuntimeError where
    ptxas refuses it."""
    if assembler is None:
        return "(no ptxas: registers not counted)"
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "kernel.ptx"
        path.write_text(ptx)
        done = subprocess.run([assembler, f"-arch=sm_{cc[0]}{cc[1]}", "-v", str(path), "-o", "/dev/null"],
                              capture_output=True, text=True)
    said = done.stderr
    if done.returncode != 0:  # it would not load on a GPU either (an unresolved function, say)
        raise RuntimeError(f"ptxas: {said.strip().splitlines()[-1] if said.strip() else done.returncode}")
    entry = said.find("Compiling entry function")  # the kernel's own account; device functions' follow it
    kernel = said[entry:said.find("Compile time", entry)] if entry >= 0 else said
    numbers = {name: re.search(pattern, kernel) for name, pattern in (
        ("registers", r"Used (\d+) registers"), ("stack", r"(\d+) bytes stack frame"),
        ("spills", r"(\d+) bytes spill stores"), ("shared", r"(\d+) bytes smem"))}
    return ", ".join(f"{name} {match.group(1)}" for name, match in numbers.items() if match)


EVENTS = {"top": (("function", "value_tilt", -1, "watch_tilt"), ("state", 2)), "chain": (("state", 0), ("state", 17))}


def kernels(precisions: tuple[str, ...]):
    """(what, GpuKernel, method) for every built-in scene and the user example, every method with a kernel,
    chains of CHAINS masses in each layout, and the event kernels of the top (its tilt, watched, and omega[2]) and
    of a chain (mass 1's x, mass 2's v)."""
    from gpu import chain_layouts  # analysis/bench/gpu.py, beside this file

    from ensemble.engine import gpu_launch
    from ensemble.scenes import methods_for, resolve

    cases = [(resolve(name), {}, ()) for name in ("top", "body")]
    cases.append((resolve(str(ROOT / "examples" / "driven_oscillator.py")), {}, ()))
    cases += [(resolve("chain"), {"n": n, "boundary": "fixed"}, ()) for n in CHAINS]
    cases += [(resolve("top"), {}, EVENTS["top"]), (resolve("chain"), {"n": CHAINS[0], "boundary": "fixed"},
                                                    EVENTS["chain"])]
    for scene, constants, events in cases:
        for method in (m for m in methods_for(scene) if not m.closed_form):
            for _ in chain_layouts(constants.get("n", 0)) if not events else ("",):
                for precision in precisions:
                    what = (f"{scene.NAME} {constants.get('n', '')} {method.name}{' events' * bool(events)} "
                            f"{precision}").replace("  ", " ")
                    chosen = gpu_launch.layout(scene, method, constants, events)
                    yield what, gpu_launch.kernel(scene, method, constants, precision, chosen), method


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cc", default="9.0", help="compute capability to compile for (default 9.0: H100, H200)")
    parser.add_argument("--precision", choices=("float64", "float32"), help="only this precision (default both)")
    parser.add_argument("--only", default="", help="only the kernels whose description holds this text")
    args = parser.parse_args()
    cc = tuple(int(x) for x in args.cc.split("."))
    without_a_gpu(cc)
    from numba import cuda

    assembler, failed = ptxas(), 0
    print(f"compute capability {args.cc}; ptxas: {assembler or 'not found'}")
    for what, kernel, method in kernels((args.precision,) if args.precision else ("float64", "float32")):
        if args.only not in what:
            continue
        try:
            ptx, _ = cuda.compile_ptx(kernel.function.py_func, signature(method.adaptive, what.split()[-1]), cc=cc)
            account = resources(ptx, cc, assembler)
        except Exception as error:  # noqa: BLE001 (what the compiler said, whatever it was)
            failed += 1
            print(f"{what}: does not compile: {type(error).__name__}: {str(error).splitlines()[0][:300]}")
            continue
        print(f"{what}, {kernel.threads} thread{'s' * (kernel.threads > 1)} per member: {account}", flush=True)
    print(f"{failed} kernels did not compile" if failed else "every kernel compiled")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

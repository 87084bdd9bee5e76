"""The host line every benchmark prints first: kernel speed depends on the CPU, its vectors and the threads."""
from __future__ import annotations

import os
import platform
from pathlib import Path


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

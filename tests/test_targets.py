"""The same bits for every compile target this host can run (issue 50): each method family's kernel, and an event
kernel watching the top's tilt, compiled for the host's own CPU and for other CPU names through NUMBA_CPU_NAME
(AVX2's generic x86-64-v3, and AVX-512's skylake-avx512 where the host has it), gives the same results to the
last bit, freshly compiled and loaded from Numba's disk cache alike. Fast math is contraction into fused
multiply-adds only, so LLVM has no licence to regroup arithmetic differently for another vector width or CPU.
(With full fast math a chain's dopri5 took other last bits on an AMD Zen 4 than on an Intel Xeon, and other bits
for skylake-avx512 than for x86-64-v3 on one machine; kernels compiled with parallel=True once gave other bits
in the process that compiled them than in the later ones that loaded them.)"""
from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys

import pytest

import ensemble
from ensemble.tuning import cpu

from .conftest import top_runfile

TOPS = (top_runfile(members=5, t_end=1.0, save_dt=0.1, method=None)
        + '[[sweep]]\nmethod = ["rk4", "split2"]\n[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-9]\n')
CHAINS = """scene = "chain"
dt = 0.01
t_end = 4.0
save_dt = 0.5
members = 3
seed = 11
[parameters]
n = 4
boundary = "free"
m = { uniform = [0.5, 2.0] }
k = { uniform = [0.5, 2.0] }
x0 = { normal = [0.0, 0.3] }
v0 = 0.0
[[sweep]]
method = ["verlet"]
[[sweep]]
method = ["dopri5"]
rtol = [1e-9]
"""
EVENTS = (top_runfile(members=5, t_end=2.0, save_dt=0.5, method="split4",
                      parameters={"lambda3": 0.5e-3, "tilt0": {"uniform": [0.38, 0.44]}})
          + '[events.tip]\nof = "tilt"\nvalue = 0.45\ndirection = "up"\nstop = true\n'  # watch_tilt's sign
          + '[events.turn]\nof = "omega"\nindex = 0\ncount = 8\nkeep = ["omega"]\n')
RUNS = {"tops": TOPS, "chains": CHAINS, "events": EVENTS}

# What each CPU name needs of the host, from LLVM's definitions of them (x86-64-v3: AVX2, FMA, BMI1 and 2, ...)
NEEDS = {"x86-64-v3": {"avx2", "fma", "bmi1", "bmi2", "movbe", "f16c", "abm"},
         "skylake-avx512": {"avx512f", "avx512bw", "avx512dq", "avx512vl", "avx512cd", "fma"}}

DIGEST = """
import hashlib, json, sys
import ensemble
found = {}
for label, text in json.loads(sys.argv[1]).items():
    ds = ensemble.run(text, progress=False)
    for name in sorted(ds.data_vars):
        if name != "seconds_per_step":
            found[f"{label}:{name}"] = hashlib.sha256(ds[name].values.tobytes()).hexdigest()
print(json.dumps(found))
"""


def _digests(cpu_name: str | None, cache) -> dict[str, str]:
    """Every result variable's SHA-256 of the runs above, computed in a process compiling for `cpu_name` (None:
    the host's own CPU) with Numba's cache and the generated kernels in `cache`."""
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_NAME", "NUMBA_CPU_FEATURES",
                                                            "ENSEMBLE_KERNEL_DIR")}
    env["NUMBA_CACHE_DIR"] = str(cache)
    if cpu_name:
        env["NUMBA_CPU_NAME"] = cpu_name
    done = subprocess.run([sys.executable, "-c", DIGEST, json.dumps(RUNS)], env=env,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.fixture(scope="module")
def host_digests():
    """In this process: kernels that the other tests compile for the host are loaded from the cache."""
    found = {}
    for label, text in RUNS.items():
        ds = ensemble.run(text, progress=False)
        found.update({f"{label}:{name}": hashlib.sha256(ds[name].values.tobytes()).hexdigest()
                      for name in sorted(ds.data_vars) if name != "seconds_per_step"})
    return found


@pytest.mark.parametrize("cpu_name", sorted(NEEDS))
def test_every_target_the_host_runs_gives_the_host_bits(cpu_name, host_digests, tmp_path):
    missing = NEEDS[cpu_name] - cpu()[1]
    if missing:
        pytest.skip(f"this host cannot run {cpu_name} code (no {', '.join(sorted(missing))})")
    cache = tmp_path / "cache"
    for how in ("compiled", "cached"):  # an empty cache: every kernel compiles; then every one loads
        found = _digests(cpu_name, cache)
        assert found.keys() == host_digests.keys()
        differ = sorted(key for key in found if found[key] != host_digests[key])
        assert not differ, f"{how} for {cpu_name}, these differ from the host's own: {differ}"
        if how == "compiled":
            compiled = sorted(path.name for path in cache.rglob("*.nbc"))
    assert len(compiled) >= 5 and sorted(path.name for path in cache.rglob("*.nbc")) == compiled  # none again

"""Results do not depend on where a kernel came from: freshly compiled or loaded from Numba's disk cache.

Kernels compiled with parallel=True gave different bits in the process that compiled them than in later ones
that loaded them (the top's dopri5 on runs/work_precision_top.toml: 128 of 765 omega values differed).
The kernels now release the GIL and run on the package's own threads instead.
"""
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import xarray as xr

SWEEPS = '[[sweep]]\nmethod = ["{0}", "{1}"]\n\n[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-8]\n'
RUNS_FOLDER = Path(__file__).resolve().parents[1] / "runs"


def _without_sweeps(path: Path, methods) -> str:
    """A run file's text untimed, without its [[sweep]] tables of the given methods."""
    head, *sweeps = path.read_text().replace("timing = true", "timing = false").split("\n[[sweep]]")
    return head + "".join("\n[[sweep]]" + table for table in sweeps
                          if not any(f'method = ["{name}"]' in table for name in methods))


# Every kernel family: a Runge-Kutta tableau, a splitting and the adaptive pair, of each scene (the top's: every
# method, over the range of steps and tolerances where the parallel kernels differed).
RUNS = {
    "top": _without_sweeps(RUNS_FOLDER / "work_precision_top.toml", ("euler", "split4")),
    "body": ('scene = "body"\ndt = 1e-3\nt_end = 0.3\nsave_dt = 0.1\nmembers = 130\nseed = 3\n[parameters]\n'
             'lambda1 = 1.0\nlambda2 = 2.0\nlambda3 = 2.5\nc = 0.1\nspin0 = 10.0\ntilt0 = { uniform = [0.1, 1.0] }\n'
             'azimuth0 = 0.5\nspin_axis = 2\n' + SWEEPS.format("euler", "rotations2")),
    "chain": ('scene = "chain"\ndt = 0.01\nt_end = 1.0\nsave_dt = 0.5\nmembers = 70\nseed = 3\n[parameters]\nn = 1\n'
              'm = { uniform = [0.5, 2.0] }\nk = 1.0\nx0 = { normal = [0.0, 0.1] }\nv0 = 0.0\n'
              + SWEEPS.format("euler", "symplectic_euler")),
}


def _runs(folder, cache, tag):
    """Run every scene's file in its own process at once, all with Numba's cache in `cache`; their datasets."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    outputs = {scene: folder / f"{scene}_{tag}.nc" for scene in RUNS}
    command = [sys.executable, "-m", "ensemble", "run"]
    started = {scene: subprocess.Popen([*command, str(folder / f"{scene}.toml"), "-o", str(out), "--quiet"], env=env,
                                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
               for scene, out in outputs.items()}
    for scene, run in started.items():
        _, err = run.communicate(timeout=600)
        assert run.returncode == 0, (scene, err)
    return {scene: xr.load_dataset(out) for scene, out in outputs.items()}


def test_every_kernel_family_gives_the_same_bits_compiled_and_cached(tmp_path):
    for scene, text in RUNS.items():
        (tmp_path / f"{scene}.toml").write_text(text)
    cache = tmp_path / "cache"
    fresh = _runs(tmp_path, cache, "fresh")  # an empty cache: every kernel compiles
    compiled = sorted(p.name for p in cache.rglob("*.nbc"))
    cached = _runs(tmp_path, cache, "cached")
    assert len(compiled) >= 9 and sorted(p.name for p in cache.rglob("*.nbc")) == compiled  # nothing compiled again
    for scene in RUNS:
        for name, variable in fresh[scene].data_vars.items():
            a, b = variable.values, cached[scene][name].values
            same = np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
            assert a.dtype == b.dtype and same, f"{scene} {name}: {np.sum(a != b)} values differ"


def test_every_kernel_is_keyed_on_the_helpers_and_its_scenes_physics():
    """Numba keys a cached kernel on its own file (and closure) alone. A kernel generated from the engine's templates
    lives in a file whose text holds hashes of the helpers it inlines (blocks.HELPERS; sites.SITES_HELPERS, which
    includes it, for a field of sites), of its scene's physics file and of the compile target, so a change to any
    makes a new file that compiles anew."""
    import hashlib
    import importlib
    import json

    from llvmlite import binding

    from ensemble.engine import kernels
    from ensemble.engine.blocks import HELPERS
    from ensemble.engine.sites import SITES_HELPERS
    from ensemble.methods import METHODS
    from ensemble.scenes import SCENES, applies

    constants = {"top": {}, "body": {"spin_axis": 2}, "chain": {"n": 16, "boundary": "fixed"}}
    for name, scene in SCENES.items():
        for method in METHODS.values():
            if not applies(method, scene) or method.closed_form:
                continue
            function = kernels.kernel(scene, method, constants[name]).function.py_func
            text = Path(function.__code__.co_filename).read_text()
            helpers = SITES_HELPERS if getattr(scene, "SITES", False) else HELPERS
            file = importlib.import_module(scene.PHYSICS).__file__
            physics = hashlib.sha256(json.dumps({file: hashlib.sha256(Path(file).read_bytes()).hexdigest()})
                                     .encode()).hexdigest()
            assert f"# helpers: {helpers}" in text and f"# physics: {physics}" in text, (name, method.name)
            assert text.startswith(f"# compiled for: cpu {binding.get_host_cpu_name()}; "), (name, method.name)

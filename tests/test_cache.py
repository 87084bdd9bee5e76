"""A kernel is keyed on everything its arithmetic depends on, so a change compiles anew and nothing else does.
(That a kernel loaded from Numba's disk cache gives the bits of one freshly compiled is tests/test_targets.py's.)
"""
from pathlib import Path


def test_every_kernel_is_keyed_on_the_helpers_and_its_scenes_physics():
    """Numba keys a cached kernel on its own file (and closure) alone. A kernel the engine generates
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
            helpers = SITES_HELPERS if scene.SITES else HELPERS
            file = importlib.import_module(scene.PHYSICS).__file__
            physics = hashlib.sha256(json.dumps({file: hashlib.sha256(Path(file).read_bytes()).hexdigest()})
                                     .encode()).hexdigest()
            assert f"# helpers: {helpers}" in text and f"# physics: {physics}" in text, (name, method.name)
            assert text.startswith(f"# compiled for: cpu {binding.get_host_cpu_name()}; "), (name, method.name)


def test_a_kernels_work_rows_are_counted_without_making_it(tmp_path, monkeypatch):
    """A run's memory check counts each kernel's work rows (launch.layout) before anything is compiled: the
    count is the made kernel's own, for every scene, method and chain layout (a ring's tiles hold halos), and
    counting writes no kernel file."""
    from ensemble.engine import kernels, launch
    from ensemble.methods import METHODS
    from ensemble.scenes import SCENES, applies

    monkeypatch.setenv("ENSEMBLE_KERNEL_DIR", str(tmp_path))
    chains = [{"n": n, "boundary": boundary} for n in (16, 1024) for boundary in ("fixed", "periodic")]
    cases = [(SCENES["top"], {}), (SCENES["body"], {"spin_axis": 2})] + [(SCENES["chain"], c) for c in chains]
    for scene, constants in cases:
        for method in METHODS.values():
            if not applies(method, scene) or method.closed_form:
                continue
            counted = launch.layout(scene, method, constants).rows
            assert not any(tmp_path.rglob("*.py")), (scene.NAME, method.name)
            assert counted == kernels.kernel(scene, method, constants).rows, (scene.NAME, method.name, constants)
            for made in tmp_path.rglob("*.py"):
                made.unlink()

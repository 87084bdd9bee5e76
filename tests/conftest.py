"""Shared helpers: run-file text from Python values. The CUDA kernels run under numba-cuda's simulator unless
ENSEMBLE_TEST_GPU=1 (set on a machine with a GPU to test them there)."""
from __future__ import annotations

import os
import sys

import pytest

if os.environ.get("ENSEMBLE_TEST_GPU") != "1":
    os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")
    # The simulator runs a block's CUDA threads as Python threads, which hand the GIL to each other at every
    # barrier while its own thread polls them: at Python's 5 ms switch interval a simulated dopri5 run of 600
    # steps took 6 to 30 s, at 0.1 ms 1.6 to 2.3 s.
    sys.setswitchinterval(1e-4)

if "ENSEMBLE_TUNING_FILE" not in os.environ:  # runs under test keep the engine's defaults and say nothing of tuning
    import tempfile
    from pathlib import Path

    os.environ["ENSEMBLE_TUNING_FILE"] = str(Path(tempfile.mkdtemp()) / "tuning.json")  # before ensemble's import
    from ensemble import tuning

    tuning.save(tuning.Tuning(), {})
    tuning.pending_line()  # the untuned hint of the import, before the file was there


def _toml_value(value) -> str:
    if isinstance(value, str):
        return f'"{value}"'
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + " }"
    return repr(value)


def top_runfile(parameters=None, sweep=None, **top_level) -> str:
    """Text of a small top run file; keyword arguments override or (with None) remove keys."""
    head = dict(scene="top", method="rk4", dt=1e-3, t_end=0.5, save_dt=0.1, members=4, seed=7)
    head.update(top_level)
    params = dict(lambda1=1.0e-3, lambda3=2.0e-3, c=1e-4, spin0=60.0,
                  tilt0={"uniform": [0.02, 0.2]}, azimuth0={"uniform": [0.0, 6.283185307179586]})
    params.update(parameters or {})
    lines = [f"{k} = {_toml_value(v)}" for k, v in head.items() if v is not None]
    lines.append("[parameters]")
    lines += [f"{k} = {_toml_value(v)}" for k, v in params.items() if v is not None]
    if sweep:
        lines.append("[sweep]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in sweep.items()]
    return "\n".join(lines) + "\n"


@pytest.fixture
def write_runfile(tmp_path):
    """Write run-file text into the test's folder and return its path."""
    def write(text: str, name: str = "run.toml"):
        path = tmp_path / name
        path.write_text(text)
        return path
    return write


def refused(text: str, folder, capsys, expected: str) -> str:
    """Run `ensemble run` on run-file text in `folder` and check the promise to users for bad input: exit
    status 2, one line on stderr containing `expected`, and no output file (no parts, no .tmp). Returns the line."""
    from ensemble import cli

    path = folder / "bad.toml"
    path.write_text(text)
    assert cli.main(["run", str(path), "-o", str(folder / "bad.nc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert not list(folder.glob("bad.nc*"))
    return err[0]


@pytest.fixture(scope="module")
def client():
    """A dask.distributed Client of a LocalCluster of two single-threaded worker processes (one per module), whose
    scheduler gives a task up after its second worker died."""
    import dask
    import distributed

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                      env={"NUMBA_NUM_THREADS": "1"}) as local, distributed.Client(local) as c:
            yield c


def run_without(module: str, argv: list[str]):
    """`ensemble` (cli.main(argv)) in a new process where `module` cannot be imported, as on a machine without
    it; the CompletedProcess, its output as text."""
    import subprocess
    import sys

    hide = f"import sys; sys.modules[{module!r}] = None; from ensemble.cli import main; sys.exit(main({argv!r}))"
    return subprocess.run([sys.executable, "-c", hide], capture_output=True, text=True)

"""The CUDA kernels (ensemble.engine.gpu) against the CPU kernels, under numba-cuda's simulator (conftest sets
NUMBA_ENABLE_CUDASIM=1 unless ENSEMBLE_TEST_GPU=1 asks for the real GPU): every method family on every scene,
failing members, segments, chunks and resume, and the errors of --device cuda.

Arithmetic differs between the two (the CPU kernels are compiled with fast-math and fused multiply-adds where LLVM
chooses; the simulator runs Python floats; a GPU fuses where NVVM chooses), so results agree to rounding rather than
bitwise; a GPU run agrees with itself bitwise however it is cut into segments and chunks.
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ensemble import cli, fitting, runner
from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.results import Status
from ensemble.scenes import resolve
from ensemble.spec import SpecError, load

from .conftest import top_runfile
from .test_resume import _interrupted, chunked_and_resumed_match_one_run

pytest.importorskip("numba.cuda")
EXAMPLE = Path(__file__).parents[1] / "examples" / "driven_oscillator.py"

TOP = dict(scene="top", dt=0.01, t_end=0.2, save_dt=0.05, members=3, seed=3,
           parameters="lambda1 = 1.0e-3\nlambda3 = 2.0e-3\nc = 1e-4\nspin0 = 60.0\n"
                      "tilt0 = { uniform = [0.02, 0.2] }\nazimuth0 = 0.3")
BODY = dict(scene="body", dt=0.01, t_end=0.2, save_dt=0.05, members=3, seed=3,
            parameters="lambda1 = 1.0\nlambda2 = 2.0\nlambda3 = 3.0\nc = 0.05\nspin0 = 2.0\nspin_axis = 2\n"
                       "tilt0 = { uniform = [0.01, 0.1] }\nazimuth0 = 0.5")
CHAIN = dict(scene="chain", dt=0.02, t_end=0.2, save_dt=0.1, members=3, seed=3,
             parameters="n = 4\nboundary = \"fixed\"\nm = 1.0\nk = { uniform = [0.5, 1.5] }\n"
                        "x0 = { normal = [0.0, 0.1] }")  # test_chain's length: its CPU kernels
RING = {**CHAIN, "parameters": CHAIN["parameters"].replace('"fixed"', '"periodic"')}
FPUT = {**CHAIN, "scene": str(Path(__file__).parents[1] / "examples" / "fput.py"),  # a user's field of sites, of
        "parameters": CHAIN["parameters"].replace("n = 4", "n = 8")}  # test_user_sites's length: its kernels
USER = dict(scene=str(EXAMPLE), dt=0.02, t_end=0.4, save_dt=0.1, members=3, seed=3,
            parameters="omega0 = 1.0\ngamma = 0.1\nF = 0.5\nOmega = { uniform = [0.5, 1.5] }\nx0 = 0.2")

def loads(text: str):
    """The Spec of a run file's text."""
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "run.toml"
        path.write_text(text)
        return load(path)


CASES = [(TOP, ("rk4", "split4", "dopri5")), (BODY, ("rk4", "rotations4", "dopri5")),
         (CHAIN, ("verlet", "yoshida4", "rk4", "dopri5")), (RING, ("verlet", "dopri5")), (USER, ("rk4", "dopri5")),
         (FPUT, ("rk4",))]  # the sites kernels are the chain's: FPUT checks that a user's acceleration reaches them


def spec_text(case: dict, method: str, **extra) -> str:
    """A case's run file text with `method` (and `extra` keys)."""
    case = {**case, **extra}
    head = "\n".join(f"{k} = {v!r}" if not isinstance(v, str) else f'{k} = "{v}"'
                     for k, v in case.items() if k != "parameters")
    tolerances = "rtol = 1e-7\natol = 1e-9\n" if METHODS[method].adaptive else ""
    return f'{head}\nmethod = "{method}"\n{tolerances}[parameters]\n{case["parameters"]}\n'


def spec_of(case: dict, method: str, **extra):
    return loads(spec_text(case, method, **extra))


def both(spec, **settings):
    """(CPU outcome, GPU outcome) of a spec's members."""
    values = runner.members_table(spec, 0, spec.n_members)
    method = METHODS[spec.method]
    base = {**runner._settings(spec, method, values), **settings, "device": "cpu"}
    return (launch.integrate(spec.model, method, values, spec.constants, **base),
            launch.integrate(spec.model, method, values, spec.constants, **{**base, "device": "cuda"}))


@pytest.mark.parametrize("case, method", [(case, m) for case, methods in CASES for m in methods],
                         ids=[f"{c['scene'].split('/')[-1]}-{m}" for c, ms in CASES for m in ms])
def test_every_family_on_every_scene_gives_the_cpus_results(case, method):
    """Within 1e-12 of the CPU's samples (relative to each member's largest state component); dopri5 within
    1e-10: the CPU's step control computes its step factors with vectorized log2 and exp2 (1e-13 relative), so
    the step sizes differ in their last bits. Status, failure times and step counts are the CPU's."""
    cpu, gpu = both(spec_of(case, method))
    scale = np.abs(cpu.samples).max(axis=(0, 1))
    error = np.abs(gpu.samples - cpu.samples).max(axis=(0, 1)) / scale
    assert error.max() < (1e-10 if METHODS[method].adaptive else 1e-12), error
    assert np.array_equal(cpu.status, gpu.status) and np.array_equal(cpu.counts, gpu.counts)
    assert np.isfinite(cpu.samples).all() and np.all(cpu.samples[-1] != cpu.samples[0])  # they moved, none failed


def test_failing_members_are_flagged_as_on_the_cpu():
    """A chain whose stiff members are beyond verlet's stability limit (h omega > 2) blows up on both, at the same
    saved time; the stable members run on. An adaptive member whose tolerance cannot be met underflows on both."""
    spec = spec_of({**CHAIN, "dt": 1.0, "t_end": 40.0, "save_dt": 1.0,
                    "parameters": CHAIN["parameters"].replace("[0.5, 1.5]", "[0.1, 3.0]")}, "verlet",
                   members=6)
    cpu, gpu = both(spec)
    assert set(cpu.status) == {Status.OK, Status.BLEW_UP}
    assert np.array_equal(cpu.status, gpu.status)
    assert np.array_equal(cpu.failure_time, gpu.failure_time, equal_nan=True)
    assert np.array_equal(np.isnan(cpu.samples), np.isnan(gpu.samples))
    cpu, gpu = both(spec_of(TOP, "dopri5"), rtol=np.full(3, 1e-30), atol=np.full(3, 1e-300))
    assert set(cpu.status) == {Status.STEP_SIZE_UNDERFLOW} and np.array_equal(cpu.status, gpu.status)
    # where each gives up depends on the last bits of its step factors (see above): before the first saved time
    assert np.all(cpu.failure_time < 0.05) and np.all(gpu.failure_time < 0.05)
    assert np.isnan(gpu.samples[1:]).all() and np.isnan(cpu.samples[1:]).all()


@pytest.mark.parametrize("method", ["rk4", "dopri5", "verlet", "chain dopri5"])
def test_a_run_in_segments_gives_the_bits_of_one_call(method):
    case = CHAIN if method.startswith("chain") or method == "verlet" else TOP
    method = method.split()[-1]
    spec = spec_of(case, method)
    values = runner.members_table(spec, 0, spec.n_members)
    settings = {**runner._settings(spec, METHODS[method], values), "device": "cuda"}
    whole = launch.new_launch(spec.model, METHODS[method], values, spec.constants, **settings)
    whole.run()
    parts = launch.new_launch(spec.model, METHODS[method], values, spec.constants, **settings, segment=1)
    parts.run()
    assert whole.samples.tobytes() == parts.samples.tobytes()
    assert whole.outcome().counts.tobytes() == parts.outcome().counts.tobytes()


PENDULUM = Path(__file__).parents[1] / "examples" / "pendulum.py"


@pytest.mark.parametrize("method, dt, stop", [("rk4", 0.05, False), ("yoshida4", 0.05, False),
                                              ("dopri5", None, False), ("dopri5", None, True)])
def test_events_on_the_gpu_are_the_cpus(method, dt, stop):
    """ensemble.engine.events on the GPU (gpu_kernels.event_watch): pendulums' zero crossings with their state
    kept, and the bob falling through the axle's height (the scene's event function), as the CPU's to 1e-12; a
    run in segments gives the bits of one call. With `stop` the bob's fall stops the two pendulums that swing
    above the axle (the same kernel: a run's stops are its arrays): status, steps and the state kept at the stop
    as on the CPU, the others run to the end."""
    from .test_events import EVENTS, OMEGA0, THETA0

    values = {"omega0": np.full(4, OMEGA0), "theta0": THETA0, "theta_dot0": np.zeros(4)}
    events = (EVENTS[0], EVENTS[1]._replace(stop=stop))
    settings = dict(n_save=31, save_dt=0.1, dt=dt, rtol=1e-7, atol=1e-9, events=events)
    scene = resolve(str(PENDULUM))
    cpu = launch.integrate(scene, METHODS[method], values, {}, **settings)
    gpu = launch.integrate(scene, METHODS[method], values, {}, **settings, device="cuda")
    assert list(cpu.status) == [Status.OK] * 2 + [Status.STOPPED_BY_EVENT if stop else Status.OK] * 2
    assert np.array_equal(cpu.status, gpu.status) and np.array_equal(cpu.counts, gpu.counts)
    assert np.array_equal(cpu.event_counts, gpu.event_counts) and cpu.event_counts[1, 2] > 0
    for name in ("event_times", "event_states", "samples"):
        mine, theirs = getattr(gpu, name), getattr(cpu, name)
        assert np.array_equal(np.isnan(mine), np.isnan(theirs)) and np.nanmax(np.abs(mine - theirs)) < 1e-12, name
    if stop:  # the stopped states' rates change by at most omega0^2 rad/s^2 times the stop times' rounding
        moved = OMEGA0**2 * np.nanmax(np.abs(gpu.event_times - cpu.event_times)) + 1e-12
        assert np.nanmax(np.abs(gpu.stopped - cpu.stopped)) <= moved
    parts = launch.new_launch(scene, METHODS[method], values, {}, **settings, device="cuda", segment=7)
    parts.run()
    assert parts.outcome().event_times.tobytes() == gpu.event_times.tobytes()


@pytest.mark.parametrize("method", ["rk4", "split4"])
def test_a_tops_stopping_event_on_the_gpu_is_the_cpus(method):
    """A prolate top's tilt rising through 0.6 rad (the top's compiled observable, watched through watch_tilt) stops
    each member there: status, steps, the state kept at the stop and the NaN samples after it as on the CPU (the
    kernels of test_events' stopping tops; dopri5's stops are tested on the pendulum above)."""
    from ensemble.results import Event

    values = {"lambda1": np.full(3, 1e-3), "lambda3": np.full(3, 0.5e-3), "c": np.full(3, 2e-4),
              "spin0": np.full(3, 60.0), "tilt0": np.array([0.4, 0.5, 0.55]), "azimuth0": np.zeros(3)}
    tip = Event("tip", "tilt", -1, ("function", "value_tilt", -1, "watch_tilt"), 0.6, "up", 1, True)  # 2.4, 1.1, .55 s
    settings = dict(n_save=11, save_dt=0.5, dt=2e-2, rtol=1e-8, atol=1e-10, events=(tip,))
    top = resolve("top")
    cpu = launch.integrate(top, METHODS[method], values, {}, **settings)
    gpu = launch.integrate(top, METHODS[method], values, {}, **settings, device="cuda")
    assert np.all(cpu.status == Status.STOPPED_BY_EVENT) and np.array_equal(cpu.status, gpu.status)
    assert np.array_equal(cpu.counts, gpu.counts) and np.all(np.isnan(gpu.failure_time))
    for name in ("event_times", "samples"):  # the rates reach 40 rad/s
        mine, theirs = getattr(gpu, name), getattr(cpu, name)
        assert np.allclose(mine, theirs, rtol=1e-12, atol=1e-12, equal_nan=True), name
        assert np.array_equal(np.isnan(mine), np.isnan(theirs)), name
    # the state at the stop turns at 60 rad/s: its rates move by 2400 rad/s^2 times the stop times' rounding
    moved = 2400.0 * np.max(np.abs(gpu.event_times - cpu.event_times)) + 1e-12
    assert np.max(np.abs(gpu.stopped - cpu.stopped)) <= moved and moved < 1e-9


@pytest.mark.parametrize("method, stop", [("verlet", False), ("rk4", True), ("dopri5", False), ("dopri5", True)])
def test_a_chains_events_on_the_gpu_are_the_cpus(method, stop):
    """A chain's events on the GPU (one thread to a member, however long the chain; a splitting's steps whole, not
    merged): mass 1's crossings with the states kept there, mass 2's velocity turning (stopping its member where
    `stop`), the samples, counts and statuses as on the CPU (test_chain_events' kernels), to rounding; a run in
    segments, the bits of one call."""
    from ensemble.engine import gpu_launch

    from .test_chain_events import CHAIN, CROSS, TURN, pluck

    events = (CROSS, TURN._replace(stop=stop))
    cpu, gpu = pluck(method, events, slice(0, 2)), pluck(method, events, slice(0, 2), device="cuda")
    assert np.array_equal(gpu.status, cpu.status) and np.array_equal(gpu.event_counts, cpu.event_counts)
    assert np.all(cpu.status == (Status.STOPPED_BY_EVENT if stop else Status.OK)) and cpu.event_counts.min() > 0
    assert np.array_equal(gpu.counts, cpu.counts) and np.all(np.isnan(gpu.failure_time))
    for name in ("event_times", "event_states", "stopped", "samples"):
        mine, theirs = getattr(gpu, name), getattr(cpu, name)
        assert np.array_equal(np.isnan(mine), np.isnan(theirs)), name
        assert np.allclose(mine, theirs, rtol=1e-11, atol=1e-12, equal_nan=True), name
    if stop:  # in segments of 7 samples: each call goes on with the events where the last left them
        original = gpu_launch.GpuLaunch.__init__
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(gpu_launch.GpuLaunch, "__init__", lambda self, *a, **k: original(self, *a, **k, segment=7))
            parts = pluck(method, events, slice(0, 2), device="cuda")
        for name in ("event_times", "event_counts", "event_states", "stopped", "samples", "counts", "status"):
            assert np.array_equal(getattr(parts, name), getattr(gpu, name), equal_nan=True), name
    long = {"n": 200, "boundary": "fixed"}
    assert gpu_launch.layout(CHAIN, METHODS[method], long, ()).threads > 1
    assert gpu_launch.layout(CHAIN, METHODS[method], long, (CROSS.source,)).threads == 1


def test_chunks_and_resume_on_the_gpu_give_the_bits_of_one_run(tmp_path, monkeypatch):
    """device = "cuda" in the run file: a run in chunks of 1, and one interrupted after two chunks of 7 and
    resumed, give the bits of one run; the result names its device."""
    text = top_runfile(members=16, device="cuda", t_end=0.2, dt=0.01, save_dt=0.05)
    path = tmp_path / "run.toml"
    path.write_text(text)
    whole = chunked_and_resumed_match_one_run(path, tmp_path, monkeypatch)
    import xarray as xr

    with xr.open_dataset(whole) as ds:
        assert ds.attrs["device"].startswith("cuda: ") and ds.attrs["precision"] == "float64"
        cpu = runner.simulate(loads(text.replace('device = "cuda"', 'device = "cpu"')))
        assert cpu.attrs["device"] == "cpu"
        assert np.allclose(ds.omega, cpu.omega, rtol=1e-12, atol=0)


def test_float32_on_the_gpu_agrees_with_float64_to_single_precision():
    spec = spec_of(TOP, "rk4")
    values = runner.members_table(spec, 0, spec.n_members)
    settings = {**runner._settings(spec, METHODS["rk4"], values), "device": "cuda"}
    double = launch.integrate(spec.model, METHODS["rk4"], values, spec.constants, **settings)
    single = launch.integrate(spec.model, METHODS["rk4"], values, spec.constants,
                              **{**settings, "precision": "float32"})
    error = np.abs(single.samples - double.samples).max() / np.abs(double.samples).max()
    assert 1e-12 < error < 1e-5  # single precision: not float64's result, but within float32's rounding


@pytest.mark.parametrize("precision, kept", [("float64", 1e-40), ("float32", 0.0)])
def test_a_subnormal_of_the_runs_precision_is_flushed_to_zero(precision, kept):
    """As the CPU flushes float64's subnormals (below 2.2e-308) at the start and at each save, a float32 run flushes
    float32's (below 1.2e-38): 1e-40 is a normal float64 and a subnormal float32."""
    spec = spec_of({**USER, "parameters": USER["parameters"].replace("x0 = 0.2", "x0 = 1e-40")
                    .replace("F = 0.5", "F = 0.0")}, "rk4")
    values = runner.members_table(spec, 0, spec.n_members)
    settings = {**runner._settings(spec, METHODS["rk4"], values), "device": "cuda", "precision": precision}
    outcome = launch.integrate(spec.model, METHODS["rk4"], values, spec.constants, **settings)
    assert np.all(outcome.samples[0, 0] == kept)  # x at the start
    assert np.all(outcome.status == 0)


@pytest.mark.parametrize("key, value, problem", [
    ("device", '"tpu"', "device: must be one of 'cpu', 'cuda', got 'tpu'"),
    ("precision", '"float16"', "precision: must be one of 'float64', 'float32', got 'float16'"),
    ("precision", '"float32"', 'precision: float32 runs on a GPU only (device = "cuda"); the CPU kernels are '
                               'float64')])
def test_a_bad_device_or_precision_is_refused(key, value, problem):
    with pytest.raises(SpecError) as error:
        loads(top_runfile().replace("[parameters]", f"{key} = {value}\n[parameters]"))
    assert str(error.value) == problem


@pytest.mark.skipif(os.environ.get("ENSEMBLE_TEST_GPU") == "1", reason="this machine has a GPU")
def test_device_cuda_without_a_gpu_is_one_line_and_exit_2_with_nothing_written(tmp_path):
    """With the simulator off and no GPU (as on the test machines) --device cuda names what is missing."""
    path = tmp_path / "run.toml"
    path.write_text(top_runfile())
    out = tmp_path / "out.nc"
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "-o", str(out), "--device", "cuda"],
                          capture_output=True, text=True, env={**os.environ, "NUMBA_ENABLE_CUDASIM": "0"})
    assert done.returncode == 2, done.stderr
    assert done.stderr.startswith(f"ensemble: error: {path}: device cuda: ") and done.stderr.count("\n") == 1
    assert not list(tmp_path.glob("out.nc*"))


def test_a_run_is_resumed_only_on_the_device_it_started_on(tmp_path, monkeypatch, capsys):
    """A CPU run interrupted after two chunks is not finished on the GPU, which rounds differently: one line,
    exit 2, before any member runs, the parts kept; on the CPU it finishes."""
    path = tmp_path / "run.toml"
    path.write_text(top_runfile(members=16))
    out = tmp_path / "out.nc"
    _interrupted(load(path), out, after=2, monkeypatch=monkeypatch)
    capsys.readouterr()
    assert cli.main(["run", str(path), "-o", str(out), "--quiet", "--resume", "--device", "cuda"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "was made by another run (device differs)" in err
    assert not out.exists() and list(tmp_path.glob("out.nc.parts/members-*"))
    assert cli.main(["run", str(path), "-o", str(out), "--quiet", "--resume"]) == 0


@pytest.mark.parametrize("method", ["rk4", "dopri5"])
def test_a_long_record_on_the_gpu_continues_from_its_last_segment(tmp_path, monkeypatch, method):
    """Issue 40, item 8 on the GPU: a record in segments of one sample, interrupted after its second segment,
    resumes from the kernel state the GPU left there (copied out after each segment) to the bits of one run."""
    from ensemble import parts

    from .test_resume import same_bits

    monkeypatch.setattr(runner, "GPU_CHUNK_BYTES", 64)
    spec = spec_of(TOP, method, device="cuda")
    assert runner.segment_samples(spec) == 1 and spec.n_save == 5
    whole, out = tmp_path / "whole.nc", tmp_path / "out.nc"
    runner.run(spec, whole, progress=False)
    real, saved = parts.SegmentLog.save, []

    def save(self, *args):
        real(self, *args)
        saved.append(1)
        if len(saved) == 2:
            raise KeyboardInterrupt

    monkeypatch.setattr(parts.SegmentLog, "save", save)
    with pytest.raises(KeyboardInterrupt):
        runner.run(spec, out, progress=False)
    monkeypatch.setattr(parts.SegmentLog, "save", real)
    assert len(list(tmp_path.glob("out.nc.parts/segment-*.npz"))) == 2
    runner.run(spec, out, progress=False, resume=True)
    same_bits(out, whole)


def test_a_gpu_run_writes_a_zarr_store_as_its_netcdf_file(tmp_path):
    """Issue 54, item 7: the GPU's chunks reach a store through the same writer thread as a file: the same bits."""
    pytest.importorskip("zarr")
    from .test_resume import same_bits

    spec = spec_of(TOP, "rk4", device="cuda")
    runner.run(spec, tmp_path / "gpu.nc", progress=False, chunk=2)
    runner.run(spec, tmp_path / "gpu.zarr", progress=False, chunk=2)
    same_bits(tmp_path / "gpu.zarr", tmp_path / "gpu.nc")


@pytest.mark.parametrize("boundary", ["fixed", "periodic"])
def test_a_long_chain_as_a_block_of_threads_gives_the_results_of_one_thread_per_chain(monkeypatch, boundary):
    """Chains of gpu_sites.SHARED_SITES masses or more run as a block of threads each, a thread owning a few sites and
    the positions in shared memory. Here 5 masses on 2 threads (the second owning one site fewer) give the bits
    of one thread per chain for splittings and Runge-Kutta, unstable members failing at the same saved time, also
    in segments. dopri5 adds its error norm over the threads in another order: the same steps, to rounding. (The
    simulator's barriers are slow: a ring only with verlet and rk4, dopri5 on the heavy chains, which take few
    steps.)"""
    from ensemble.engine import gpu_launch, gpu_sites
    from ensemble.scenes import resolve

    chain, n = resolve("chain"), 5
    rng = np.random.default_rng(5)
    values = {"m": np.repeat([[0.05], [0.1], [10.0], [20.0]], n, axis=1), "k": rng.uniform(0.5, 2.0, (4, n + 1)),
              "x0": rng.normal(0.0, 0.3, (4, n)), "v0": rng.normal(0.0, 0.1, (4, n))}
    constants = {"n": n, "boundary": boundary}
    for method in ("verlet", "rk4") + (("yoshida4", "dopri5") if boundary == "fixed" else ()):
        settings = dict(device="cuda", **(dict(n_save=3, save_dt=0.5, rtol=1e-6, atol=1e-8)
                                          if METHODS[method].adaptive else dict(n_save=7, save_dt=1.0, dt=0.5)))
        if METHODS[method].adaptive:
            values = {name: value[2:] for name, value in values.items()}
        one = launch.integrate(chain, METHODS[method], values, constants, **settings)
        with monkeypatch.context() as patch:
            patch.setattr(gpu_sites, "SHARED_SITES", 2)
            patch.setattr(gpu_sites, "MOST_SITE_THREADS", 2)
            patch.setattr(gpu_sites, "WARP", 1)
            assert gpu_launch.kernel(chain, METHODS[method], constants).threads == 2
            block = launch.integrate(chain, METHODS[method], values, constants, **settings)
            segments = launch.new_launch(chain, METHODS[method], values, constants, **settings, segment=2)
            segments.run()  # each call continues from where the block's threads left their sites in works
        assert segments.samples.tobytes() == block.samples.tobytes()
        assert np.array_equal(one.counts, block.counts) and np.array_equal(one.status, block.status), method
        if METHODS[method].adaptive:
            assert np.abs(block.samples - one.samples).max() <= 1e-12 * np.abs(one.samples).max()
            continue
        assert list(one.status) == [Status.BLEW_UP] * 2 + [Status.OK] * 2, method  # dt 0.5: the light fail
        for name in ("samples", "failure_time"):
            assert np.array_equal(getattr(one, name), getattr(block, name), equal_nan=True), (method, name)


def test_work_precision_charts_float32_beside_float64(tmp_path, capsys):
    """Issue 42: one run file run on the GPU in float64 and (--precision) in float32, charted together: a line
    each; where rk4's own error is large both agree, where it is small float32's round-off is far above it."""
    path = tmp_path / "wp.toml"
    path.write_text(top_runfile(members=1, t_end=1.0, save_dt=0.5, dt=None, method="rk4", device="cuda",
                                parameters={"tilt0": 0.3, "azimuth0": 1.0, "spin0": 20.0, "c": 2e-3},
                                sweep={"dt": [0.05, 0.025, 0.0125, 0.005, 0.0025, 0.001]})
                    + "[measure]\nerror = true\n")
    double, single = tmp_path / "double.nc", tmp_path / "single.nc"
    assert cli.main(["run", str(path), "-o", str(double), "--quiet"]) == 0
    assert cli.main(["run", str(path), "-o", str(single), "--quiet", "--precision", "float32"]) == 0
    capsys.readouterr()
    assert cli.main(["work-precision", str(double), str(single), "--charts", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "rk4 float64: nominal order 4" in out and "rk4 float32: nominal order 4" in out
    import xarray as xr

    table = xr.load_dataset(tmp_path / "double_work_precision.nc")
    error = {line: table["error"].values[table["line"].values == line] for line in ("rk4 float64", "rk4 float32")}
    assert error["rk4 float32"][0] == pytest.approx(error["rk4 float64"][0], rel=1e-3)  # dt 0.05: truncation
    assert error["rk4 float32"][-1] > 30 * error["rk4 float64"][-1]  # dt 1e-3: float32's round-off
    assert fitting.convergence_order(table, "rk4 float64")[0] == pytest.approx(4, abs=0.2)
    assert (tmp_path / "double_work_precision.png").stat().st_size > 20_000


def test_work_precision_refuses_results_of_two_scenes_and_float32_on_the_cpu(tmp_path, capsys):
    top_path, chain_path = tmp_path / "top.toml", tmp_path / "chain.toml"
    top_path.write_text(top_runfile(members=1, t_end=0.2) + "[measure]\nerror = true\n")
    chain_path.write_text(spec_text(CHAIN, "verlet") + "[measure]\nerror = true\n")
    for path in (top_path, chain_path):
        assert cli.main(["run", str(path), "-o", str(path.with_suffix(".nc")), "--quiet"]) == 0
    capsys.readouterr()
    assert cli.main(["work-precision", str(tmp_path / "top.nc"), str(tmp_path / "chain.nc")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "chain.nc: a chain result, charted with" in err
    assert not list(tmp_path.glob("*_work_precision.nc"))
    assert cli.main(["work-precision", str(tmp_path / "x.nc"), str(tmp_path / "y.nc")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "x.nc" in err  # the first that cannot be read, in one line
    assert cli.main(["run", str(top_path), "-o", str(tmp_path / "f32.nc"), "--quiet", "--precision", "float32"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "precision: float32 runs on a GPU only" in err
    assert not list(tmp_path.glob("f32.nc*"))


def _example_error(module: str, family: str, step: float | None) -> float:
    """A GPU kernels module (ensemble.engine.gpu_kernels or .gpu_sites_kernels) called directly, as its example
    binds it, through 1 s from sample 0 in one call and the save interval in a second (a resume): its largest error
    against the exact flow (a harmonic oscillator's cos and sin; a chain's matrix exponential)."""
    import importlib

    from scipy.linalg import expm

    example = importlib.import_module(f"ensemble.engine.{module}")
    members, t_end = 2, 1.0
    if module == "gpu_kernels":
        state0, rate = np.array([[1.0, 0.5], [0.0, -0.3]]), np.array([[1.0, 2.0]])  # x, v rows; omega
        w, x0, v0 = rate[0], state0[0], state0[1]
        exact = np.stack([x0 * np.cos(w * t_end) + v0 / w * np.sin(w * t_end),
                          -x0 * w * np.sin(w * t_end) + v0 * np.cos(w * t_end)])
        rows = 2 * example.D + 7
    else:
        n = example.N
        state0, rate = np.random.default_rng(3).normal(size=(2 * n, members)), np.ones((2 * n, members))
        K = 2 * np.eye(n) - np.eye(n, k=1) - np.eye(n, k=-1)
        exact = expm(t_end * np.block([[np.zeros((n, n)), np.eye(n)], [-K, np.zeros((n, n))]])) @ state0
        rows = 4 * n + 7
    status, failure_time, limit = np.zeros(members, np.int8), np.zeros(members), np.full(members, 1e6)
    works = np.zeros((rows, members))
    no_events = (np.zeros((0, 5)), np.zeros((0, 1, 1)), np.zeros((0, 1)), np.zeros((len(state0), 1)),
                 np.zeros((0, 1, len(state0), 1)))  # its example has none
    for start in (0, 1):
        samples = np.full((1, len(state0), members), np.nan)
        if family == "adaptive":
            control = np.array([[0.0] * members, [1e-8] * members, [1e-10] * members])
            example.adaptive_kernel[1, members](state0, rate, control, t_end, limit, samples, np.zeros((3, members)),
                                               status, failure_time, works, start, members, *no_events)
        else:
            getattr(example, f"{family}_kernel")[1, members](state0, rate, step, round(t_end / step), limit, samples,
                                                            status, failure_time, works, start, members, *no_events)
    assert np.all(status == 0)
    return np.max(np.abs(samples[0] - exact))


@pytest.mark.parametrize("module", ["gpu_kernels", "gpu_sites_kernels"])
@pytest.mark.parametrize("family, order, bound", [("runge_kutta", 3, 2e-5), ("splitting", 2, 2e-3)])
def test_the_gpu_kernels_modules_run_their_examples_at_their_order(module, family, order, bound):
    coarse, fine = _example_error(module, family, 0.05), _example_error(module, family, 0.025)
    assert fine < bound
    assert order - 0.15 < np.log2(coarse / fine) < order + 0.15


@pytest.mark.parametrize("module", ["gpu_kernels", "gpu_sites_kernels"])
def test_the_gpu_kernels_modules_run_their_examples_to_tolerance(module):
    assert _example_error(module, "adaptive", None) < 1e-6

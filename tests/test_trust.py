"""Nothing stale, nothing forged (issue 50): what a kernel computes is what the user wrote.

An edited scene runs its new physics, in the same process and in later ones (never an old right-hand side from
a cache); an edited module of the user's that the scene imports counts as an edit of the scene; a generated
kernel file whose text is not its name's is written again, never imported; the kernel folder is the user's
alone; a NaN or inf that the right-hand side returns fails its member; a resume never mixes two physics, nor
keeps an edit of the unfinished result's parameters or attributes."""
from __future__ import annotations

import math
import os
import re
import subprocess
import sys
from pathlib import Path

import netCDF4
import numpy as np
import pytest
import xarray as xr

import ensemble
from ensemble import cli, runner
from ensemble.engine import kernels
from ensemble.parts import folder_of
from ensemble.results import Status
from ensemble.spec import load

from .conftest import top_runfile
from .test_resume import _interrupted

# x' = -a x: x(t) = x0 exp(-a t); euler's x_n = x0 (1 - a dt)^n. EDIT replaces the rate.
DECAY = '''
import math

from ensemble import Parameter

STATE = {"x": ("m", "position")}
PARAMETERS = {"a": Parameter("s-1", "rate"), "x0": Parameter("m", "start")}

def rhs(t, x, a):
    return (-RATE * a * x,)
'''
FIT_BY_ENVIRONMENT = '''
def fit(ds):
    import os
    if os.environ["DECAY_FIT"] == "raise":
        raise ValueError("my fit broke")
    return {"rate": 1.0}
'''
RUN = '''scene = "{scene}"
method = "{method}"
dt = 0.01
t_end = 1.0
save_dt = 0.5
members = {members}
seed = 1
[parameters]
a = {{ uniform = [0.5, 1.5] }}
x0 = 1.0
'''


def _scene(folder: Path, rate: float, helper: bool = False) -> Path:
    """decay.py with x' = -rate a x (its rate read from helper.py if `helper`)."""
    path = folder / "decay.py"
    if helper:
        (folder / "helper.py").write_text(f"RATE = {rate!r}\n")
        path.write_text("from helper import RATE\n" + DECAY)
    else:
        path.write_text(f"RATE = {rate!r}\n" + DECAY)
    return path


def _runfile(folder: Path, method: str, members: int = 5, scene: str = "decay.py") -> Path:
    path = folder / f"{method}.toml"
    path.write_text(RUN.format(method=method, members=members, scene=scene))
    return path


@pytest.fixture(scope="module")
def decay(tmp_path_factory) -> str:
    """decay.py at rate 1, with a fit(ds) that does what the environment's DECAY_FIT says: for the tests that do not
    edit it, which then share its kernels."""
    path = tmp_path_factory.mktemp("decay") / "decay.py"
    path.write_text("RATE = 1.0\nNAME = 'decay'\n" + DECAY + FIT_BY_ENVIRONMENT)
    return str(path)


def _x_end(ds: xr.Dataset) -> np.ndarray:
    return ds.x.isel(t=-1).values


def _expected(ds: xr.Dataset, rate: float, method: str) -> np.ndarray:
    a = ds.a.values
    return (1.0 - rate * a * 0.01) ** 100 if method == "euler" else np.exp(-rate * a)


def test_a_scene_edited_between_two_runs_of_one_process_runs_its_new_physics(tmp_path):
    """The issue's case: rk4 before the edit, then euler (compiled only after it) and rk4 again: both with the
    new rate; then a fresh process loads euler from the disk cache: the new rate too (the old code cached an euler
    kernel holding the old right-hand side under the new file's name)."""
    _scene(tmp_path, 1.0)
    before = ensemble.run(str(_runfile(tmp_path, "rk4")), progress=False)
    assert np.allclose(_x_end(before), _expected(before, 1.0, "rk4"), rtol=1e-8)
    _scene(tmp_path, 2.0)
    for method in ("euler", "rk4"):
        after = ensemble.run(str(_runfile(tmp_path, method)), progress=False)
        assert np.allclose(_x_end(after), _expected(after, 2.0, method), rtol=1e-8), method
    out = tmp_path / "euler.nc"
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(_runfile(tmp_path, "euler")), "-o", str(out),
                           "--quiet"], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    with xr.open_dataset(out) as ds:
        assert np.allclose(_x_end(ds), _expected(ds, 2.0, "euler"), rtol=1e-8)


def test_an_edited_module_the_scene_imports_is_an_edited_scene(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(tmp_path))
    _scene(tmp_path, 1.0, helper=True)
    before = ensemble.run(str(_runfile(tmp_path, "rk4")), progress=False)
    assert np.allclose(_x_end(before), _expected(before, 1.0, "rk4"), rtol=1e-8)
    _scene(tmp_path, 3.0, helper=True)
    after = ensemble.run(str(_runfile(tmp_path, "rk4")), progress=False)
    assert np.allclose(_x_end(after), _expected(after, 3.0, "rk4"), rtol=1e-8)
    sys.modules.pop("helper", None)


def test_an_edited_event_function_and_its_helper_run_their_new_code(tmp_path, monkeypatch):
    """A kernel's watch inlines the scene's event function (events.written_out): edited, or its helper module
    edited, the event is the new one's, in the same process and in a new one loading kernels from the disk cache."""
    monkeypatch.syspath_prepend(str(tmp_path))
    runfile = tmp_path / "low.toml"
    runfile.write_text('scene = "decay.py"\nmethod = "rk4"\ndt = 0.01\nt_end = 2.0\nsave_dt = 2.0\nsave = []\n'
                       'members = 2\nseed = 1\n[parameters]\na = 2.0\nx0 = 1.0\n[events.low]\nof = "low"\n'
                       'direction = "down"\n')

    def edit(level: str, scale: float):
        (tmp_path / "levels.py").write_text(f"LEVEL = {level}\n")
        (tmp_path / "decay.py").write_text("from levels import LEVEL\nRATE = 1.0\nEVENTS = ('low',)\n" + DECAY
                                           + f"\ndef event_low(t, x, a):\n    return {scale!r} * x - LEVEL\n")

    for level, scale in (("0.5", 1.0), ("0.25", 1.0), ("0.25", 0.5)):  # x crosses LEVEL / scale at ln(.) / 2 s
        edit(level, scale)
        expected = math.log(scale / float(level)) / 2.0
        ds = ensemble.run(str(runfile), progress=False)
        assert np.allclose(ds.low_time.values, expected, rtol=0, atol=1e-9), (level, scale)
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(tmp_path / "low.nc"),
                           "--quiet"], capture_output=True, text=True, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(tmp_path)})
    assert done.returncode == 0, done.stderr
    with xr.open_dataset(tmp_path / "low.nc") as ds:
        assert np.allclose(ds.low_time.values, math.log(2.0) / 2.0, rtol=0, atol=1e-9)
    sys.modules.pop("levels", None)


def test_a_kernel_file_that_is_not_its_name_is_written_again_not_imported(tmp_path, capfd):
    _scene(tmp_path, 1.0)
    runfile = _runfile(tmp_path, "rk4")
    expected = ensemble.run(str(runfile), progress=False)
    scene = ensemble.scenes.resolve(str(tmp_path / "decay.py"))
    path = Path(kernels.kernel(scene, ensemble.methods.METHODS["rk4"], {}).function.py_func.__code__.co_filename)
    genuine = path.read_text()
    assert "(0.16666666666666666, 0.3333333333333333, 0.3333333333333333, 0.16666666666666666)" in genuine  # b
    path.write_text(genuine.replace("(0.16666666666666666, 0.3333", "(0.16666666666666667, 0.3333"))
    out = tmp_path / "out.nc"
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--quiet"],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert done.stderr.strip() == f"ensemble: {path} did not match its name (edited or damaged); writing it again"
    assert path.read_text() == genuine
    with xr.open_dataset(out) as ds:
        assert ds.x.values.tobytes() == expected.x.values.tobytes()


@pytest.mark.skipif(os.getuid() != 0, reason="making a folder of another user's needs root")
def test_a_kernel_folder_of_another_users_is_refused_in_one_line(tmp_path, write_runfile):
    folder = tmp_path / "kernels"
    folder.mkdir()
    os.chown(folder, 4242, 4242)
    path = _runfile(tmp_path, "rk4")
    _scene(tmp_path, 1.0)
    env = {**os.environ, "ENSEMBLE_KERNEL_DIR": str(folder)}
    done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(path), "-o", str(tmp_path / "out.nc")],
                          capture_output=True, text=True, env=env)
    assert done.returncode == 2 and done.stderr.strip().count("\n") == 0, done.stderr
    assert "belongs to another user (uid 4242)" in done.stderr and not list(tmp_path.glob("out.nc*"))


def test_a_new_kernel_folder_is_private(tmp_path, monkeypatch):
    from ensemble.tuning import private_kernel_folder

    monkeypatch.setenv("ENSEMBLE_KERNEL_DIR", str(tmp_path / "mine" / "kernels"))
    assert private_kernel_folder().stat().st_mode & 0o777 == 0o700
    (tmp_path / "open").mkdir(mode=0o777)
    os.chmod(tmp_path / "open", 0o777)
    monkeypatch.setenv("ENSEMBLE_KERNEL_DIR", str(tmp_path / "open"))
    assert private_kernel_folder().stat().st_mode & 0o777 == 0o700
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("ENSEMBLE_KERNEL_DIR", str(tmp_path / "file" / "kernels"))  # given, so used or refused
    with pytest.raises(ensemble.EnsembleError, match=r"file/kernels: cannot make the kernel folder \(Not a dir"):
        private_kernel_folder()


@pytest.mark.parametrize("method, returned", [("rk4", "math.nan"), ("rk4", "-math.inf"), ("rk4", "x * math.nan"),
                                              ("euler", "math.inf"), ("dopri5", "math.nan")])
def test_a_non_finite_right_hand_side_fails_its_member(tmp_path, returned, method):
    """With fast-math's nnan and ninf LLVM folded a constant NaN away: every member ok, x frozen at its start. A
    fixed step's member blows up; dopri5 rejects every trial step whose error is not a number, until its step
    underflows."""
    (tmp_path / "decay.py").write_text(DECAY.replace("(-RATE * a * x,)", f"({returned},)"))
    ds = ensemble.run(RUN.format(method=method, members=3, scene=tmp_path / "decay.py"), progress=False)
    failed = Status.STEP_SIZE_UNDERFLOW if method == "dopri5" else Status.BLEW_UP
    assert np.all(ds.status.values == int(failed)), ds.status.values
    assert np.all(np.isnan(ds.x.isel(t=-1).values))


def test_a_resume_after_the_scene_was_edited_is_refused(tmp_path, monkeypatch, capsys):
    _scene(tmp_path, 1.0)
    runfile = _runfile(tmp_path, "rk4", members=40)
    out = tmp_path / "out.nc"
    _interrupted(load(runfile), out, after=2, monkeypatch=monkeypatch)
    _scene(tmp_path, 2.0)
    assert cli.main(["run", str(runfile), "-o", str(out), "--quiet", "--resume"]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "scene_sources_sha256 differs" in line, line
    assert len(list(folder_of(out).glob("members-*.nc"))) == 2 and not out.exists()


def test_a_resume_writes_the_run_files_parameters_and_attributes_again(tmp_path, monkeypatch, decay):
    """Edits of OUT.nc.tmp outside the samples (a parameter, global attributes, a unit) do not reach the result:
    it is bitwise the uninterrupted run's."""
    from .test_resume import same_bits

    runfile = _runfile(tmp_path, "rk4", members=40, scene=decay)
    whole, out = tmp_path / "whole.nc", tmp_path / "out.nc"
    runner.run(load(runfile), whole, progress=False)
    _interrupted(load(runfile), out, after=2, monkeypatch=monkeypatch)
    with netCDF4.Dataset(f"{out}.tmp", "a") as nc:
        nc["a"][3] = 0.5
        nc.seed = 999
        nc.method = "euler"
        nc.forged = "yes"
        nc["x"].units = "degree"
        nc["member"].comment = "forged"
    assert cli.main(["run", str(runfile), "-o", str(out), "--quiet", "--resume"]) == 0
    same_bits(out, whole)


def test_a_scene_that_exits_at_import_is_one_line(tmp_path, capsys):
    (tmp_path / "decay.py").write_text("import sys\nsys.exit(0)\n" + DECAY)
    assert cli.main(["run", str(_runfile(tmp_path, "rk4")), "-o", str(tmp_path / "out.nc")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "called sys.exit(0)" in err, err
    assert not list(tmp_path.glob("out.nc*"))


def test_the_kernels_identity_is_in_the_result(tmp_path, decay):
    from ensemble.scenes.contract import identity
    from ensemble.scenes.contract import load as load_scene

    ds = ensemble.run(str(_runfile(tmp_path, "rk4", scene=decay)), progress=False)
    assert ds.attrs["scene_sources_sha256"] == identity(load_scene(decay))
    assert len(ds.attrs["engine_sha256"]) == 64 and "fastmath ['contract']" in ds.attrs["compile_target"]
    assert math.isfinite(float(ds.x.isel(t=-1).max()))


def test_the_kernels_flush_subnormals_to_zero(tmp_path):
    """x' = a y^2 with y = 1e-155: y^2 = 1e-310 is subnormal, which the kernels' threads flush to zero (a
    hundred cycles an operation otherwise), so x stays 0; without flushing one euler step would make it 1e-295.
    A thread that is not a kernel's keeps IEEE's gradual underflow."""
    (tmp_path / "square.py").write_text('''
from ensemble import Parameter

STATE = {"x": ("m", "x"), "y": ("m", "y")}
PARAMETERS = {"a": Parameter("s-1", "a"), "x0": Parameter("m", "x at 0"), "y0": Parameter("m", "y at 0")}

def rhs(t, x, y, a):
    return y * y * a, 0.0
''')
    ds = ensemble.run(f'scene = {str(tmp_path / "square.py")!r}\nmethod = "euler"\ndt = 1.0\nt_end = 1.0\n'
                      'save_dt = 1.0\nmembers = 2\nseed = 1\n[parameters]\na = 1e15\nx0 = 0.0\ny0 = 1e-155\n',
                      progress=False)
    assert np.all(ds.status.values == 0) and np.all(ds.x.values == 0.0), ds.x.values
    assert np.float64(1e-155) * np.float64(1e-155) * np.float64(1e15) == pytest.approx(1e-295, rel=1e-3)


def test_an_rhs_that_raises_midway_is_one_line_and_exit_3(tmp_path, capsys):
    (tmp_path / "decay.py").write_text(DECAY.replace("    return (-RATE * a * x,)", "    if t > 0.55:\n"
                                                     "        raise ValueError('x ran away')\n"
                                                     "    return (-a * x,)"))
    out = tmp_path / "out.nc"
    assert cli.main(["run", str(_runfile(tmp_path, "rk4")), "-o", str(out), "--quiet"]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "raised ValueError: x ran away, between t = 0 and 1 s" in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("change, expected", [
    ('NAME = "../../escaped"\n', "NAME must be letters, digits"),
    ('STATE = {"a/b": ("m", "x")}\n', "'a/b' is not a name for a state variable"),
    ('STATE = {"": ("m", "x")}\n', "'' is not a name for a state variable"),
    ('PARAMETERS["sweep_point"] = Parameter("1", "clash")\n', "'sweep_point' is a name every result already uses"),
    ('import numpy as np\ndef exact(t, x0, a):\n    return x0 * np.exp(-a * t), x0, x0\n',
     "exact must return a tuple of 1 arrays (one per state variable), got 3"),
    ('def exact(t, x0, a):\n    return (x0[:, :2],)\n', "exact's value 0 does not broadcast to (times, members)"),
    ('def check(values):\n    raise Exception("no")\n', "check(values) raised Exception: no (a value no"),
    ('def slow(x):\n    return x\ndef rhs(t, x, a):\n    return (-slow(a) * x,)\n',
     "rhs calls slow, a plain Python function: decorate it with @numba.njit"),
])
def test_a_scene_that_breaks_the_contract_is_one_line(tmp_path, capsys, change, expected):
    (tmp_path / "decay.py").write_text("RATE = 1.0\n" + DECAY + change)
    assert cli.main(["run", str(_runfile(tmp_path, "rk4")), "-o", str(tmp_path / "out.nc")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and expected in err[0], err
    assert not list(tmp_path.glob("out.nc*"))


def test_a_kernel_that_does_not_compile_leaves_no_folder_and_says_one_line(tmp_path, capsys):
    """Bad input found while compiling: its one line alone (no notice of the machine's tuning before it), and no
    empty output folder made for the result that never came."""
    (tmp_path / "decay.py").write_text("import fractions\nRATE = 1.0\n" + DECAY.replace(
        "return (-RATE * a * x,)", "return (-RATE * a * x * float(fractions.Fraction(1)),)"))  # Python, not Numba
    out = tmp_path / "new" / "deeper" / "out.nc"
    assert cli.main(["run", str(_runfile(tmp_path, "euler", members=2)), "-o", str(out)]) == 2
    err = [line for line in capsys.readouterr().err.splitlines() if not line.startswith("compiling")]
    assert len(err) == 1 and "the euler kernel does not compile" in err[0], err
    assert not (tmp_path / "new").exists()


@pytest.fixture(scope="module")
def fitted_decay(tmp_path_factory, decay):
    """A result of the shared decay.py, whose fit(ds) does what the environment's DECAY_FIT says."""
    folder = tmp_path_factory.mktemp("fit")
    out = folder / "out.nc"
    assert cli.main(["run", str(_runfile(folder, "rk4", members=2, scene=decay)), "-o", str(out), "--quiet"]) == 0
    return out


@pytest.mark.parametrize("fit, expected", [
    ("raise", "the decay scene's fit(ds) raised ValueError: my fit broke"),
    ("dict", "the decay scene's fit(ds) returned a dict, not an xarray.Dataset over member"),
])
def test_a_scenes_fit_that_raises_or_returns_no_dataset_is_one_line(fitted_decay, monkeypatch, capsys, fit,
                                                                    expected):
    monkeypatch.setenv("DECAY_FIT", fit)
    assert cli.main(["fit", str(fitted_decay)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"ensemble: error: {fitted_decay}: {expected}"], err
    with pytest.raises(ensemble.EnsembleError, match=re.escape(expected)):
        ensemble.fit(fitted_decay)


@pytest.mark.parametrize("options, expected", [
    ({"device": "tpu"}, "device: 'tpu' is not one of cpu, cuda"),
    ({"precision": "float16"}, "precision: 'float16' is not one of float64, float32"),
    ({"chunk": "8"}, "chunk: a whole number of members, not '8'"),
])
def test_the_api_refuses_what_it_cannot_do(tmp_path, options, expected):
    _scene(tmp_path, 1.0)
    with pytest.raises(ensemble.EnsembleError, match=expected):
        ensemble.run(str(_runfile(tmp_path, "rk4")), progress=False, **options)


def test_a_run_files_path_that_does_not_exist_is_said_as_such(tmp_path):
    with pytest.raises(ensemble.EnsembleError, match="osc: no such file"):
        ensemble.run("osc", progress=False)
    with pytest.raises(ensemble.EnsembleError, match="no_such.toml: no such file"):
        ensemble.run(tmp_path / "no_such.toml", progress=False)


def test_fit_takes_combined_results(tmp_path):
    """The README's own workflow: ensemble.fit of ensemble.open of several results, of a list, of a glob: each
    member fitted as in its own result."""
    from .conftest import top_runfile

    paths = []
    for seed in (1, 2):
        paths.append(tmp_path / f"r{seed}.nc")
        ensemble.run(top_runfile(members=3, t_end=2.0, seed=seed), paths[-1], progress=False)
    alone = np.concatenate([ensemble.fit(p).rate.values for p in paths])
    for given in (ensemble.open(paths), paths, str(tmp_path / "r*.nc")):
        assert np.array_equal(ensemble.fit(given).rate.values, alone)
    with pytest.raises(ensemble.EnsembleError, match="ensemble.fit takes a result"):
        ensemble.fit({})
    (tmp_path / "broken.nc").write_bytes(paths[0].read_bytes()[:1000])
    with pytest.raises(ensemble.EnsembleError, match="broken.nc: cannot be read as a result"):
        ensemble.fit([paths[0], tmp_path / "broken.nc"])


def test_fit_command_takes_several_results(tmp_path, capsys):
    """`ensemble fit A.nc B.nc`: the results combined, a row per run, the fits beside the first; results of two
    scenes, or a file that is not one, are one line and exit 2."""
    from ensemble.cli import main

    from .conftest import top_runfile

    root = Path(__file__).resolve().parent.parent

    paths = []
    for seed in (1, 2):
        paths.append(tmp_path / f"r{seed}.nc")
        ensemble.run(top_runfile(members=3, t_end=2.0, seed=seed), paths[-1], progress=False)
    assert main(["fit", *map(str, paths), "--check", "--against", "method"]) == 0
    printed = capsys.readouterr().out
    assert "r1.nc and 1 more" in printed and re.search(r"^run 1 .* pass$", printed, flags=re.M), printed
    fits = xr.load_dataset(tmp_path / "r1_tilt_decay.nc")
    alone = np.concatenate([ensemble.fit(p).rate.values for p in paths])
    assert np.array_equal(fits.rate.values, alone)
    ensemble.run(root / "runs" / "two_mass.toml", tmp_path / "chain.nc", progress=False)
    (tmp_path / "text.nc").write_text("not a result")
    for other in ("chain.nc", "text.nc"):
        assert main(["fit", str(paths[0]), str(tmp_path / other)]) == 2
        said = capsys.readouterr().err.strip().splitlines()
        assert len(said) == 1 and said[0].startswith("ensemble: error:"), said


@pytest.mark.parametrize("damage", ["features", "nesting"])
def test_a_tuning_file_that_is_not_this_machines_is_ignored_in_one_line(tmp_path, damage):
    import json

    from ensemble import tuning

    path = tmp_path / "tuning.json"
    tuning.save(tuning.Tuning(vector_bits=256), {}, path)
    found = json.loads(path.read_text())
    if damage == "features":
        found["choices"]["features"] = "-avx,-avx2,-avx512f,-fma"
        path.write_text(json.dumps(found))
    else:
        path.write_text('{"format": 1, "choices": ' + "[" * 100_000 + "]" * 100_000 + "}")
    chosen, line = tuning.load(path)
    assert chosen is None and line.startswith(f"ensemble: ignoring {path}: it cannot be read"), line


@pytest.mark.parametrize("damage", ["truncated"])
def test_a_damaged_numba_cache_file_is_compiled_again_in_one_line(tmp_path, damage):
    """A .nbc file cut short or overwritten used to stop every later run (exit 3, "LLVM bitcode parsing error",
    naming no cache) until the cache was emptied by hand."""
    _scene(tmp_path, 1.0)
    runfile = _runfile(tmp_path, "rk4")
    env = {**{k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"},  # Numba's cache beside the kernel
           "ENSEMBLE_KERNEL_DIR": str(tmp_path / "kernels")}

    def run(out):
        return subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--quiet"],
                              capture_output=True, text=True, env=env)

    assert run(tmp_path / "first.nc").returncode == 0
    (data,) = (tmp_path / "kernels").glob("__pycache__/ensemble_kernel_decay_rk4_*.nbc")
    data.write_bytes(data.read_bytes()[:200] if damage == "truncated" else b"\x80\x04garbage" * 100)
    done = run(tmp_path / "second.nc")
    assert done.returncode == 0, done.stderr
    line = done.stderr.strip()
    assert "\n" not in line and "Numba's cache of the rk4 kernel" in line and "compiling it again" in line, line
    with xr.open_dataset(tmp_path / "first.nc") as a, xr.open_dataset(tmp_path / "second.nc") as b:
        assert a.x.values.tobytes() == b.x.values.tobytes()


def test_a_numba_cache_that_cannot_be_written_is_one_line(tmp_path, monkeypatch, capsys):
    """A full disk under Numba's cache: the kernel compiled here runs, and one line says why the next run will
    compile it again (it was "could not be loaded", after compiling it twice)."""
    import errno

    import numba.core.caching

    def full(self, *args):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setenv("ENSEMBLE_KERNEL_DIR", str(tmp_path / "kernels"))
    monkeypatch.setattr(numba.core.caching.IndexDataCacheFile, "save", full)
    _scene(tmp_path, 0.75)  # a kernel of its own: compiled (and saved) in this test
    ds = ensemble.run(str(_runfile(tmp_path, "rk4")), progress=False)
    said = capsys.readouterr().err.strip().splitlines()
    assert len(said) == 1 and said[0].startswith("ensemble: cannot write Numba's cache of the rk4 kernel in "), said
    assert said[0].endswith("(No space left on device); every run compiles it again until it can"), said
    np.testing.assert_allclose(_x_end(ds), _expected(ds, 0.75, "rk4"), rtol=1e-9)


def test_saved_times_are_written_in_pieces_to_the_same_bits(monkeypatch, decay):
    """A member may save 10^8 samples: the t coordinate is written TIMES_AT_ONCE at a time (a one-member run
    saving 2e7 samples peaked at 527 MB where it now takes 231, against 218 MB for 100 samples)."""
    from ensemble import store

    monkeypatch.setattr(store, "TIMES_AT_ONCE", 7)
    ds = ensemble.run(RUN.format(method="rk4", members=2, scene=decay).replace("save_dt = 0.5", "save_dt = 0.05"),
                      progress=False)
    assert ds.sizes["t"] == 21 and ds.t.values.tobytes() == (np.arange(21) * 0.05).tobytes()


def test_a_scene_edited_during_a_run_stops_it_in_one_line(tmp_path, monkeypatch, capsys):
    """Edited after the first of its chunks, the run stops (one line, exit 3: the chunk it finished is kept),
    and a resume refuses the parts of the other physics: no result mixes the two (the old code computed the
    first chunk with the old rate and the others with the new)."""
    _scene(tmp_path, 1.0)
    runfile = _runfile(tmp_path, "rk4", members=40)
    real, calls = runner.integrate_chunk, []

    def compute(*args, **kwargs):
        if calls:
            _scene(tmp_path, 2.0)
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(runner, "integrate_chunk", compute)
    out = tmp_path / "out.nc"
    with pytest.raises(ensemble.EnsembleError, match="changed since the run began; a run takes one physics") as raised:
        runner.run(load(runfile), out, chunk=7, progress=False)
    assert raised.value.exit_status == 3 and not out.exists()
    monkeypatch.setattr(runner, "integrate_chunk", real)
    assert cli.main(["run", str(runfile), "-o", str(out), "--quiet", "--resume"]) == 2
    line = capsys.readouterr().err.strip()
    assert "\n" not in line and "scene_sources_sha256 differs" in line, line


def test_ctrl_c_while_compiling_stops_at_once(tmp_path, monkeypatch, capfd):
    """Issue 50: Ctrl-C while LLVM compiled could land inside one of its callbacks into Python: ctypes printed
    "Exception ignored" with a traceback, dropped the interrupt, and the run went on compiling (27 s). Compiling
    now runs on a thread of its own, and the interrupt reaches the run at once. Here a stand-in compiler spends
    its time in such callbacks."""
    import ctypes
    import signal
    import threading
    import time

    from ensemble import runner
    from ensemble.spec import load

    _scene(tmp_path, 1.0)
    spec = load(_runfile(tmp_path, "rk4"))
    callback = ctypes.CFUNCTYPE(None)(lambda: time.sleep(0.5))  # as LLVM's object cache calls into Python

    def compiling(*args, **kwargs):
        for _ in range(6):
            callback()

    monkeypatch.setattr(runner.launch, "prepare", compiling)
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()
        start = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            runner.prepare_kernels(spec, announce=False)
        assert time.monotonic() - start < 1.5
    finally:
        signal.signal(signal.SIGINT, previous)
    assert "Exception ignored" not in capfd.readouterr().err


@pytest.mark.parametrize("asked", [None, "0"])
def test_intel_svml_is_off_unless_the_user_asks_for_it(asked):
    """Importing ensemble before Numba sets NUMBA_DISABLE_INTEL_SVML=1 (SVML's sin and exp are not the C library's
    bits); a user's own setting stands. compile_target says which Numba ran with. (This host's LLVM has no SVML,
    so Numba's USING_SVML stays False either way: what is checked is the switch Numba reads.)"""
    env = {name: value for name, value in os.environ.items() if name != "NUMBA_DISABLE_INTEL_SVML"}
    if asked is not None:
        env["NUMBA_DISABLE_INTEL_SVML"] = asked
    code = ("import ensemble, numba; from ensemble.engine.kernels import compile_target; "
            "print(numba.config.DISABLE_INTEL_SVML, numba.config.USING_SVML, compile_target().split('; ')[-1])")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    disabled, using, said = out.split(maxsplit=2)
    assert disabled == ("0" if asked == "0" else "1")
    assert said.strip() == ("svml on" if using == "True" else "svml off")


def test_numbas_inliner_without_its_spare_copies_compiles_the_same_code(tmp_path):
    """ensemble.inlining edits two lines of Numba's inliner (up to a third off a kernel's compile): a top's euler kernel
    with a tilt event, made anew with Numba's inliner as ensemble edits it and as Numba ships it
    (ENSEMBLE_NUMBA_INLINER=unedited), is the same optimized LLVM IR to the byte. The package's own functions are
    loaded from Numba's cache by both (this process ran the same first), so each compiles the same functions."""
    text = top_runfile(members=3, t_end=0.2, save_dt=0.1, method="euler") + '[events.tip]\nof = "tilt"\nvalue = 0.3\n'
    ensemble.run(text, progress=False)
    code = (f"import sys, ensemble; ensemble.run({text!r}, progress=False); from ensemble import inlining;"
            " print('applied', inlining.applied, file=sys.stderr)")
    dumps = {}
    for inliner in ("edited", "unedited"):
        env = {**os.environ, "ENSEMBLE_NUMBA_INLINER": inliner, "ENSEMBLE_KERNEL_DIR": str(tmp_path / inliner),
               "NUMBA_DUMP_OPTIMIZED": "1"}
        done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-2000:]
        assert f"applied {inliner == 'edited'}" in done.stderr
        dumps[inliner] = done.stdout
    assert "OPTIMIZED DUMP kernel" in dumps["edited"] and len(dumps["edited"]) > 100_000
    assert dumps["edited"] == dumps["unedited"]


def test_a_numba_whose_inliner_reads_otherwise_is_left_alone(monkeypatch):
    """The edit is made only to the lines it was written for: an inline_ir or inline_function whose source differs
    (another Numba's), or a pass that keeps the original inline_ir returns, leaves the installed inliner as it is."""
    from ensemble import inlining

    assert inlining.apply()  # the installed Numba's lines are those the edit was written for
    monkeypatch.setitem(inlining.ORIGINAL, "inline_ir", inlining.apply)
    assert inlining._edited_inline_ir() is None
    monkeypatch.setitem(inlining.ORIGINAL, "inline_function", inlining._inline_function)
    assert not inlining._inline_function_is_numbas()
    discarded = "            _, _, _, new_blocks = \\\n                inline_worker.inline_function(state.func_ir,\n"
    assert inlining.discards_the_original(discarded)
    assert not inlining.discards_the_original(discarded.replace("_, _, _, new_blocks", "kept, _, _, new_blocks"))
    assert not inlining.discards_the_original("no inlining here\n")


def test_an_unknown_inliner_setting_is_one_line_and_exit_2_with_nothing_written(tmp_path):
    """ENSEMBLE_NUMBA_INLINER takes 'edited' (the default) or 'unedited', read once, before a process's first kernel
    is made: a typo is named, not taken for either."""
    runfile = tmp_path / "run.toml"
    runfile.write_text(top_runfile(members=3, t_end=0.2, save_dt=0.1))
    command = [sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(tmp_path / "out" / "run.nc")]
    done = subprocess.run(command, env={**os.environ, "ENSEMBLE_NUMBA_INLINER": "off"}, capture_output=True,
                          text=True)
    err = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(err) == 1, done.stderr
    assert "ENSEMBLE_NUMBA_INLINER='off'" in err[0] and "'unedited'" in err[0], err
    assert not (tmp_path / "out").exists()

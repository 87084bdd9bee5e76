"""A scene of the user's own, from a file: every method family that applies to it converges at its order to the
closed form, its run file runs and fits like a built-in scene's, and each mistake in a scene file is one line,
exit status 2, with nothing written."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.integrate import solve_ivp

from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SceneError, methods_for, resolve

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "driven_oscillator.py"
# Under-, critically and over-damped members, driven off and on resonance
MEMBERS = {"gamma": np.array([0.1, 1.0, 2.5, 0.05]), "omega0": np.array([1.0, 1.0, 1.5, 2.0]),
           "F": np.array([0.5, 0.3, 1.0, 0.2]), "Omega": np.array([0.9, 2.0, 0.7, 2.0]),
           "x0": np.array([1.0, -0.5, 0.2, 0.0]), "v0": np.array([0.0, 0.3, -1.0, 0.5])}
# A harmonic oscillator with exactly solved kick and drift pieces: splittings apply to it
SPRING = '''
from ensemble import Parameter
from ensemble.methods import KICK_DRIFT

STATE = {"x": ("m", "position"), "v": ("m s-1", "velocity")}
PARAMETERS = {"omega": Parameter("rad s-1", "angular frequency"), "x0": Parameter("m", "start"),
              "v0": Parameter("m s-1", "start", default=0.0)}
PIECES = KICK_DRIFT
EVALUATING_PIECES = ("kick",)

def rhs(t, x, v, omega):
    return v, -omega * omega * x

def kick(tau, x, v, omega):
    return x, v - tau * omega * omega * x

def drift(tau, x, v, omega):
    return x + tau * v, v

def exact(t, x0, v0, omega):
    import numpy as np
    c, s = np.cos(omega * t), np.sin(omega * t)
    return x0 * c + v0 / omega * s, v0 * c - x0 * omega * s
'''


def largest_error(scene, method, values, dt=None, t_end=4.0, **tolerances):
    """max |x - x_exact| over the saved samples (every 0.5 s), over every member."""
    n_save = round(t_end / 0.5) + 1
    outcome = launch.integrate(scene, METHODS[method], values, {}, n_save=n_save, save_dt=0.5, dt=dt, **tolerances)
    exact = scene.exact(values, {}, np.arange(n_save) * 0.5)
    assert np.all(outcome.status == 0)
    return np.abs(outcome.samples - exact).max()


def test_the_examples_closed_form_solves_its_equation():
    """The closed form (under-, critically and over-damped) against scipy's DOP853 at tight tolerances: an
    independent check of the reference every method is measured against."""
    scene = resolve(str(EXAMPLE))
    t = np.linspace(0.0, 8.0, 33)
    exact = scene.exact(MEMBERS, {}, t)
    for j in range(4):
        p = [MEMBERS[name][j] for name in ("gamma", "omega0", "F", "Omega")]
        reference = solve_ivp(lambda s, y: scene.module.rhs(s, *y, *p), (0.0, 8.0),
                               [MEMBERS["x0"][j], MEMBERS["v0"][j]], method="DOP853", t_eval=t, rtol=1e-12,
                               atol=1e-13)
        assert np.abs(reference.y.T - exact[:, :, j]).max() < 1e-10, j


@pytest.mark.parametrize("method, order", [("euler", 1), ("rk4", 4)])
def test_fixed_step_methods_converge_at_their_order_on_the_example(method, order):
    scene = resolve(str(EXAMPLE))
    assert {m.name for m in methods_for(scene)} == {"euler", "rk4", "dopri5", "exact"}
    coarse, fine = (largest_error(scene, method, MEMBERS, dt) for dt in (0.01, 0.005))
    assert order - 0.2 < np.log2(coarse / fine) < order + 0.3, (coarse, fine)


def test_dopri5_meets_its_tolerance_and_the_exact_method_is_the_closed_form_on_the_example():
    scene = resolve(str(EXAMPLE))
    loose, tight = (largest_error(scene, "dopri5", MEMBERS, rtol=rtol, atol=rtol * 1e-3) for rtol in (1e-5, 1e-9))
    assert tight < 1e-7 and loose / tight > 1e3, (loose, tight)
    assert largest_error(scene, "exact", MEMBERS) == 0.0


@pytest.mark.parametrize("method, order", [("symplectic_euler", 1), ("verlet", 2), ("yoshida4", 4)])
def test_a_user_scenes_splittings_converge_at_their_order(tmp_path, method, order):
    (tmp_path / "spring.py").write_text(SPRING)
    scene = resolve(str(tmp_path / "spring.py"))
    values = {"omega": np.array([1.0, 2.0, 3.0]), "x0": np.array([1.0, 0.5, -0.2]), "v0": np.array([0.0, 1.0, 0.4])}
    coarse, fine = (largest_error(scene, method, values, dt) for dt in (0.02, 0.01))
    assert order - 0.2 < np.log2(coarse / fine) < order + 0.3, (coarse, fine)


def run(runfile: Path, out: Path, *extra):
    return subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(out), "--quiet", *extra],
                          capture_output=True, text=True, timeout=600)


def test_the_examples_run_file_runs_and_its_fit_finds_the_steady_amplitude(tmp_path):
    done = run(ROOT / "runs" / "driven_oscillator.toml", tmp_path / "osc.nc")
    assert done.returncode == 0, done.stderr
    ds = xr.load_dataset(tmp_path / "osc.nc")
    assert ds.attrs["scene"] == "driven_oscillator" and ds.attrs["scene_source"] == str(EXAMPLE)
    assert ds["x"].attrs["units"] == "m" and ds["x"].dims == ("member", "t")
    fitted = resolve(str(EXAMPLE)).fit(ds)
    np.testing.assert_allclose(fitted["amplitude"], fitted["amplitude_theory"], rtol=1e-8)  # rk4 at dt = 0.01 s
    checked = subprocess.run([sys.executable, "-m", "ensemble", "fit", str(tmp_path / "osc.nc"), "--check"],
                             capture_output=True, text=True)  # the example passes its own check (issue 53)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    assert checked.stdout.count(" pass\n") == 10 and "Omega = 0.95 " in checked.stdout, checked.stdout


STABILITY_SCAN = f"""scene = "{EXAMPLE}"
dt = 1.0
t_end = 3000.0
save_dt = 1.0
members = 1
seed = 1
save = ["x"]
[measure]
growth = true
[parameters]
gamma = 0.0
F = 0.0
Omega = 1.0
x0 = 1e-3
[[sweep]]
method = ["euler"]
omega0 = [0.05, 0.5, 1.0, 2.0]
[[sweep]]
method = ["rk4"]
omega0 = [0.5, 2.0, 2.7, 2.79, 2.81, 2.82, 2.84, 2.85, 2.88, 3.0]
"""


def test_a_user_scene_that_declares_its_stability_gets_stability_maps(tmp_path, capsys):
    """The example's optional stability functions: `ensemble stability --check` on an undamped scan of h omega0
    finds rk4's limit 2 sqrt(2) within 2% (between the scan's 2.82 and 2.84) and euler growing at every step."""
    from ensemble import cli, stability

    runfile = tmp_path / "scan.toml"
    runfile.write_text(STABILITY_SCAN)
    out = tmp_path / "scan.nc"
    assert cli.main(["run", str(runfile), "-o", str(out), "--quiet"]) == 0
    assert cli.main(["stability", str(out), "--check"]) == 0, capsys.readouterr().out
    points = stability.stability_map(xr.load_dataset(out))
    rows = {r["method"]: r for r in stability.stability_limits(points)}
    assert rows["rk4"]["theory"] == pytest.approx(8**0.5, rel=1e-6) and 2.82 <= rows["rk4"]["measured"] <= 2.84
    assert rows["euler"]["theory"] == 0 and rows["euler"]["measured"] == 0
    # each member's growth per step (fitted to the state's norm) is the theory's |R(i h omega0)|, where a
    # member lasts long enough to fit: euler at h omega0 = 1 blows up after 40 steps
    lasting = points["x"].values <= np.where(points["method"].values == "euler", 1.0, 2.85)
    np.testing.assert_allclose(points["growth"].values[lasting], points["growth_theory"].values[lasting], rtol=3e-4)


def test_a_user_scene_without_stability_axes_is_refused_by_ensemble_stability_in_one_line(tmp_path, capsys):
    from ensemble import cli

    (tmp_path / "spring.py").write_text(SPRING)
    runfile = tmp_path / "run.toml"
    runfile.write_text('scene = "spring.py"\nmethod = "rk4"\ndt = 0.1\nt_end = 1.0\nsave_dt = 0.1\nmembers = 2\n'
                       'seed = 1\n[measure]\ngrowth = true\n[parameters]\nomega = 1.0\nx0 = 1.0\n')
    assert cli.main(["run", str(runfile), "-o", str(tmp_path / "r.nc"), "--quiet"]) == 0
    capsys.readouterr()
    assert cli.main(["stability", str(tmp_path / "r.nc")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "declares no stability axes" in err, err


def test_a_scene_declaring_part_of_its_stability_is_one_line(tmp_path):
    (tmp_path / "spring.py").write_text(SPRING + "STABILITY_AXES = ('h omega',)\n")
    with pytest.raises(SceneError, match="declares STABILITY_AXES for stability maps, but not stability_axis, "
                                         "step_growth, axis_growth"):
        resolve(str(tmp_path / "spring.py"))


BROKEN = {
    "no rhs": ("STATE = {'x': ('m', 'x')}\nPARAMETERS = {'x0': Parameter('m', 'start')}\n", "has no rhs"),
    "wrong signature": (_ := "STATE = {'x': ('m', 'x')}\nPARAMETERS = {'k': Parameter('s-1', 'rate'), "
                        "'x0': Parameter('m', 'start')}\n") + "def rhs(t, x):\n    return (-x,)\n",
    "wrong size": _ + "def rhs(t, x, k):\n    return -k * x, 0.0\n",
    "reserved name": "STATE = {'status': ('1', 's')}\nPARAMETERS = {'status0': Parameter('1', 'start')}\n"
                     "def rhs(t, status):\n    return (0.0,)\n",
    "does not import": _ + "def rhs(t, x, k):\n    return (-k * x,\n",
    "does not compile": "import scipy.special\n" + _ + "def rhs(t, x, k):\n    return (scipy.special.erf(x) * k,)\n",
}
BROKEN["no rhs"] = BROKEN["no rhs"][0]
SAYS = {"no rhs": "has no rhs", "wrong signature": "rhs takes 2 argument(s), (t, x); ensemble calls it as rhs(t, x, k)",
        "wrong size": "rhs must return a tuple of 1 numbers", "reserved name": "'status' is a name every result",
        "does not import": "does not import (line", "does not compile": "the rk4 kernel does not compile"}


@pytest.mark.parametrize("mistake", sorted(BROKEN))
def test_a_mistake_in_a_scene_file_is_one_line_and_exit_2_with_nothing_written(tmp_path, mistake):
    (tmp_path / "scene.py").write_text("from ensemble import Parameter\n" + BROKEN[mistake])
    runfile = tmp_path / "run.toml"
    runfile.write_text('scene = "scene.py"\nmethod = "rk4"\ndt = 0.1\nt_end = 1.0\nsave_dt = 0.5\nmembers = 2\n'
                       'seed = 1\n[parameters]\n' + ("status0 = 1.0\n" if mistake == "reserved name" else
                                                    "x0 = 1.0\n" + ("k = 1.0\n" if mistake != "no rhs" else "")))
    done = run(runfile, tmp_path / "out" / "result.nc")
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and SAYS[mistake] in done.stderr, done.stderr
    assert "Traceback" not in done.stderr and not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_an_unknown_scene_name_says_what_a_scene_can_be():
    with pytest.raises(SceneError, match="unknown scene 'pendulum'; scenes: top, chain, body, or a scene file"):
        resolve("pendulum")


def test_the_reserved_names_are_every_name_a_result_gives_each_member():
    from ensemble.scenes.contract import RESERVED
    from ensemble.store import RUN_RECORDS, SETTING_UNITS

    assert {"t", "member", "method", *RUN_RECORDS, *SETTING_UNITS} <= set(RESERVED)


def test_a_user_scene_chunks_resumes_runs_on_dask_and_measures_its_error_like_a_built_in_one(tmp_path, monkeypatch):
    """The example swept over methods with [measure] error: chunks of 1, a run interrupted and resumed, and two
    Dask workers all give the bits of one uninterrupted run, and its work-precision table has every method."""
    from ensemble import fitting, runner
    from ensemble.spec import load

    from .test_resume import chunked_and_resumed_match_one_run, same_bits

    text = (f'scene = "{EXAMPLE}"\nt_end = 4.0\nsave_dt = 0.5\nmembers = 3\nseed = 5\n[parameters]\n'
            'gamma = { uniform = [0.05, 0.5] }\nomega0 = 1.0\nF = 0.5\nOmega = 0.9\nx0 = { normal = [0.0, 1.0] }\n'
            '[measure]\nerror = true\n[[sweep]]\nmethod = ["euler", "rk4"]\ndt = [0.01, 0.005]\n'
            '[[sweep]]\nmethod = ["dopri5"]\nrtol = [1e-6, 1e-9]\n[[sweep]]\nmethod = ["exact"]\n')
    path = tmp_path / "sweep.toml"
    path.write_text(text)
    whole = chunked_and_resumed_match_one_run(path, tmp_path, monkeypatch)
    table = fitting.work_precision(xr.load_dataset(whole))
    assert set(table["method"].values) == {"euler", "rk4", "dopri5", "exact"}
    errors = {(m, dt if m != "dopri5" else rtol): e for m, dt, rtol, e in
              zip(*(table[name].values for name in ("method", "dt", "rtol", "error")))}
    # error_max is relative, so near x = 0 it does not scale exactly as h^order (the orders are tested above)
    assert errors[("euler", 0.01)] > 1.5 * errors[("euler", 0.005)]
    assert errors[("rk4", 0.01)] > 4.0 * errors[("rk4", 0.005)]
    assert errors[("rk4", 0.01)] < 1e-4 * errors[("euler", 0.01)]
    assert errors[("dopri5", 1e-6)] > 10.0 * errors[("dopri5", 1e-9)]
    assert next(e for (m, _), e in errors.items() if m == "exact") == 0.0
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  env={"NUMBA_NUM_THREADS": "1"}) as local, distributed.Client(local) as client:
        remote = tmp_path / "remote.nc"
        runner.run(load(path), remote, chunk=4, progress=False, client=client)
    same_bits(remote, whole)


def test_an_edited_scene_file_compiles_anew_and_an_unchanged_one_loads_from_the_cache(tmp_path):
    """Numba's cache keys a generated kernel on its file, whose text holds a hash of the scene's file: the same
    scene loads its kernel from the cache in a new process, and an edited one compiles a kernel of its own."""
    import os

    scene = tmp_path / "decay.py"
    text = ("from ensemble import Parameter\nSTATE = {'x': ('m', 'x')}\n"
            "PARAMETERS = {'k': Parameter('s-1', 'rate'), 'x0': Parameter('m', 'start')}\n"
            "def rhs(t, x, k):\n    return (-FACTOR * k * x,)\n")
    scene.write_text(text.replace("FACTOR", "1.0"))
    runfile = tmp_path / "run.toml"
    runfile.write_text('scene = "decay.py"\nmethod = "rk4"\ndt = 0.01\nt_end = 1.0\nsave_dt = 1.0\nmembers = 1\n'
                       'seed = 1\n[parameters]\nk = 1.0\nx0 = 1.0\n')
    cache = tmp_path / "cache"
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}

    def run(name):
        done = subprocess.run([sys.executable, "-m", "ensemble", "run", str(runfile), "-o", str(tmp_path / name),
                               "--quiet"], capture_output=True, text=True, env=env, timeout=600)
        assert done.returncode == 0, done.stderr
        return float(xr.load_dataset(tmp_path / name)["x"][0, -1]), sorted(p.name for p in cache.rglob("*.nbc"))

    first, compiled = run("first.nc")
    again, loaded = run("again.nc")
    assert again == first == pytest.approx(np.exp(-1.0), rel=1e-7) and loaded == compiled
    scene.write_text(text.replace("FACTOR", "2.0"))
    edited, recompiled = run("edited.nc")
    assert edited == pytest.approx(np.exp(-2.0), rel=1e-7) and len(recompiled) > len(compiled)


def test_methods_lists_what_applies_to_a_scene_of_ones_own(capsys):
    """`ensemble methods SCENE.py` (issue 53): the example has a closed form and no pieces to split."""
    from ensemble import cli

    assert cli.main(["methods", str(EXAMPLE)]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()[2:]]
    assert listed == ["euler", "rk4", "dopri5", "exact"], listed
    assert cli.main(["methods", "no_such_scene.py"]) == 2


def lorenz96_scene(folder, n: int) -> list[str]:
    """examples/lorenz96.py's scene of n sites, written into `folder`/lorenz96.py; its state names."""
    import runpy

    example = runpy.run_path(str(Path(__file__).parents[1] / "examples" / "lorenz96.py"))
    (folder / "lorenz96.py").write_text(example["scene_text"](n))
    return example["state_names"](n)


def test_a_scene_of_forty_state_variables_is_numpys_rk4(tmp_path):
    """Issue 51: an rhs of more than 30 arguments did not compile ("Calling a closure with *args is unsupported":
    Numba inlines no call that long). Lorenz-96 over 40 sites with rk4 against rk4 written in NumPy over the
    sites' array, to 1e-12 after 100 steps, and against scipy's DOP853 at 1e-13 to rk4's own error."""
    import ensemble

    n, dt = 40, 0.01
    names = lorenz96_scene(tmp_path, n)
    (tmp_path / "run.toml").write_text(f'scene = "lorenz96.py"\nmethod = "rk4"\ndt = {dt}\nt_end = 1.0\n'
                                       'save_dt = 0.5\nmembers = 2\nseed = 1\n[parameters]\nF = 8.0\n'
                                       'x0_0 = 8.01\n')
    ds = ensemble.run(tmp_path / "run.toml", progress=False)
    got = np.stack([ds[name].isel(t=-1).values for name in names], axis=1)

    def slope(x):
        return (np.roll(x, -1) - np.roll(x, 2)) * np.roll(x, 1) - x + 8.0
    x = np.zeros(n)
    x[0] = 8.01
    x0 = x.copy()
    for _ in range(100):
        k1 = slope(x)
        k2 = slope(x + dt / 2 * k1)
        k3 = slope(x + dt / 2 * k2)
        k4 = slope(x + dt * k3)
        x = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    np.testing.assert_allclose(got, np.broadcast_to(x, got.shape), rtol=1e-12, atol=1e-12)
    reference = solve_ivp(lambda t, y: slope(y), (0, 1), x0, method="DOP853", rtol=1e-13, atol=1e-13).y[:, -1]
    assert 1e-9 < np.abs(got - reference).max() < 1e-5  # rk4's own error at this step, not a copy of DOP853's

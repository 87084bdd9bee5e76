"""A field of sites of the user's own (examples/fput.py, a Fermi-Pasta-Ulam-Tsingou alpha chain written as one
`acceleration`): every sites method converges at its order to SciPy's DOP853 on its equations, between walls and
in a ring; its run file runs into a result with the chain's variables; a mistake in its file is one line, exit
status 2, with nothing written."""
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from scipy.integrate import solve_ivp

from ensemble.engine import launch
from ensemble.methods import METHODS
from ensemble.scenes import SceneError, methods_for, resolve

from .test_user_scene import run

ROOT = Path(__file__).resolve().parents[1]
FPUT = ROOT / "examples" / "fput.py"
N, T_END = 8, 1.0


def members(boundary: str) -> dict:
    """Three chains of N masses: springs and masses drawn, displaced, at rest."""
    rng = np.random.default_rng(7)
    springs = N + 1 if boundary == "fixed" else N
    return {"m": rng.uniform(0.5, 2.0, (3, N)), "k": rng.uniform(0.5, 1.5, (3, springs)),
            "x0": rng.normal(0.0, 0.3, (3, N)), "v0": rng.normal(0.0, 0.1, (3, N))}


def reference(values: dict, boundary: str, alpha: float) -> np.ndarray:
    """Each member's state (2N, members) at T_END from DOP853 on m x'' = f(d_right) - f(d_left), f(d) = k (d +
    alpha d^2): the chain's equations written in NumPy."""
    def rhs(t, y, k, m):
        x = y[:N]
        if boundary == "fixed":
            d = np.diff(np.concatenate(([0.0], x, [0.0])))  # spring s: from mass s - 1 (or the wall) to mass s
            f = k * (d + alpha * d * d)
            return np.concatenate((y[N:], (f[1:] - f[:-1]) / m))
        d = np.roll(x, -1) - x  # spring s: from mass s to mass s + 1 (mod N)
        f = k * (d + alpha * d * d)
        return np.concatenate((y[N:], (f - np.roll(f, 1)) / m))
    return np.stack([solve_ivp(rhs, (0.0, T_END), np.concatenate((values["x0"][j], values["v0"][j])), "DOP853",
                               rtol=1e-13, atol=1e-13, args=(values["k"][j], values["m"][j])).y[:, -1]
                     for j in range(3)], axis=1)


def error(method: str, boundary: str, **settings) -> float:
    scene = resolve(str(FPUT))
    values, constants = members(boundary), {"n": N, "boundary": boundary}
    out = launch.integrate(scene, METHODS[method], values, constants, n_save=2, save_dt=T_END, **settings)
    assert np.all(out.status == 0)
    return np.abs(out.samples[-1] - reference(values, boundary, scene.module.ALPHA)).max()


def test_every_sites_method_applies_to_a_users_field_of_sites():
    assert {m.name for m in methods_for(resolve(str(FPUT)))} == {"euler", "symplectic_euler", "verlet", "rk4",
                                                                 "yoshida4", "dopri5"}


# Each method on one boundary (a kernel each, which this file's tests and test_gpu's FPUT case share), walls and
# a ring both among them: method -> (boundary, order, dt).
CASES = {"euler": ("fixed", 1, 2e-3), "symplectic_euler": ("periodic", 1, 2e-3), "verlet": ("periodic", 2, 4e-3),
         "yoshida4": ("fixed", 4, 0.02), "rk4": ("fixed", 4, 0.02)}


@pytest.mark.parametrize("method", sorted(CASES))
def test_a_users_field_of_sites_converges_at_each_methods_order(method):
    boundary, order, dt = CASES[method]
    coarse, fine = error(method, boundary, dt=dt), error(method, boundary, dt=dt / 2)
    assert fine < 1e-2
    assert order - 0.2 < np.log2(coarse / fine) < order + 0.2, (coarse, fine)


def test_a_users_field_of_sites_meets_dopri5s_tolerance():
    assert error("dopri5", "fixed", rtol=1e-10, atol=1e-12) < 1e-8


def test_a_users_field_of_sites_runs_from_its_run_file(tmp_path):
    """runs/fput.toml, at N masses (the kernel the tests above use)."""
    text = (ROOT / "runs" / "fput.toml").read_text().replace("n = 32", f"n = {N}").replace("t_end = 2000.0",
                                                                                            "t_end = 100.0")
    assert f"n = {N}" in text and "t_end = 100.0" in text
    (tmp_path / "fput.toml").write_text(text.replace('scene = "../examples/fput.py"', f'scene = "{FPUT}"'))
    done = run(tmp_path / "fput.toml", tmp_path / "fput.nc")
    assert done.returncode == 0, done.stderr
    ds = xr.load_dataset(tmp_path / "fput.nc")
    assert ds.attrs["scene"] == "fput" and Path(ds.attrs["scene_source"]).resolve() == FPUT
    assert ds.x.dims == ("member", "t", "site") and ds.v.dims == ("member", "t", "site") and "energy" not in ds
    assert np.all(ds.status == 0) and np.isfinite(ds.x).all()
    # its masses' x and v are watched as the chain's: the first mass through 0, and the same samples
    events = '[events.cross]\nof = "x"\nindex = 0\ncount = 4\nkeep = ["v"]\n[parameters]'
    (tmp_path / "fput.toml").write_text((tmp_path / "fput.toml").read_text().replace("[parameters]", events, 1))
    done = run(tmp_path / "fput.toml", tmp_path / "events.nc")
    assert done.returncode == 0, done.stderr
    watched = xr.load_dataset(tmp_path / "events.nc")
    assert np.all(watched.cross_count > 0) and watched.cross_v.dims == ("member", "cross", "site")
    np.testing.assert_array_equal(watched.x, ds.x)


BROKEN = {
    "no acceleration": ("SITES = True\n", "sets SITES = True but has no acceleration(x_left, x, x_right"),
    "wrong signature": ("SITES = True\ndef acceleration(x_left, x, x_right):\n    return 0.0\n",
                        "acceleration takes 3 argument(s), (x_left, x, x_right); ensemble calls it as "
                        "acceleration(x_left, x, x_right, c_left, c_right)"),
    "two numbers": ("SITES = True\ndef acceleration(x_left, x, x_right, c_left, c_right):\n    return 0.0, 1.0\n",
                    "acceleration must return one number"),
    "plain helper": ("SITES = True\ndef f(d):\n    return d\ndef acceleration(x_left, x, x_right, c_left, c_right):"
                     "\n    return c_right * f(x_right - x) - c_left * f(x - x_left)\n",
                     "acceleration calls f, a plain Python function"),
}


@pytest.mark.parametrize("mistake", sorted(BROKEN))
def test_a_mistake_in_a_sites_scene_is_one_line_and_exit_2_with_nothing_written(tmp_path, mistake):
    text, says = BROKEN[mistake]
    (tmp_path / "chain.py").write_text(text)
    runfile = tmp_path / "run.toml"
    runfile.write_text('scene = "chain.py"\nmethod = "verlet"\ndt = 0.1\nt_end = 1.0\nsave_dt = 0.5\nmembers = 2\n'
                       'seed = 1\n[parameters]\nn = 4\nm = 1.0\nk = 1.0\nx0 = 0.1\n')
    done = run(runfile, tmp_path / "out" / "result.nc")
    assert done.returncode == 2, done.stderr
    assert len(done.stderr.strip().splitlines()) == 1 and says in done.stderr, done.stderr
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
    with pytest.raises(SceneError, match=says.split("(")[0]):
        resolve(str(tmp_path / "chain.py"))

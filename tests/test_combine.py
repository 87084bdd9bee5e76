"""Several results as one dataset: unique member ids and sweep points, each run's provenance, groupby, fits."""
import numpy as np
import pytest
import xarray as xr

from ensemble import runner
from ensemble.combine import open_results
from ensemble.scenes.top import fits as top_fit
from ensemble.spec import parse
from tests.conftest import top_runfile


@pytest.fixture(scope="module")
def two_runs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("combine")
    first, second = folder / "rk4.nc", folder / "split2.nc"
    runner.run(parse(top_runfile(members=3, sweep={"c": [1e-4, 2e-4]}, parameters={"c": None}), "rk4.toml"), first,
               progress=False)
    runner.run(parse(top_runfile(method="split2", members=2, parameters={"c": 2e-4}) +
                     "[observe]\nnoise = { tilt = 0.001 }\n", "split2.toml"), second, progress=False)
    return first, second


def test_members_and_sweep_points_are_numbered_across_runs(two_runs):
    combined = open_results(two_runs)
    runs = [xr.load_dataset(p) for p in two_runs]
    assert combined.sizes["member"] == 8 and list(combined["member"].values) == list(range(8))
    assert list(combined["run_index"].values) == [0] * 6 + [1] * 2
    assert list(combined["member_in_run"].values) == [0, 1, 2, 3, 4, 5, 0, 1]
    assert list(combined["sweep_point"].values) == [0, 0, 0, 1, 1, 1, 2, 2]
    names = combined["method"].attrs["flag_meanings"].split()
    assert [names[i] for i in combined["method"].values] == ["rk4"] * 6 + ["split2"] * 2
    np.testing.assert_array_equal(combined["tilt"].values, np.concatenate([r["tilt"].values for r in runs]))
    assert list(combined["run_method"].values) == ["rk4", "split2"]
    assert list(combined["run_spec"].values) == [r.attrs["spec"] for r in runs]
    np.testing.assert_array_equal(combined["tilt_noise_stddev"].values, [0.0, 0.001])
    assert "observation_noise_stddev" not in combined["tilt"].attrs  # the runs differ: kept per run only


def test_groupby_and_fits_work_on_the_combined_dataset(two_runs):
    """groupby needs no dask; the fits over the combined noise-free members equal each run's own fits."""
    combined = open_results([two_runs[0], two_runs[0]])
    by_c = combined["tilt0"].groupby(combined["c"]).mean()
    run = xr.load_dataset(two_runs[0])
    np.testing.assert_allclose(by_c.values, run["tilt0"].groupby(run["c"]).mean().values, rtol=1e-15)
    together, alone = top_fit.tilt_decay(combined), top_fit.tilt_decay(run)
    np.testing.assert_array_equal(together["rate"].values, np.concatenate([alone["rate"].values] * 2))


def test_results_of_different_scenes_are_refused(two_runs, tmp_path):
    chain = tmp_path / "chain.nc"
    runner.run(parse('scene = "chain"\nmethod = "verlet"\ndt = 0.01\nt_end = 1.0\nsave_dt = 0.1\nmembers = 2\n'
                     'seed = 1\n[parameters]\nn = 2\nm = 1.0\nk = 1.0\nx0 = 0.1\n'), chain, progress=False)
    with pytest.raises(ValueError, match=r"results of one scene can be combined; these are of \['chain', 'top'\]"):
        open_results([two_runs[0], chain])

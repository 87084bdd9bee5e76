"""The Python API (ensemble.run, ensemble.open, ensemble.fit): the same bits as the command line, from a path,
TOML text or a dict; results in memory or on disk; the same one-line errors, raised."""
from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

import ensemble
from ensemble import api, cli
from ensemble.spec import SpecError

RUNS = Path(__file__).resolve().parent.parent / "runs"
TWO_MASS = (RUNS / "two_mass.toml").read_text().replace("members = 16", "members = 3")


def same_bits(a: xr.Dataset, b: xr.Dataset) -> None:
    assert set(a.data_vars) == set(b.data_vars)
    for name in a.data_vars:
        np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)


def test_run_gives_the_command_lines_bits_from_a_path_text_or_dict(tmp_path, monkeypatch):
    path = tmp_path / "two_mass.toml"
    path.write_text(TWO_MASS)
    assert cli.main(["run", str(path), "-o", str(tmp_path / "cli.nc"), "--quiet"]) == 0
    by_cli = xr.load_dataset(tmp_path / "cli.nc")
    monkeypatch.setattr(api.tempfile, "tempdir", str(tmp_path / "scratch"))
    (tmp_path / "scratch").mkdir()
    from_path = ensemble.run(path, progress=False)
    from_text = ensemble.run(TWO_MASS, progress=False)
    as_dict = tomllib.loads(TWO_MASS)
    as_dict["parameters"]["k"] = np.float64(1.0)  # numpy numbers, as a notebook makes them
    from_dict = ensemble.run(as_dict, progress=False)
    for ds in (from_path, from_text, from_dict):
        same_bits(by_cli, ds)
    assert not list((tmp_path / "scratch").iterdir())  # small results come back in memory; no file is left
    assert from_dict.attrs["history"].endswith("ensemble.run(a dict)")
    assert tomllib.loads(from_dict.attrs["spec"]) == tomllib.loads(TWO_MASS)  # its provenance parses again


def test_run_writes_the_output_it_is_given_and_refuses_what_the_command_refuses(tmp_path):
    out = tmp_path / "deep" / "two_mass.nc"
    ds = ensemble.run(TWO_MASS, out, progress=False)
    assert out.is_file() and ds.sizes["member"] == 3
    ds.close()
    with pytest.raises(ensemble.EnsembleError, match=r"two_mass.nc: exists; use --force to replace it"):
        ensemble.run(TWO_MASS, out, progress=False)
    with pytest.raises(SpecError, match=r"^parameters.lamda1: unknown key"):
        ensemble.run(TWO_MASS.replace("k = 1.0 ", "lamda1 = 1.0 "), tmp_path / "bad.nc")
    with pytest.raises(ensemble.EnsembleError, match=r"^chunk: must be >= 1, got 0"):
        ensemble.run(TWO_MASS, tmp_path / "chunk.nc", chunk=0)
    with pytest.raises(SpecError, match=r"^run: the dict holds a value TOML cannot write"):
        ensemble.run({**tomllib.loads(TWO_MASS), "seed": object()})
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["deep", "two_mass.nc"]


def test_a_large_result_is_opened_lazily_from_its_temporary_file(tmp_path, monkeypatch):
    monkeypatch.setattr(api, "IN_MEMORY_BYTES", 0)
    monkeypatch.setattr(api.tempfile, "tempdir", str(tmp_path))
    ds = ensemble.run(TWO_MASS, progress=False)
    (folder,) = tmp_path.iterdir()
    assert ds.encoding["source"] == str(folder / "result.nc") and ds["x"].shape == (3, 1001, 2)


def test_open_and_fit(tmp_path):
    first = tmp_path / "a.nc"
    ensemble.run(TWO_MASS, first, progress=False).close()
    ensemble.run(TWO_MASS.replace("seed = 1", "seed = 2"), tmp_path / "b.nc", progress=False).close()
    one = ensemble.open(first)
    both = ensemble.open(str(tmp_path / "*.nc"))
    assert one.sizes["member"] == 3 and both.sizes["member"] == 6 and list(both["run_path"].values) == [
        str(tmp_path / "a.nc"), str(tmp_path / "b.nc")]
    fits = ensemble.fit(one)
    from_path = ensemble.fit(first)
    same_bits(fits, from_path)
    np.testing.assert_allclose(fits["frequency"], np.broadcast_to([1.0, np.sqrt(3.0)], (3, 2)), rtol=1e-6)
    foreign = tmp_path / "foreign.nc"
    xr.Dataset({"x": ("time", np.arange(3.0))}).to_netcdf(foreign)
    with pytest.raises(api.NotAResult, match="is not a result of `ensemble run`"):
        ensemble.open(foreign)
    with pytest.raises(api.NotAResult, match="no such results"):
        ensemble.open(str(tmp_path / "none*.nc"))
    with pytest.raises(ensemble.EnsembleError, match="is not a result of `ensemble run`"):
        ensemble.fit(xr.load_dataset(foreign))

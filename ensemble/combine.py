"""Several results as one dataset: members numbered across runs, each run's provenance kept.

`xarray.open_mfdataset` is not the tool for this: it needs dask, its default
combine fails on results, and its nested combine repeats member ids and keeps
only the first file's attributes.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import xarray as xr

from .errors import EnsembleError


class CombineError(EnsembleError, ValueError):
    """Results that cannot be combined: one line naming the file or what differs."""


#: Global attributes kept per run, as variables over `run`.
RUN_ATTRIBUTES = ("title", "history", "source", "method", "spec", "seed", "draws", "members_written",
                  "members_per_sweep_point", "sweep_axes", "scene_sources_sha256", "engine_sha256", "compile_target")


def open_results(paths) -> xr.Dataset:
    """Results of `ensemble run` (same scene) concatenated over `member`, loaded in memory.

    Members get ids 0 .. N-1 across all runs, and sweep points are numbered
    across runs too. Per member, `run_index` is the run (file) it came from,
    `member_in_run` and `sweep_point_in_run` its ids there, `method` its
    method (flags, as in a run that sweeps it) and `dt` its step. Per run
    (dimension `run`): `run_path`, the run's global attributes in
    RUN_ATTRIBUTES as `run_<name>`, and each noisy variable's
    `<name>_noise_stddev`; the attribute `observation_noise_stddev` stays on a
    variable only when every run has the same noise. Variables saved by some
    runs only are NaN for the others; differing time grids are joined (NaN
    where a run has no sample). Raises CombineError for results of different
    scenes or a file that cannot be read.
    """
    paths = [Path(p) for p in paths]
    runs = [_loaded(p) for p in paths]
    scenes = {ds.attrs.get("scene") for ds in runs}
    if len(scenes) != 1 or None in scenes:
        raise CombineError(f"results of one scene can be combined; these are of {sorted(map(str, scenes))}")
    names = list(dict.fromkeys(m for ds in runs for m in _methods(ds)))
    noisy = {name for ds in runs for name in ds.data_vars if "observation_noise_stddev" in ds[name].attrs}
    first_points = np.cumsum([0] + [int(ds["sweep_point"].max()) + 1 for ds in runs[:-1]])
    parts = [_per_member(ds, index, names, first) for index, (ds, first) in enumerate(zip(runs, first_points))]
    out = xr.concat(parts, dim="member", data_vars="all", coords="different", compat="equals", join="outer",
                    combine_attrs="drop_conflicts", fill_value=np.nan)
    out = out.assign_coords(member=np.arange(out.sizes["member"], dtype=np.int32))
    out["method"] = out["method"].astype(np.int8)
    out["method"].attrs = {"long_name": "integration method", "flag_values": np.arange(len(names), dtype=np.int8),
                           "flag_meanings": " ".join(names)}
    out = out.assign_coords(run=("run", np.arange(len(runs), dtype=np.int32), {"long_name": "run (file) index"}))
    out["run_path"] = ("run", np.array([str(p) for p in paths]))
    for key in RUN_ATTRIBUTES:
        out[f"run_{key}"] = ("run", np.array([ds.attrs.get(key, "") for ds in runs]))
    for name in sorted(noisy):
        sigma = np.array([float(ds[name].attrs.get("observation_noise_stddev", 0.0)) if name in ds else np.nan
                          for ds in runs])
        out[f"{name}_noise_stddev"] = ("run", sigma, {"long_name": f"observation noise stddev of {name}, per run"})
        if np.all(sigma == sigma[0]):
            out[name].attrs["observation_noise_stddev"] = sigma[0]
        else:
            out[name].attrs.pop("observation_noise_stddev", None)
    axes = dict.fromkeys(axis for ds in runs for axis in ds.attrs.get("sweep_axes", "").split())
    out.attrs = {**{k: v for k, v in runs[0].attrs.items() if k not in RUN_ATTRIBUTES and k != "dt"},
                 "title": f"{len(runs)} ensemble {scenes.pop()} runs combined", "method": " ".join(names),
                 "sweep_axes": " ".join(axes), "source": _shared_source(runs)}
    return out


def _loaded(path: Path) -> xr.Dataset:
    from .zarr_store import xarray_source

    source, options = xarray_source(path)
    try:
        return xr.load_dataset(source, **options)
    except (OSError, ValueError, RuntimeError) as e:
        said = str(e).splitlines()[0] if str(e) else repr(e)
        raise CombineError(f"{path}: cannot be read as a result ({said})") from None


def _shared_source(runs: list[xr.Dataset]) -> str:
    """The runs' `source` (ensemble and its version) when they share it, else a note that run_source has each."""
    sources = {ds.attrs.get("source", "") for ds in runs}
    return sources.pop() if len(sources) == 1 else "ensemble, several versions (run_source has each run's)"


def _methods(ds: xr.Dataset) -> list[str]:
    if "method" in ds.variables:
        return ds["method"].attrs["flag_meanings"].split()
    return ds.attrs["method"].split()


def _per_member(ds: xr.Dataset, index: int, names: list[str], first_point: int) -> xr.Dataset:
    """One run's members with run_index, member_in_run, method (index into names) and dt as variables over
    member, and sweep points numbered from first_point (sweep_point_in_run keeps the run's own)."""
    n = ds.sizes["member"]
    own = _methods(ds)
    methods = ds["method"].values.astype(int) if "method" in ds.variables else np.zeros(n, dtype=int)
    ds = ds.drop_vars("method", errors="ignore")
    ds = ds.assign(run_index=("member", np.full(n, index, dtype=np.int32)),
                   member_in_run=("member", ds["member"].values.astype(np.int32)),
                   sweep_point_in_run=("member", ds["sweep_point"].values.astype(np.int32)),
                   sweep_point=("member", ds["sweep_point"].values.astype(np.int32) + first_point),
                   method=("member", np.array([names.index(own[m]) for m in methods], dtype=float)))
    if "dt" not in ds.variables:
        ds["dt"] = ("member", np.full(n, float(ds.attrs.get("dt", np.nan))), {"units": "s",
                                                                              "long_name": "integration step"})
    ds["run_index"].attrs = {"long_name": "index along run of the run (file) the member came from"}
    ds["member_in_run"].attrs = {"long_name": "the member's id in its run"}
    return ds

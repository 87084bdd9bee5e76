"""The Python API, for notebooks and scripts: run a run file, open results, fit them.

    import ensemble
    ds = ensemble.run("runs/aerobie.toml")     # a run file's path, its TOML text, or a dict
    fits = ensemble.fit(ds)                    # the scene's fit: what was measured against theory
    ds = ensemble.open("results/*.nc")         # one result, or several as one dataset

Each gives the bits `ensemble run` and `ensemble fit` give, and raises an EnsembleError with their one-line
message where they exit 2.
"""
from __future__ import annotations

import atexit
import glob
import shutil
import tempfile
import warnings
from pathlib import Path

import numpy as np
import xarray as xr

from .errors import EXIT_BAD_INPUT, EnsembleError
from .places import is_remote, place

IN_MEMORY_BYTES = 2**30  # a result written to a temporary file is returned in memory up to this size


class NotAResult(EnsembleError, ValueError):
    """A file that is not a result of `ensemble run`, or a dataset without one's attributes."""


def run(spec, output=None, *, chunk: int | None = None, progress: bool = True, force: bool = False,
        resume: bool = False, device: str | None = None, precision: str | None = None,
        values: dict | None = None) -> xr.Dataset:
    """Integrate every member of a run and return its dataset.

    spec: a run file's path (a Path, or a str ending in .toml), run-file TOML text, or the same as a dict.
    output: the NetCDF file (or Zarr store, OUT.zarr) to write (its folder is made). None writes a temporary
    file: a result of at most IN_MEMORY_BYTES comes back in memory and the file is deleted; a larger one is opened
    lazily from the file, which is deleted when Python exits. chunk, force, resume and device are `ensemble
    run`'s options.
    values: parameters given member by member, name -> an array over the run's members (or over a sweep
    point's, each point taking the same), one value or one row (per site or spring) a member: start states you
    computed, say. They replace what the run file says; the result's `parameters_given` attribute names them.
    The progress bar is a notebook widget in Jupyter (with ipywidgets) and text elsewhere.
    """
    from . import preflight
    from .runner import run as run_spec

    if chunk is not None and (isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer))):
        raise preflight.RunRefused(f"chunk: a whole number of members, not {chunk!r}")
    spec, runfile, described = _spec(spec)
    if values:
        from .spec import with_values

        spec = with_values(spec, values)
    if output is not None and (url := preflight.url_problem(str(output))):
        raise preflight.RunRefused(url)
    folder = Path(tempfile.mkdtemp(prefix="ensemble-")) if output is None else None
    out = folder / "result.nc" if folder else place(output)
    spec, rounded, problem = preflight.check(spec, out, runfile, device=device, chunk=chunk, force=force,
                                             resume=resume, precision=precision)
    if rounded != chunk:
        warnings.warn(f"chunk {chunk} is rounded up to {rounded}, whole kernel blocks", stacklevel=2)
        chunk = rounded
    made = []
    try:
        if problem:
            raise preflight.RunRefused(problem)
        made = preflight.make_folder(out.parent)
        try:
            with preflight.OutputLock(out):
                run_spec(spec, out, chunk=chunk, progress=progress, force=force, resume=resume,
                         command=f"ensemble.run({described})")
        except preflight.OutputLocked:
            raise preflight.RunRefused(f"{out}: another run is writing it now; wait for it or choose another "
                                       f"output") from None
        except EnsembleError as e:
            if e.exit_status == EXIT_BAD_INPUT:  # nothing run or written: nor a folder made for it
                preflight.remove_empty(made)
            raise
        if folder is None:  # the user's output: a NetCDF file or a Zarr store
            return open(out)  # ensemble.open (below), not the builtin
        if out.stat().st_size <= IN_MEMORY_BYTES:
            return xr.load_dataset(out, engine="netcdf4")
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
        folder = None  # kept while the lazily opened dataset may read it
        return xr.open_dataset(out, engine="netcdf4")
    finally:
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


def _spec(given):
    """(Spec, the run file's Path or None, how the history names it) of a path, TOML text or dict."""
    from .spec import SpecError, load, parse

    if isinstance(given, dict):
        import tomli_w

        try:
            text = tomli_w.dumps(_plain(given))
        except TypeError as e:
            raise SpecError("run", f"the dict holds a value TOML cannot write ({e})") from None
        return parse(text), None, "a dict"
    if isinstance(given, Path) or (isinstance(given, str) and "\n" not in given):  # one line holds no run file
        if not Path(given).is_file():
            raise SpecError("run file", f"{given}: no such file")
        return load(given), Path(given), repr(str(given))
    if isinstance(given, str):
        return parse(given), None, "TOML text"
    raise TypeError(f"spec: a run file's path, TOML text or a dict, not {type(given).__name__}")


def _plain(value):
    """numpy scalars and arrays in a run given as a dict, as Python's own numbers and lists."""
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(item) for item in value]
    return value.item() if isinstance(value, np.generic) else value


def open(paths) -> xr.Dataset:  # noqa: A001 (ensemble.open, as xarray.open_dataset)
    """Results of `ensemble run`: one file (a str or Path), opened lazily; several (a list, or a glob pattern
    such as "results/sweep_*.nc"), loaded and combined over `member` (ensemble.combine.open_results)."""
    from .combine import open_results
    from .zarr_store import xarray_source

    if isinstance(paths, (str, Path)) or is_remote(paths):
        found = sorted(glob.glob(str(paths))) if glob.has_magic(str(paths)) else [paths]
    else:
        found = list(paths)
    if not found:
        raise NotAResult(f"{paths}: no such results")
    if len(found) > 1:
        return open_results(found)
    source, options = xarray_source(found[0])
    try:
        ds = xr.open_dataset(source, **options)
    except (OSError, ValueError) as e:
        raise NotAResult(f"{found[0]}: {str(e).splitlines()[0]}") from None
    problem = not_a_result(ds)
    if problem:
        ds.close()
        raise NotAResult(f"{found[0]} {problem}")
    return ds


def not_a_result(ds: xr.Dataset) -> str | None:
    """Why a dataset is not a result to fit (None if it is): not written by ensemble, or no members."""
    if not str(ds.attrs.get("source", "")).startswith("ensemble") or "member" not in ds.dims:
        return "is not a result of `ensemble run` (no `source` attribute of ensemble's, or no member dimension)"
    if ds.sizes["member"] == 0:
        return "has no members to fit"
    return None


def fit(result) -> xr.Dataset:
    """The scene's fit of a result (a dataset, or a path ensemble.open takes): per member, each fitted quantity
    with its `_stderr`, `_theory`, `_method` (what the run's method shows) and `z`, and the sweep axes. A top
    fits its tilt decay, a chain its normal modes, a body its growth, wobble and flip; a scene of your own its
    `fit(ds)`. Raises FitError when the result cannot be fitted."""
    from .fitting import FitError
    from .scenes import of_result

    ds = open(result) if isinstance(result, (str, Path, list, tuple)) else result
    if not isinstance(ds, xr.Dataset):
        raise NotAResult(f"ensemble.fit takes a result (an xarray.Dataset, a path, a list of paths or a glob), not "
                         f"{type(result).__name__}")
    problem = not_a_result(ds)
    if problem:
        raise NotAResult(f"the dataset {problem}")
    scene = of_result(ds.attrs)
    if scene is None or not hasattr(scene, "fit"):
        raise FitError(f"no fit for the scene {ds.attrs.get('scene')!r} of this result (a scene of your own "
                       f"gives one as fit(ds))")
    try:
        fits = scene.fit(ds.load())
    except EnsembleError:
        raise
    except KeyError as e:
        raise FitError(f"the result has no variable {e}, which a {ds.attrs.get('scene')} result has") from None
    except Exception as e:  # noqa: BLE001 (a scene's own fit: one line that says whose it is)
        raise FitError(f"the {ds.attrs.get('scene')} scene's fit(ds) raised {type(e).__name__}: {e}") from None
    if not isinstance(fits, xr.Dataset):
        raise FitError(f"the {ds.attrs.get('scene')} scene's fit(ds) returned a {type(fits).__name__}, not an "
                       f"xarray.Dataset over member")
    if "member" in fits.dims and "sweep_point" not in fits.coords:  # a scene's own fit: its rows per sweep point
        fits = fits.assign_coords(sweep_point=ds["sweep_point"])
        fits.attrs.setdefault("sweep_axes", ds.attrs.get("sweep_axes", ""))
    for axis in ds.attrs.get("sweep_axes", "").split():
        fits[axis] = ds[axis]
    if "run_index" in ds and ds.sizes.get("run", 1) > 1:  # combined results: each sweep point is of one run
        fits["run_index"] = ds["run_index"]
    return fits

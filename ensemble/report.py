"""The analysis commands (`ensemble fit`, `ensemble stability`, `ensemble work-precision`): per-sweep-point tables
against theory, the fits written beside the result, the charts (ensemble.charts) on request.

The tables and --check need only the core install; the charts need matplotlib (the `plot` extra).
"""
from __future__ import annotations

import os
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from .api import not_a_result
from .errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_OK
from .fitting import FIT_TITLES, RTOL, Z_TOLERANCE, fitted_values, has_noise
from .places import is_remote


@dataclass(frozen=True)
class Row:
    """One sweep point (and mode): means over its fitted members.

    Members may each have their own theory (a disordered chain), so the
    comparison is the mean of each member's miss (fitted - its reference).
    """

    label: str
    mean: float  # mean fitted value
    theory: float  # mean physics prediction
    method: float  # mean prediction of the run's method
    miss: float  # mean of fitted - reference over members
    error: float  # standard error of miss
    members: int
    failed: int
    against: str = "theory"  # or "method": what miss, z and pass compare with
    excited: bool = True  # False: the run gave this row nothing to measure (a chain mode its start left silent)
    noisy: bool = True  # the result has observation noise: z is compared with N(0, 1)
    rtol: float = RTOL  # the relative miss that passes


    @property
    def reference(self) -> float:
        return self.method if self.against == "method" else self.theory

    @property
    def z(self) -> float:
        """miss / error; NaN without noise, where the error is a fit's residual, not a distribution's width."""
        if not self.noisy:
            return np.nan
        return self.miss / self.error if self.error > 0 else np.inf * np.sign(self.miss)

    @property
    def result(self) -> str:
        if self.members == 0:
            return "not excited" if not self.excited else "none fitted: FAIL"
        return "pass" if self.passed else "FAIL"

    @property
    def checked(self) -> bool:
        """What --check requires: a row the run excited passes; one it did not excite is left out."""
        return self.passed or not self.excited

    @property
    def passed(self) -> bool:
        close = abs(self.miss) <= self.rtol * abs(self.reference)
        return bool(self.members > 0 and (close or (self.noisy and abs(self.z) <= Z_TOLERANCE)))


def mean_with_error(values: np.ndarray, stderr: np.ndarray) -> tuple[float, float]:
    """Mean of member values and its standard error: the larger of their scatter and the fits' own errors."""
    n = values.size
    if n == 0:
        return np.nan, np.nan
    mean = float(values.mean())
    propagated = float(np.sqrt(np.sum(stderr**2))) / n
    scatter = float(values.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0
    return mean, max(propagated, scatter)


def rows(fits: xr.Dataset, value: str, label_of, against: str = "theory", noisy: bool = True) -> list[Row]:
    """One row per sweep point (and per mode, for chains) of a fit dataset; `noisy`: the result has observation
    noise. A fitted value without `<value>_stderr` has its members' scatter alone as its error.

    label_of(selection, sweep point or None, mode number or None) names a row.
    """
    out = []
    points = np.unique(fits["sweep_point"].values) if "sweep_point" in fits.coords else [None]
    modes = fits["mode"].values if "mode" in fits[value].dims else [None]
    rtol = float(fits[value].attrs.get("check_rtol", RTOL))
    for point in points:
        chosen = fits if point is None else fits.isel(member=np.flatnonzero(fits["sweep_point"].values == point))
        for mode in modes:
            sel = chosen if mode is None else chosen.sel(mode=mode)
            v = sel[value].values
            e = sel[f"{value}_stderr"].values if f"{value}_stderr" in sel else np.zeros(v.shape)
            theory = sel[f"{value}_theory"].values
            method = sel[f"{value}_method"].values if f"{value}_method" in sel else np.full(v.shape, np.nan)
            ok = np.isfinite(v) & np.isfinite(e)
            miss, error = mean_with_error((v - (method if against == "method" else theory))[ok], e[ok])
            over = ok if ok.any() else np.ones(v.shape, dtype=bool)  # the same members in every column
            excited = bool(np.any(sel["excited"].values)) if "excited" in sel else True
            out.append(Row(label_of(sel, point, mode), float(np.mean(v[ok])) if ok.any() else np.nan,
                           float(np.mean(theory[over])), float(np.mean(method[over])), miss, error,
                           int(ok.sum()), int((~ok).sum()), against, excited, noisy, rtol))
    return out


def point_label(sel) -> str:
    """The sweep point of a selection of members, as "axis = value, ..." ("" without sweep axes).

    A swept method is named (the dataset stores it as flags); in combined results, the run (file) it came from.
    """
    parts = [f"run {int(sel['run_index'].values.flat[0])}"] if "run_index" in sel else []
    for axis in sel.attrs.get("sweep_axes", "").split():
        if axis not in sel:
            continue
        value = sel[axis].values[0]
        meanings = sel[axis].attrs.get("flag_meanings")
        if not meanings and np.isnan(value):
            continue  # a setting this point's method does not take (dt of dopri5, rtol of rk4)
        parts.append(f"{axis} = {meanings.split()[int(value)]}" if meanings else f"{axis} = {float(value):.4g}")
    return ", ".join(parts)


def print_table(title: str, rows_: list[Row], units: str) -> None:
    against = rows_[0].against if rows_ else "theory"
    noisy = rows_[0].noisy if rows_ else True
    rtol = rows_[0].rtol if rows_ else RTOL
    print(title)
    print(f"{'':<24} {'fitted mean':>13} {'theory':>13} {'method shows':>13} {'miss':>10} {'+-':>9} {'z':>9}"
          f"  members  result")
    for r in rows_:
        failed = f" ({r.failed} not fitted)" if r.failed else ""
        z = f"{r.z:>9.3g}" if noisy else f"{'-':>9}"
        print(f"{r.label:<24} {r.mean:>13.8g} {r.theory:>13.8g} {r.method:>13.8g} {r.miss:>10.2g} {r.error:>9.2g}"
              f" {z}  {r.members:>7}  {r.result}{failed}")
    what = "theory" if against == "theory" else "what the method shows"
    if noisy:
        rule = f"z = miss / error. pass: |z| <= {Z_TOLERANCE:g} or |miss| <= {rtol:g} relative"
    else:
        rule = f"noise-free: no z. pass: |miss| <= {rtol:g} relative"
    print(f"miss: mean over members of fitted - {what}, +- its standard error; {rule}. Units: {units}")


def label(sel, point, mode) -> str:
    """A table row's name: its sweep point (and mode), or "all members"."""
    where = point_label(sel) if point is not None else ""
    if mode is not None:
        return f"{where}, mode {mode}" if where else f"mode {mode}"
    return where or "all members"


def outputs(result: Path, name: str, charts: Path | None = None) -> tuple[Path, Path]:
    """Where a command writes its table (NetCDF, beside the result) and the stem of its charts (in `charts`,
    default beside the result): RESULT_<name>.nc and RESULT_<name>_<chart>.png."""
    stem = result.with_suffix("")
    return (stem.with_name(f"{stem.name}_{name}.nc"),
            (charts or result.parent) / f"{stem.name}_{name}")


def charts_problem(folder: Path | None) -> str | None:
    """Why the charts cannot go to `folder` (None if they can, or when no charts are asked for): checked before
    anything is written."""
    from .preflight import existing_folder

    if folder is None:
        return None
    existing = existing_folder(folder)
    if not existing.is_dir():
        return f"{existing} is not a folder"
    if not os.access(existing, os.W_OK):
        return f"cannot write in {existing} (permission denied)"
    return None


def cannot_write(folder: Path, error: OSError) -> None:
    """One line on stderr: a table or chart could not be written (the table printed above stands)."""
    print(f"ensemble: error: cannot write in {folder} ({error.strerror or error}); the table above stands",
          file=sys.stderr)


def load_result(path: Path, fit_function):
    """(dataset, fit_function(dataset)) of a result file; None after one line on stderr for bad input: a file
    that is not NetCDF or not a result of `ensemble run`, a result without members, or one that lacks a variable
    its scene's results have (a `scene` attribute that does not say what the file holds)."""
    from .zarr_store import xarray_source

    source, options = xarray_source(path)
    try:
        ds = xr.load_dataset(source, **options)
        problem = not_a_result(ds)
        if problem:
            raise ValueError(problem)
        return ds, fit_function(ds)
    except KeyError as e:
        print(f"ensemble: error: {path}: the result has no variable {e}, which a {ds.attrs.get('scene')} result has",
              file=sys.stderr)
        return None
    except (OSError, ValueError) as e:  # FitError is a ValueError
        print(f"ensemble: error: {path}: {str(e).splitlines()[0]}", file=sys.stderr)
        return None


def load_results(paths: list[Path], fit_function):
    """load_result of one path; of several, (their combination, fit_function of it) (ensemble.open), or None after
    one line on stderr."""
    if len(paths) == 1:
        return load_result(paths[0], fit_function)
    from .api import open as open_results
    from .errors import EnsembleError

    try:
        ds = open_results(paths)
        return ds, fit_function(ds)
    except EnsembleError as e:
        print(f"ensemble: error: {str(e).splitlines()[0]}", file=sys.stderr)
        return None


def fit_command(args) -> int:
    """`ensemble fit`: fit a result, print a table per fitted quantity, write the fits beside the result and, with
    --charts, the charts; the exit status (1: --check failed; 2: bad input, one line)."""
    from .api import fit

    loaded = load_results(args.results, fit)
    if loaded is None:
        return EXIT_BAD_INPUT
    ds, fits = loaded
    named = str(args.results[0]) + (f" and {len(args.results) - 1} more" if len(args.results) > 1 else "")
    noisy = has_noise(ds)
    if args.members and max(args.members) >= ds.sizes["member"]:
        print(f"ensemble: error: --members: {max(args.members)} is not in 0..{ds.sizes['member'] - 1}", file=sys.stderr)
        return EXIT_BAD_INPUT
    step = f"dt = {ds.attrs['dt']} s" if "dt" in ds.attrs else "dt per member"
    table = []
    for name in fitted_values(fits):
        if not np.isfinite(fits[name].values).any() and not np.isfinite(fits[f"{name}_theory"].values).any():
            continue  # a quantity this result does not have (a body's wobble, when every member is spun to grow)
        against = args.against if f"{name}_method" in fits else "theory"
        found = [r for r in rows(fits, name, label, against, noisy) if np.isfinite(r.theory)]
        table += found
        what = fits[name].attrs.get("long_name", name)
        print_table(f"{what} [{name}], {named} ({ds.attrs['method']}, {step})", found,
                    fits[name].attrs.get("units", ""))
    if fits.attrs.get("members_not_ok"):
        print(f"{fits.attrs['members_not_ok']} members did not run to the end (their status is not ok) and are left "
              f"out")
    if fits.attrs.get("members_failed"):
        print(f"{fits.attrs['members_failed']} members could not be fitted and are left out")
    if not table:
        print("no member could be fitted: nothing to compare with the theory")
    if len(args.results) > 1:
        print("runs:", ", ".join(f"{k} {path}" for k, path in enumerate(args.results)))
    _write(args.results[0], args.charts, fits, fits.attrs.get("fit", "fit"), "fits",
           lambda plt, stem: _fit_charts(plt, ds, fits, table, stem, args))
    return EXIT_CHECK_FAILED if args.check and not (table and all(r.checked for r in table)) else EXIT_OK


def _fit_charts(plt, ds, fits, table, stem, args) -> list[Path]:
    from . import charts
    from .scenes import of_result

    scene = of_result(ds.attrs)
    paths = []
    if hasattr(scene, "charts"):
        try:
            paths = list(scene.charts(plt, ds, fits, table, stem, args.members))
        except OSError:
            raise
        except Exception as e:  # noqa: BLE001 (a scene's own charts: one line, the other charts still drawn)
            print(f"ensemble: error: the {ds.attrs.get('scene')} scene's charts raised {type(e).__name__}: {e}",
                  file=sys.stderr)
    fit = fits.attrs.get("fit", "fit")
    title = FIT_TITLES.get(fit, fit.replace("_", " "))  # "tilt decay rate", not the file name's tilt_decay
    return [*paths, charts.draw_misses(plt, fits, stem, args.against, title, has_noise(ds))]


def _to_netcdf(table: xr.Dataset, out: Path) -> None:
    """table.to_netcdf(out), at a URL too (beside a result in an object store: written here, then put there)."""
    if not is_remote(out):
        return table.to_netcdf(out)
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        table.to_netcdf(Path(folder) / out.name)
        out.write_bytes((Path(folder) / out.name).read_bytes())


def _write(result: Path, charts: Path | None, table: xr.Dataset, name: str, what: str, draw) -> None:
    """Write `table` beside the result as RESULT_<name>.nc and, with --charts DIR (`charts`), draw(plt, stem)
    there."""
    out, stem = outputs(result, name, charts)
    try:
        _to_netcdf(table, out)
    except OSError as e:
        return cannot_write(out.parent, e)
    print(f"{what}: {out}")
    if charts is None:
        return None
    from .plotting import pyplot

    plt = pyplot()
    try:
        if plt is not None:
            charts.mkdir(parents=True, exist_ok=True)
            print("charts:", *[path for path in draw(plt, stem) if path is not None])
    except OSError as e:
        cannot_write(charts, e)


def stability_command(args) -> int:
    """`ensemble stability`: theoretical and measured limits per method and axis, the map beside the result, the
    charts with --charts; 1 with --check when a measured limit misses theory by more than LIMIT_RTOL."""
    from . import stability

    loaded = load_result(args.result, stability.stability_map)
    if loaded is None:
        return EXIT_BAD_INPUT
    ds, points = loaded
    limits = stability.stability_limits(points)
    print(f"stability of {args.result} ({ds.attrs['scene']}, {ds.sizes['t'] - 1} saved intervals)")
    stability.print_limits(limits, points)

    def draw(plt, stem):
        from . import charts

        return [charts.draw_stability_map(plt, points, limits, stem),
                charts.draw_energy_drift(plt, ds, points, args.drift_step, stem)]

    _write(args.result, args.charts, points, "stability", "map", draw)
    return EXIT_CHECK_FAILED if args.check and not all(stability.limit_agrees(r) for r in limits) else EXIT_OK


def work_precision_command(args) -> int:
    """`ensemble work-precision`: per method, its points and measured convergence order; the table beside the
    (first) result, the chart with --charts. Several results of one scene (a GPU run in float64 and in float32,
    say) are charted together, a line per method and result."""
    from . import fitting

    loaded = []
    for path in args.results:  # the first that cannot be read is the one line
        loaded.append(load_result(path, fitting.work_precision))
        if loaded[-1] is None:
            return EXIT_BAD_INPUT
    scenes = [ds.attrs["scene"] for ds, _ in loaded]
    for path, scene in zip(args.results, scenes):
        if scene != scenes[0]:
            print(f"ensemble: error: {path}: a {scene} result, charted with {args.results[0]}'s {scenes[0]}: "
                  f"work-precision compares runs of one scene", file=sys.stderr)
            return EXIT_BAD_INPUT
    table = fitting.combined_work_precision([t for _, t in loaded], [ds.attrs for ds, _ in loaded])
    for path, (ds, _) in zip(args.results, loaded):
        print(f"work against precision in {path} ({ds.attrs['scene']}, t_end = {ds.attrs['t_end']} s, "
              f"{ds.attrs.get('precision', 'float64')} on {ds.attrs.get('device', 'cpu')})")
        if "seconds_per_step" not in ds:
            print("  no timing in this result ([measure] timing = true): its cost panel is empty")
    print_work_precision(table)
    ds = loaded[0][0]

    def draw(plt, stem):
        from . import charts

        return [charts.draw_work_precision(plt, table, stem, f"{ds.attrs['scene']}: {ds.attrs.get('title', '')}")]

    _write(args.results[0], args.charts, table, "work_precision", "table", draw)
    return EXIT_OK


def print_work_precision(table: xr.Dataset) -> None:
    """Per method: its nominal and measured order, and its points' dt, rtol, error, steps, rhs evaluations and
    kernel seconds per member."""
    from .fitting import convergence_order
    from .methods import METHODS

    for line in dict.fromkeys(table["line"].values):
        chosen = np.flatnonzero(table["line"].values == line)
        m = METHODS[str(table["method"].values[chosen[0]])]
        order, used = convergence_order(table, line)
        against = "mean step" if m.adaptive else "dt"
        print(f"{line}: nominal order {m.order}, measured {order:.3f} "
              f"(slope of log error on log {against} over {used} points in the asymptotic range)")
        print(f"  {'dt (s)':>10} {'rtol':>9} {'error':>10} {'steps':>10} {'rhs evals':>10} {'s/member':>10}")
        for i in chosen:
            row = {name: table[name].values[i] for name in ("dt", "rtol", "error", "steps", "rhs_evals", "seconds")}
            print(f"  {row['dt']:>10.3g} {row['rtol']:>9.2g} {row['error']:>10.3g} {row['steps']:>10.0f} "
                  f"{row['rhs_evals']:>10.0f} {row['seconds']:>10.3g}")

"""What the analysis scripts share: the command line, per-sweep-point tables against theory, charts.

Plotting needs matplotlib (the `plot` extra); the tables do not.
"""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import xarray as xr

from .arguments import OneLineParser
from .errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_OK

Z_TOLERANCE = 5.0  # a sweep point passes when its mean is within this many standard errors of theory...
RTOL = 1e-6  # ...or within this relative difference (noise-free runs have tiny standard errors)


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

    @property
    def reference(self) -> float:
        return self.method if self.against == "method" else self.theory

    @property
    def z(self) -> float:
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
        close = abs(self.miss) <= RTOL * abs(self.reference)
        return bool(self.members > 0 and (close or abs(self.z) <= Z_TOLERANCE))


def mean_with_error(values: np.ndarray, stderr: np.ndarray) -> tuple[float, float]:
    """Mean of member values and its standard error: the larger of their scatter and the fits' own errors."""
    n = values.size
    if n == 0:
        return np.nan, np.nan
    mean = float(values.mean())
    propagated = float(np.sqrt(np.sum(stderr**2))) / n
    scatter = float(values.std(ddof=1) / np.sqrt(n)) if n > 1 else 0.0
    return mean, max(propagated, scatter)


def rows(fits: xr.Dataset, value: str, label_of, against: str = "theory") -> list[Row]:
    """One row per sweep point (and per mode, for chains) of a fit dataset.

    label_of(selection, sweep point or None, mode number or None) names a row.
    """
    out = []
    points = np.unique(fits["sweep_point"].values) if "sweep_point" in fits.coords else [None]
    modes = fits["mode"].values if "mode" in fits[value].dims else [None]
    for point in points:
        chosen = fits if point is None else fits.isel(member=np.flatnonzero(fits["sweep_point"].values == point))
        for mode in modes:
            sel = chosen if mode is None else chosen.sel(mode=mode)
            v, e = sel[value].values, sel[f"{value}_stderr"].values
            theory = sel[f"{value}_theory"].values
            method = sel[f"{value}_method"].values if f"{value}_method" in sel else np.full(v.shape, np.nan)
            ok = np.isfinite(v) & np.isfinite(e)
            miss, error = mean_with_error((v - (method if against == "method" else theory))[ok], e[ok])
            over = ok if ok.any() else np.ones(v.shape, dtype=bool)  # the same members in every column
            excited = bool(np.any(sel["excited"].values)) if "excited" in sel else True
            out.append(Row(label_of(sel, point, mode), float(np.mean(v[ok])) if ok.any() else np.nan,
                           float(np.mean(theory[over])), float(np.mean(method[over])), miss, error,
                           int(ok.sum()), int((~ok).sum()), against, excited))
    return out


def point_label(sel) -> str:
    """The sweep point of a selection of members, as "axis = value, ..." ("" without sweep axes).

    A swept method is named (the dataset stores it as flags).
    """
    parts = []
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
    print(title)
    print(f"{'':<24} {'fitted mean':>13} {'theory':>13} {'method shows':>13} {'miss':>10} {'+-':>9} {'z':>9}"
          f"  members  result")
    for r in rows_:
        failed = f" ({r.failed} not fitted)" if r.failed else ""
        print(f"{r.label:<24} {r.mean:>13.8g} {r.theory:>13.8g} {r.method:>13.8g} {r.miss:>10.2g} {r.error:>9.2g}"
              f" {r.z:>9.3g}  {r.members:>7}  {r.result}{failed}")
    what = "theory" if against == "theory" else "what the method shows"
    print(f"miss: mean over members of fitted - {what}, +- its standard error; z = miss / error. "
          f"pass: |z| <= {Z_TOLERANCE:g} or |miss| <= {RTOL:g} relative. Units: {units}")


def outputs(result: Path, fit: str) -> tuple[Path, Path]:
    """Where a script writes its fits (NetCDF) and the stem of its charts, next to the result."""
    stem = result.with_suffix("")
    return stem.with_name(f"{stem.name}_{fit}.nc"), stem.with_name(f"{stem.name}_{fit}")


def parser(doc: str) -> argparse.ArgumentParser:
    """The options every analysis script takes: RESULT, --check and --against."""
    out = OneLineParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    out.add_argument("result", type=Path, help="a result file written by `ensemble run`")
    out.add_argument("--check", action="store_true", help="exit 1 when a fitted sweep point disagrees")
    out.add_argument("--against", choices=("theory", "method"), default="theory",
                     help="compare with the physics (default) or with what the run's method shows")
    return out


def run_script(args, fit_function, *, name: str, value, units: str, title: str, label, draw,
               validate=None) -> int:
    """Fit a result, print the table, write the fits and charts; the exit status of a script.

    value: the fitted variable, or several (value, units, title) triples, each
    tabled at the sweep points where it has a theory (one without
    `<value>_method` is compared with theory only). draw(plt, ds, fits, rows, stem) returns the paths of the
    script's own charts; the z histogram is added here. Bad input prints one
    line and returns 2.
    """
    loaded = load_result(args.result, fit_function, validate)
    if loaded is None:
        return EXIT_BAD_INPUT
    ds, fits = loaded
    for axis in ds.attrs.get("sweep_axes", "").split():
        fits[axis] = ds[axis]
    step = f"dt = {ds.attrs['dt']} s" if "dt" in ds.attrs else "dt per member"
    several = not isinstance(value, str)
    table = []
    for variable, variable_units, variable_title in value if several else [(value, units, title)]:
        if several and not np.isfinite(fits[variable].values).any():
            continue
        against = args.against if f"{variable}_method" in fits else "theory"
        found = rows(fits, variable, label, against)
        if several:  # leave out sweep points where this quantity does not apply
            found = [r for r in found if np.isfinite(r.theory)]
        table += found
        print_table(f"{variable_title} of {args.result} ({ds.attrs['method']}, {step})", found, variable_units)
    if fits.attrs.get("members_not_ok"):
        print(f"{fits.attrs['members_not_ok']} members did not run to the end (their status is not ok) and are left "
              f"out")
    if fits.attrs["members_failed"]:
        print(f"{fits.attrs['members_failed']} members could not be fitted and are left out")
    if not table:
        print("no member could be fitted: nothing to compare with the theory")
    out, stem = outputs(args.result, name)
    try:
        fits.to_netcdf(out)
        print(f"fits: {out}")
        plt = pyplot()
        if plt is not None:
            paths = draw(plt, ds, fits, table, stem)
            paths.append(draw_misses(plt, fits, stem, args.against, title))
            print("charts:", *paths)
    except OSError as e:
        cannot_write(out.parent, e)
    return EXIT_CHECK_FAILED if args.check and not (table and all(r.checked for r in table)) else EXIT_OK


def cannot_write(folder: Path, error: OSError) -> None:
    """One line on stderr: the fits and charts could not be written (the table printed above stands)."""
    print(f"error: cannot write the fits and charts in {folder} ({error.strerror or error}); the table above "
          f"stands", file=sys.stderr)


def load_result(path: Path, fit_function, validate=None):
    """(dataset, fit_function(dataset)) of a result file; None after one line on stderr for bad input: a file
    that is not NetCDF or not a result of `ensemble run`, a result without members, or one that lacks a variable
    its scene's results have (a `scene` attribute that does not say what the file holds)."""
    try:
        ds = xr.load_dataset(path, engine="netcdf4")
        problem = _not_a_result(ds)
        if problem:
            raise ValueError(problem)
        if validate:
            validate(ds)
        return ds, fit_function(ds)
    except KeyError as e:
        print(f"error: {path}: the result has no variable {e}, which a {ds.attrs.get('scene')} result has",
              file=sys.stderr)
        return None
    except (OSError, ValueError) as e:
        print(f"error: {path}: {str(e).splitlines()[0]}", file=sys.stderr)
        return None


def _not_a_result(ds: xr.Dataset) -> str | None:
    if not str(ds.attrs.get("source", "")).startswith("ensemble") or "member" not in ds.dims:
        return "is not a result of `ensemble run` (no `source` attribute of ensemble's, or no member dimension)"
    if ds.sizes["member"] == 0:
        return "has no members to fit"
    return None


def pyplot():
    """matplotlib.pyplot, drawing to files; None, after one line on stderr, without the `plot` extra (the tables
    and --check need no matplotlib)."""
    try:
        import matplotlib
    except ImportError:
        print('no charts: they need matplotlib (pip install "ensemble[plot]"); the table above stands',
              file=sys.stderr)
        return None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(plt, fig, stem: Path, chart: str = "") -> Path:
    """Write a chart as STEM_CHART.png (STEM.png without a chart name) and close it."""
    path = stem.with_name(f"{stem.name}_{chart}.png" if chart else f"{stem.name}.png")
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def save_against_theory(plt, stem: Path, chart: str, draw_fits, span, theory_label: str, xlabel: str, ylabel: str,
                        title: str) -> Path:
    """A chart of fitted values against theory: draw_fits(ax) draws the fits, then the line y = x over span."""
    fig, ax = plt.subplots(figsize=(5.5, 4.5), layout="constrained")
    draw_fits(ax)
    low, high = float(np.min(span)), float(np.max(span))
    if high - low <= 1e-6 * max(abs(low), abs(high)):  # one sweep point: give y = x a length around it
        pad = 0.05 * max(abs(low), abs(high)) or 1.0
        span = [low - pad, high + pad]
        ax.set_xlim(span)
        ax.set_ylim(span)
    ax.ticklabel_format(useOffset=False)  # an offset label makes a 1e-13 difference look like a gap
    ax.plot(span, span, "k--", lw=1, label=theory_label)
    ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
    ax.legend()
    return save(plt, fig, stem, chart)


def draw_misses(plt, fits: xr.Dataset, stem: Path, against: str, title: str) -> Path:
    """The chart of how fits miss their reference, RESULT_<fit>_z.png: z against N(0, 1) when the result has
    observation noise; without noise z has no distribution to follow (its error bar is the fit's own residual),
    so the relative miss (fitted / reference - 1) per member is drawn instead."""
    fig, ax = plt.subplots(figsize=(5.5, 4.5), layout="constrained")
    what = "theory" if against == "theory" else "what the method shows"
    if fits.attrs.get("observation_noise_stddev", 0.0) > 0:
        z_histogram(ax, fits["z" if against == "theory" else "z_method"].values.ravel(), "fits", what)
        ax.set_title(f"{title}: fitted against {what}")
    else:
        misses = [_relative_miss(fits, row_value, against) for row_value in _fitted_values(fits)]
        for (name, miss), marker in zip(misses, "ox^"):
            ax.plot(np.arange(miss.size), miss, marker, ms=3, mfc="none", label=name.replace("_", " "))
        ax.axhline(0.0, color="k", lw=0.5)
        ax.axhspan(-RTOL, RTOL, color="g", alpha=0.15, label=f"the check's {RTOL:g}")
        ax.set_xlabel("member (and mode)")
        ax.set_ylabel(f"fitted / {what} - 1")
        ax.set_title(f"{title}: relative miss (noise-free: no z)", fontsize=9)
        ax.legend(fontsize=8)
    return save(plt, fig, stem, "z")


def _fitted_values(fits: xr.Dataset) -> list[str]:
    """The fitted quantities of a fit dataset: variables with a _theory beside them."""
    return [name for name in fits.data_vars if f"{name}_theory" in fits and f"{name}_stderr" in fits]


def _relative_miss(fits: xr.Dataset, name: str, against: str) -> tuple[str, np.ndarray]:
    reference = fits[f"{name}_method" if against == "method" and f"{name}_method" in fits else f"{name}_theory"]
    with np.errstate(divide="ignore", invalid="ignore"):
        miss = (fits[name].values / reference.values - 1).ravel()
    return name, miss[np.isfinite(miss)]


Z_SPAN = 50.0  # z histograms show |z| up to this; larger values are counted at the edge, and the legend says so


def z_histogram(ax, z: np.ndarray, label: str, reference: str = "theory") -> None:
    """Histogram of z values as a density, with the N(0, 1) density over it."""
    z = z[np.isfinite(z)]
    span = min(max(4.0, float(np.nanmax(np.abs(z))) if z.size else 4.0), Z_SPAN)
    outside = int(np.sum(np.abs(z) > span))
    clipped = f", {outside} beyond +-{span:g} drawn at the edges" if outside else ""
    ax.hist(np.clip(z, -span, span), bins=40, range=(-span, span), density=True, alpha=0.6,
            label=f"{label} ({z.size}{clipped})")
    grid = np.linspace(-span, span, 400)
    ax.plot(grid, np.exp(-grid**2 / 2) / np.sqrt(2 * np.pi), "k-", label="N(0, 1)")
    ax.set_xlabel(f"z = (fitted - {reference}) / standard error")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)


"""Where methods fail: measured growth per step, and the limits that linear theory predicts.

Each scene linearizes its equations into motions a method amplifies by a
factor per step (see `axis_growth` and `step_growth` in the scene modules):
a chain's normal modes (frequency omega), a top's transverse rotation at the
body-frame precession rate Omega and its drag decays at rates c / lambda.
A stability axis is one such dimensionless step, h omega or h r; a method's
limit on it is the smallest step at which its factor exceeds 1.
"""
from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.optimize import brentq

from . import fitting
from .methods import METHODS
from .results import Status
from .scenes import of_result

#: A member counts as growing when its measured factor per step exceeds 1 by more than this.
GROWTH_TOLERANCE = 1e-3
_THEORY_SLACK = 1e-9  # a factor this close to 1 is neutral (rounding in the one-step map)


def theoretical_limit(growth, upper: float = 10.0, points: int = 20001) -> float:
    """Smallest x in (0, upper] with growth(x) > 1: 0 if growing from the start, inf if never, NaN if growth
    is NaN throughout (no limit on this axis alone).

    growth: vectorized factor per step along a stability axis. The first
    crossing is bracketed on a grid of `points` and refined with brentq.
    """
    x = np.linspace(0.0, upper, points)[1:]
    factor = growth(x)
    if np.isnan(factor).all():
        return np.nan
    over = factor > 1.0 + _THEORY_SLACK
    if not over.any():
        return np.inf
    first = int(np.argmax(over))
    if first == 0:
        return 0.0
    return brentq(lambda s: float(growth(np.array([s]))[0]) - 1.0 - _THEORY_SLACK / 2, x[first - 1], x[first],
                  xtol=1e-14)


def measured_limit(x: np.ndarray, growth: np.ndarray, failed: np.ndarray) -> tuple[float, float, float]:
    """Where measured growth first exceeds 1 + GROWTH_TOLERANCE along increasing x.

    Returns (limit, last stable x, first growing x): the limit interpolates
    linearly in growth between the two; (0, nan, x_min) when the smallest x
    already grows, (inf, x_max, nan) when none does. Members without a
    measured growth (NaN) count as growing if they failed, and are left out
    if not (a motion that a step takes exactly to zero).
    """
    x, growth, failed = (np.asarray(v)[np.isfinite(growth) | failed] for v in (x, growth, failed))
    order = np.argsort(x, kind="stable")
    x, growth = x[order].astype(float), growth[order].astype(float)
    grows = ~(growth <= 1.0 + GROWTH_TOLERANCE)
    if not grows.any():
        return np.inf, float(x[-1]), np.nan
    first = int(np.argmax(grows))
    if first == 0:
        return 0.0, np.nan, float(x[0])
    x0, x1, g0, g1 = x[first - 1], x[first], growth[first - 1], growth[first]
    target = 1.0 + GROWTH_TOLERANCE
    limit = x1 if not np.isfinite(g1) else x0 + (x1 - x0) * (target - g0) / (g1 - g0)
    return float(limit), float(x0), float(x1)


def member_steps(ds: xr.Dataset) -> np.ndarray:
    """The step h (s) of each member: dt for fixed-step methods, the mean accepted step for adaptive ones
    (time reached / steps accepted), NaN for the closed form."""
    methods, dt = fitting.member_settings(ds)
    reached = np.where(np.isnan(ds["failure_time"].values), float(ds.attrs["t_end"]), ds["failure_time"].values)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_step = reached / ds["steps_accepted"].values
    used = {name: METHODS[name] for name in set(methods)}
    adaptive = np.array([used[m].adaptive for m in methods])
    closed = np.array([used[m].closed_form for m in methods])
    return np.where(closed, np.nan, np.where(adaptive, mean_step, dt))


def stability_map(ds: xr.Dataset) -> xr.Dataset:
    """Each member of a result on its stability axis, with its measured and predicted growth per step.

    Returns over member: method, axis (the scene's STABILITY_AXES: which
    dimensionless step dominates the member), x (its value: h times the
    rate), growth (growth_per_step, measured), growth_theory (the scene's
    step_growth at the member's h) and status. Closed-form members are left
    out.
    """
    scene = of_result(ds.attrs)
    if scene is None:
        raise fitting.FitError("stability_map needs a result of `ensemble run`")
    if not scene.STABILITY_AXES:
        raise fitting.FitError(f"stability_map: scene {ds.attrs['scene']!r} declares no stability axes (a scene of "
                               f"your own: STABILITY_AXES, stability_axis, step_growth and axis_growth, see "
                               f"docs/scenes.md)")
    if "growth_per_step" not in ds:
        raise fitting.FitError("stability_map: the result has no growth_per_step; add `[measure] growth = true` to "
                           "its run file and run it again")
    methods, _ = fitting.member_settings(ds)
    h = member_steps(ds)
    keep = np.isfinite(h)
    values = {name: ds[name].values[keep] for name in scene.PARAMETERS if name in ds}
    constants = {name: ds.attrs[name] for name, p in scene.PARAMETERS.items() if p.constant and name in ds.attrs}
    axis, x = scene.stability_axis(values, constants, h[keep])
    theory = np.full(keep.sum(), np.nan)
    for method in dict.fromkeys(methods[keep]):
        chosen = methods[keep] == method
        theory[chosen] = scene.step_growth(METHODS[method], {k: v[chosen] for k, v in values.items()}, constants,
                                           h[keep][chosen])
    out = xr.Dataset(coords={"member": ds["member"].values[keep]})
    for name, data, units, long_name in (
            ("method", methods[keep], "", "integration method"),
            ("axis", axis, "", "stability axis: the dimensionless step that dominates the member"),
            ("x", x, "1", "the member's dimensionless step on its axis"),
            ("growth", ds["growth_per_step"].values[keep], "1", "measured growth factor per step"),
            ("growth_theory", theory, "1", "growth factor per step that linear theory predicts")):
        out[name] = ("member", data, {"units": units, "long_name": long_name} if units else {"long_name": long_name})
    out["status"] = ("member", ds["status"].values[keep], {"long_name": "how the member ended",
                                                          "flag_values": Status.flag_values(),
                                                          "flag_meanings": Status.flag_meanings()})
    out.attrs["scene"] = ds.attrs["scene"]
    if "scene_source" in ds.attrs:
        out.attrs["scene_source"] = ds.attrs["scene_source"]
    return out


def stability_limits(points: xr.Dataset) -> list[dict]:
    """Per method and stability axis of a stability_map: the theoretical and the measured limit.

    Each row: method, axis, theory (first x where the factor exceeds 1),
    measured, last_stable, first_growing (see measured_limit), members.
    Adaptive methods are left out: their step control chooses x.
    """
    scene = of_result(points.attrs)
    rows = []
    for name in dict.fromkeys(points["method"].values):
        method = METHODS[name]
        if method.adaptive:
            continue
        for axis in scene.STABILITY_AXES:
            chosen = (points["method"].values == name) & (points["axis"].values == axis)
            if not chosen.any():
                continue
            measured, stable, growing = measured_limit(points["x"].values[chosen], points["growth"].values[chosen],
                                                       points["status"].values[chosen] != Status.OK)
            rows.append(dict(method=name, axis=axis, members=int(chosen.sum()), measured=measured,
                             last_stable=stable, first_growing=growing,
                             theory=theoretical_limit(lambda s: scene.axis_growth(method, axis, s))))
    return rows


def energy_drift(ds: xr.Dataset) -> xr.DataArray:
    """|E(t) / E(0) - 1| over (member, t) for members whose energy the physics conserves; NaN elsewhere
    (see the scene's conserved_energy: a chain's saved energy, a top's kinetic energy without drag)."""
    scene = of_result(ds.attrs)
    if scene is None:
        raise fitting.FitError("energy_drift needs a result of `ensemble run`")
    try:
        energy = scene.conserved_energy(ds)
    except KeyError as e:
        raise fitting.FitError(f"energy_drift: the result lacks {e.args[0]} (save it in the run file)") from None
    with np.errstate(invalid="ignore", divide="ignore"):
        drift = np.abs(energy / energy[:, :1] - 1)
    return xr.DataArray(drift, dims=("member", "t"), coords={"member": ds["member"], "t": ds["t"]},
                        attrs={"units": "1", "long_name": "relative energy error |E / E(0) - 1|"})


LIMIT_RTOL = 0.02  # --check: measured limits within this of theory


def limit_agrees(row: dict) -> bool:
    """Measured and theoretical limit agree: both none, both zero, or within LIMIT_RTOL. A limit with no theory on
    its axis alone (a body's splitting: the limit depends on the moments) is not judged; the map's per-member
    growth_theory covers it."""
    measured, theory = row["measured"], row["theory"]
    if np.isnan(theory):
        return True
    if np.isinf(theory) or theory == 0:
        return measured == theory
    return abs(measured / theory - 1) <= LIMIT_RTOL


def print_limits(rows: list[dict], points: xr.Dataset) -> None:
    print(f"{'method':<17} {'axis':<12} {'theory':>8} {'measured':>9} {'stable..growing':>16} {'miss':>7} "
          f"{'members':>7}  agree")
    for r in rows:
        bracket = f"{r['last_stable']:.3g}..{r['first_growing']:.3g}"
        miss = (f"{r['measured'] / r['theory'] - 1:+.1%}" if np.isfinite(r["theory"]) and r["theory"] > 0
                else "")
        print(f"{r['method']:<17} {r['axis']:<12} {r['theory']:>8.4g} {r['measured']:>9.4g} {bracket:>16} "
              f"{miss:>7} {r['members']:>7}  {'n/a' if np.isnan(r['theory']) else 'yes' if limit_agrees(r) else 'NO'}")
    print(f"limit: the smallest dimensionless step at which growth per step exceeds 1 (measured: 1 + "
          f"{GROWTH_TOLERANCE:g}); inf: none, 0: grows at every step")
    for method in dict.fromkeys(points["method"].values):
        status = points["status"].values[points["method"].values == method]
        print(f"{method}: {np.sum(status == Status.BLEW_UP)} of {status.size} members blew up, "
              f"{np.sum(status == Status.STEP_SIZE_UNDERFLOW)} step size underflows")

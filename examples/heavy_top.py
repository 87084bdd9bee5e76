"""The heavy symmetric top on a fixed pivot, in the Euler-Poisson form: a scene of your own whose nutation turning
points are events (runs/heavy_top.toml).

The state is the body-frame angular velocity w (rad/s) and the body-frame components of the upward vertical,
g (a unit vector): no Euler angles, so the motion is not singular when the top stands upright (phi, below, is).
With moments lambda1 (transverse, about the pivot) and lambda3, and gravity's torque M g R (R: the pivot to the
centre of mass, along the symmetry axis e3):

    lambda1 w1' = (lambda1 - lambda3) w2 w3 + M g R g2,    lambda1 w2' = (lambda3 - lambda1) w3 w1 - M g R g1,
    w3' = 0,    g' = g x w.

The tilt theta of e3 from the vertical has u = cos(theta) = g3, and u' = g1 w2 - g2 w1 (EVENTS: `nutation`),
zero at the turning points of the nutation. Between them u moves between the two roots u1 < u2 of the cubic
u'^2 = f(u) = (1 - u^2)(alpha - beta u) - (b - a u)^2 (Goldstein, Classical Mechanics, 5.7; Brizard,
arXiv:0711.4064: u = u1 + (u2 - u1) sn^2), so the nutation period is 4 K(m) / sqrt(beta (u3 - u1)), m = (u2 -
u1) / (u3 - u1), u3 > 1 the cubic's third root.

A top released at tilt theta0 with spin w3 and no other motion starts at a turning point (u2 = cos theta0).

The precession angle phi, the azimuth of e3 about the vertical, enters nothing above: it is integrated beside
them, phi' = (b - a u) / (1 - u^2) = (w1 g1 + w2 g2) / (g1^2 + g2^2), for its mean rate, the advance of phi over
a nutation period over that period (`precession_rate`, by quadrature); a fast top's is M g R / (lambda3 w3). It is
undefined for a top exactly upright (g1 = g2 = 0), which `check` refuses.
"""
import numpy as np
from scipy.special import ellipk

from ensemble import Parameter

NAME = "heavy_top"

STATE = {"w1": ("rad s-1", "body-frame angular velocity about e1"),
         "w2": ("rad s-1", "body-frame angular velocity about e2"),
         "w3": ("rad s-1", "spin about the symmetry axis e3"),
         "g1": ("1", "upward vertical along e1"), "g2": ("1", "upward vertical along e2"),
         "g3": ("1", "upward vertical along e3: cos(tilt)"),
         "phi": ("rad", "precession angle: the azimuth of e3 about the vertical")}

PARAMETERS = {  # w10 .. g30 start the state; lambda1, lambda3 and MgR are the right-hand side's
    "lambda1": Parameter("kg m2", "moment about a transverse axis through the pivot"),
    "lambda3": Parameter("kg m2", "moment about the symmetry axis"),
    "MgR": Parameter("N m", "gravity's largest torque, M g R"),
    "w10": Parameter("rad s-1", "w1 at t = 0", default=0.0),
    "w20": Parameter("rad s-1", "w2 at t = 0", default=0.0),
    "w30": Parameter("rad s-1", "spin at t = 0"),
    "g10": Parameter("1", "g1 at t = 0", default=0.0),
    "g20": Parameter("1", "g2 at t = 0: sin(tilt0) for a top tilted about e1"),
    "g30": Parameter("1", "g3 at t = 0: cos(tilt0)"),
    "phi0": Parameter("rad", "precession angle at t = 0", default=0.0),
}

EVENTS = ("nutation",)


def rhs(t, w1, w2, w3, g1, g2, g3, phi, lambda1, lambda3, MgR):
    """(w', g', phi') of one member at time t (s)."""
    a = (lambda1 - lambda3) / lambda1
    return (a * w2 * w3 + MgR / lambda1 * g2, -a * w3 * w1 - MgR / lambda1 * g1, 0.0,
            g2 * w3 - g3 * w2, g3 * w1 - g1 * w3, g1 * w2 - g2 * w1, (w1 * g1 + w2 * g2) / (g1 * g1 + g2 * g2))


def event_nutation(t, w1, w2, w3, g1, g2, g3, phi, lambda1, lambda3, MgR):
    """u' = d cos(tilt) / dt (1/s): zero at the nutation's turning points."""
    return g1 * w2 - g2 * w1


def check(values):
    """The vertical must be a unit vector, and not along e3 (the precession angle is undefined there)."""
    from ensemble import ParameterError

    norm = np.sqrt(values["g10"] ** 2 + values["g20"] ** 2 + values["g30"] ** 2)
    if np.any(np.abs(norm - 1.0) > 1e-9):
        raise ParameterError("g30", "g10, g20, g30 must make a unit vector (the upward vertical)")
    if np.any((values["g10"] == 0.0) & (values["g20"] == 0.0)):
        raise ParameterError("g20", "a top exactly upright (g10 = g20 = 0) has no precession angle: tilt it")


def nutation_roots(w1, w2, w3, g1, g2, g3, phi, lambda1, lambda3, MgR):
    """The roots u1 <= u2 <= u3 of u'^2 = f(u) for each member's state (arrays), (3, members)."""
    beta = 2.0 * MgR / lambda1
    a = lambda3 * w3 / lambda1
    alpha = w1 * w1 + w2 * w2 + beta * g3  # 2 E' / lambda1, E' = the energy but the spin's
    b = w1 * g1 + w2 * g2 + a * g3  # the angular momentum about the vertical over lambda1
    roots = [np.sort(np.roots([beta_, -(alpha_ + a_ * a_), 2 * a_ * b_ - beta_, alpha_ - b_ * b_]).real)
             for alpha_, beta_, a_, b_ in np.broadcast(alpha, beta, a, b)]
    return np.array(roots).T


def nutation_period(w1, w2, w3, g1, g2, g3, phi, lambda1, lambda3, MgR):
    """The nutation period 4 K(m) / sqrt(beta (u3 - u1)) (s), m = (u2 - u1) / (u3 - u1), per member."""
    u1, u2, u3 = nutation_roots(w1, w2, w3, g1, g2, g3, phi, lambda1, lambda3, MgR)
    beta = 2.0 * np.asarray(MgR) / np.asarray(lambda1)
    return 4.0 * ellipk((u2 - u1) / (u3 - u1)) / np.sqrt(beta * (u3 - u1))


def precession_rate(w1, w2, w3, g1, g2, g3, phi, lambda1, lambda3, MgR):
    """The mean precession rate (rad/s), phi's advance over a nutation period over that period, per member: with
    u = u1 + (u2 - u1) sin^2(psi), dt = 2 dpsi / sqrt(beta (u3 - u)) and dphi = (b - a u) / (1 - u^2) dt, both
    integrated over psi from 0 to pi / 2 (half a period) by quadrature."""
    from scipy.integrate import quad

    state = np.broadcast_arrays(w1, w2, w3, g1, g2, g3, lambda1, lambda3, MgR)
    u1, u2, u3 = nutation_roots(*state[:6], 0.0, *state[6:])
    rates = []
    for w1_, w2_, w3_, g1_, g2_, g3_, lambda1_, lambda3_, mgr, u1_, u2_, u3_ in zip(*state, u1, u2, u3):
        beta, a = 2.0 * mgr / lambda1_, lambda3_ * w3_ / lambda1_
        b = w1_ * g1_ + w2_ * g2_ + a * g3_

        def u(psi):
            return u1_ + (u2_ - u1_) * np.sin(psi) ** 2

        def dt(psi):
            return 2.0 / np.sqrt(beta * (u3_ - u(psi)))

        def dphi(psi):
            return (b - a * u(psi)) / (1.0 - u(psi) ** 2) * dt(psi)

        options = dict(epsabs=0.0, epsrel=1e-13, limit=200)
        rates.append(quad(dphi, 0.0, np.pi / 2, **options)[0] / quad(dt, 0.0, np.pi / 2, **options)[0])
    return np.array(rates)


def fit(ds):
    """The run's nutation event (of = "nutation") against the elliptic theory, an xarray Dataset over member:
    the nutation period from the turning points alone (the event kept both ways: half a period apart), against
    4 K(m) / sqrt(beta (u3 - u1)); or, where the event stops each top at its first turning point (direction
    "up": the lowest u, a top released at rest tilts further first), the largest tilt arccos(g3 there) against
    arccos(u1). Where the event keeps phi (keep = ["phi"]), the mean precession rate too: phi at the turning
    points, half a nutation period apart, advances by half its advance over a period, so the slope of a line
    through them is the mean rate, against `precession_rate` and beside the fast top's M g R / (lambda3 w3). The
    events are located to the method's own accuracy, so `ensemble fit --check` holds each to 1e-6 relative
    (check_rtol)."""
    import xarray as xr

    from ensemble.fitting import event_period

    turns = [name for name in ds.data_vars if ds[name].attrs.get("event_of") == "nutation"]
    if not turns:
        raise ValueError("heavy_top's fit needs a run with an event of = \"nutation\"")
    times = ds[turns[0]].values
    starts = [np.broadcast_to(ds[f"{name}0"].values, times.shape[:1]) for name in STATE]
    moments = [np.broadcast_to(ds[name].values, times.shape[:1]) for name in ("lambda1", "lambda3", "MgR")]
    if ds[turns[0]].attrs["event_stop"]:
        lowest = nutation_roots(*starts, *moments)[0]
        tilt = np.arccos(np.clip(ds["g3_at_stop"].values, -1.0, 1.0))
        return xr.Dataset({"max_tilt": ("member", tilt, {"units": "rad", "check_rtol": 1e-6,
                                                          "long_name": "tilt at the first turning point"}),
                           "max_tilt_theory": ("member", np.arccos(lowest), {
                               "units": "rad", "long_name": "arccos(u1), the cubic's lowest root"})})
    period = np.array([event_period(row, 2)[0] for row in times])
    theory = nutation_period(*starts, *moments)
    fits = xr.Dataset({"nutation_period": ("member", period, {"units": "s", "check_rtol": 1e-6,
                                                              "long_name": "nutation period from turning points"}),
                       "nutation_period_theory": ("member", theory, {
                           "units": "s", "long_name": "nutation period, 4 K(m) / sqrt(beta (u3 - u1))"})})
    phi = turns[0].removesuffix("_time") + "_phi"  # the precession angle kept at each turning point (keep)
    if phi in ds:
        rate = [np.polyfit(t[np.isfinite(t)], angle[np.isfinite(t)], 1)[0] for t, angle in zip(times, ds[phi].values)]
        fits["precession_rate"] = ("member", np.array(rate), {
            "units": "rad s-1", "check_rtol": 1e-6, "long_name": "mean precession rate from turning points"})
        fits["precession_rate_theory"] = ("member", precession_rate(*starts, *moments), {
            "units": "rad s-1", "long_name": "mean precession rate, by quadrature over a nutation period"})
        fits["precession_rate_fast"] = ("member", moments[2] / (moments[1] * starts[2]), {
            "units": "rad s-1", "long_name": "the fast top's precession rate M g R / (lambda3 w3)"})
    return fits


def charts(plt, ds, fits, rows, stem, members=None):
    """`ensemble fit --charts`: the largest tilt against the spin across the sleeping threshold (STEM_max_tilt.png),
    or the nutation period against the spin with the fast top's 2 pi lambda1 / (lambda3 w3) (STEM_nutation.png)
    and, where fitted, the mean precession rate with the fast top's M g R / (lambda3 w3) (STEM_precession.png);
    the fitted values from the events as dots, the theory as a line."""
    spin = np.broadcast_to(ds["w30"].values, (ds.sizes["member"],))
    grid = np.linspace(spin.min(), spin.max(), 300)
    starts = [np.full(grid.shape, float(ds[f"{name}0"].values.ravel()[0])) for name in STATE]
    starts[2] = grid
    moments = [np.full(grid.shape, float(ds[name].values.ravel()[0])) for name in ("lambda1", "lambda3", "MgR")]
    fig, ax = plt.subplots(figsize=(6, 3.6), layout="constrained")
    if "max_tilt" in fits:
        lambda1, lambda3, mgr = (moments[k][0] for k in range(3))
        ax.plot(grid, np.arccos(nutation_roots(*starts, *moments)[0]), color="0.3", label="theory arccos(u1)")
        ax.plot(spin, fits["max_tilt"].values, "o", color="C0", label="tilt at the first turning point (event)")
        ax.axvline(2 * np.sqrt(lambda1 * mgr) / lambda3, color="C3", ls="--", label="(lambda3 w3)^2 = 4 lambda1 M g R")
        ax.set(ylabel="largest tilt (rad)", title="the sleeping top: which spins stay up")
        name = "max_tilt"
    else:
        ax.plot(grid, nutation_period(*starts, *moments), color="0.3", label="theory 4 K(m) / sqrt(beta (u3 - u1))")
        ax.plot(grid, 2 * np.pi * moments[0] / (moments[1] * grid), color="C3", ls="--",
                label="fast top 2 pi lambda1 / (lambda3 w3)")
        ax.plot(spin, fits["nutation_period"].values, "o", color="C0", label="from turning-point events")
        ax.set(ylabel="nutation period (s)", yscale="log", title="the heavy top's nutation")
        name = "nutation"
    paths = [_saved(plt, fig, ax, f"{stem}_{name}.png")]
    if "precession_rate" in fits:
        fig, ax = plt.subplots(figsize=(6, 3.6), layout="constrained")
        ax.plot(grid, precession_rate(*starts, *moments), color="0.3", label="theory (quadrature over a nutation)")
        ax.plot(grid, moments[2] / (moments[1] * grid), color="C3", ls="--", label="fast top M g R / (lambda3 w3)")
        ax.plot(spin, fits["precession_rate"].values, "o", color="C0", label="from phi at turning-point events")
        ax.set(ylabel="mean precession rate (rad/s)", yscale="log", title="the heavy top's precession")
        paths.append(_saved(plt, fig, ax, f"{stem}_precession.png"))
    return paths


def _saved(plt, fig, ax, path: str) -> str:
    """A chart against the spin, written to path."""
    ax.set(xlabel="spin w3 (rad/s)")
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path

"""The plane pendulum, theta'' = -omega0^2 sin(theta), released at rest from theta0: a scene of your own whose
zero crossings are events (runs/pendulum.toml).

It swings through theta = 0 at t_j = (2 j + 1) K(m) / omega0, j = 0, 1, ..., with m = sin^2(theta0 / 2) and K
the complete elliptic integral of the first kind: its period 4 K(m) / omega0 grows with the amplitude from
2 pi / omega0. Its closed form is theta = 2 asin(k sn(K(m) - omega0 t | m)), k = sin(theta0 / 2). Its bob's
height above the lowest point, 1 - cos(theta) lengths, is an event function of its own (EVENTS).
"""
import math

import numpy as np
from scipy.special import ellipj, ellipk, ellipkinc

from ensemble import Parameter

NAME = "pendulum"

STATE = {"theta": ("rad", "angle from the downward vertical"), "theta_dot": ("rad s-1", "angular velocity")}

PARAMETERS = {  # theta0 and theta_dot0 start the state; omega0 is the right-hand side's
    "omega0": Parameter("rad s-1", "small-swing angular frequency sqrt(g / l)"),
    "theta0": Parameter("rad", "angle at t = 0"),
    "theta_dot0": Parameter("rad s-1", "angular velocity at t = 0", default=0.0),
}


def rhs(t, theta, theta_dot, omega0):
    """(theta', theta_dot') of one member at time t (s)."""
    return theta_dot, -omega0 * omega0 * math.sin(theta)


EVENTS = ("height",)  # a run file's [events] may watch it: of = "height"


def event_height(t, theta, theta_dot, omega0):
    """The bob's height above its lowest point, in pendulum lengths."""
    return 1.0 - math.cos(theta)


PIECES = ("kick", "drift")  # the splittings' pieces: verlet and yoshida4 apply
EVALUATING_PIECES = ("kick",)


def kick(tau, theta, theta_dot, omega0):
    """Gravity alone for time tau (s)."""
    return theta, theta_dot - tau * omega0 * omega0 * math.sin(theta)


def drift(tau, theta, theta_dot, omega0):
    """Free rotation for time tau (s)."""
    return theta + tau * theta_dot, theta_dot


def crossing_times(theta0, omega0, count: int) -> np.ndarray:
    """The first `count` times (s) at which a pendulum released at rest from theta0 passes theta = 0, (count,)
    for one member or (..., count) over members' arrays."""
    quarter = ellipk(np.sin(np.asarray(theta0) / 2.0) ** 2) / np.asarray(omega0)
    return (2 * np.arange(count) + 1) * quarter[..., None]


def height_times(theta0, omega0, level: float) -> np.ndarray:
    """The first time (s) at which a pendulum released at rest from theta0 (above the level) falls to height
    `level` (lengths): theta = acos(1 - level) = 2 asin(k sn(K - omega0 t)), so omega0 t = K - F(asin(sin(theta /
    2) / k) | m)."""
    k = np.sin(np.asarray(theta0) / 2.0)
    reached = np.arcsin(np.sin(np.arccos(1.0 - level) / 2.0) / k)
    return (ellipk(k * k) - ellipkinc(reached, k * k)) / np.asarray(omega0)


def exact(t, theta0, theta_dot0, omega0):
    """theta(t) and theta_dot(t) of a pendulum released at rest from theta0, |theta0| < pi (numpy arrays broadcast
    over t (times, 1) and the members' values (1, members)); NaN for a member not released at rest."""
    k = np.sin(theta0 / 2.0)
    m = k * k
    sn, cn, _, _ = ellipj(ellipk(m) - omega0 * t, m)
    at_rest = np.where(theta_dot0 == 0.0, 1.0, np.nan)
    return 2.0 * np.arcsin(k * sn) * at_rest, -2.0 * k * omega0 * cn * at_rest


def fit(ds):
    """Each member's period from its zero-crossing events alone (an event of = "theta", value 0, both ways: half
    a period apart), against the elliptic theory 4 K(m) / omega0; an xarray Dataset over member (a member with
    fewer than three crossings: NaN). The events are located to the method's own accuracy, so `ensemble fit
    --check` holds the period to 1e-6 relative (check_rtol)."""
    import xarray as xr

    from ensemble.fitting import event_period

    zeros = [name for name in ds.data_vars if ds[name].attrs.get("event_of") == "theta"
             and ds[name].attrs.get("event_value") == 0.0 and ds[name].attrs.get("event_direction") == "both"]
    if not zeros:
        raise ValueError('the pendulum\'s fit needs a run with an event of = "theta" (value 0, both directions)')
    times = ds[zeros[0]].values  # (member, occurrence), NaN where fewer occurred
    period = np.array([event_period(row, 2)[0] for row in times])
    theta0, omega0 = (np.broadcast_to(ds[name].values, times.shape[:1]) for name in ("theta0", "omega0"))
    theory = 4.0 * ellipk(np.sin(theta0 / 2.0) ** 2) / omega0
    return xr.Dataset({"period": ("member", period, {"units": "s", "long_name": "period from zero crossings",
                                                      "check_rtol": 1e-6}),
                       "period_theory": ("member", theory, {"units": "s", "long_name": "period, 4 K(m) / omega0"})})


def charts(plt, ds, fits, rows, stem, members=None):
    """`ensemble fit --charts`: each member's period from its zero crossings, in units of the small-swing
    2 pi / omega0, against the elliptic theory over the amplitude; STEM_period.png."""
    theta0 = np.broadcast_to(ds["theta0"].values, fits["period"].shape)
    small = 2 * np.pi / np.broadcast_to(ds["omega0"].values, theta0.shape)
    grid = np.linspace(0.0, theta0.max(), 200)
    fig, ax = plt.subplots(figsize=(6, 3.6), layout="constrained")
    ax.plot(grid, 2 / np.pi * ellipk(np.sin(grid / 2) ** 2), color="0.3", label="theory 4 K(m) / omega0")
    ax.plot(theta0, fits["period"].values / small, ".", ms=3, color="C0", label="from zero-crossing events")
    ax.set(xlabel="amplitude theta0 (rad)", ylabel="period / (2 pi / omega0)",
           title="pendulum period from its events")
    ax.legend()
    path = f"{stem}_period.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return [path]

"""The free rigid body with three different moments: its model (Euler's equations, the elliptic closed form,
observables, linear theory) and, in `physics`, the right-hand side and pieces its kernels are built from."""
from .model import *  # noqa: F403

# The fit and the charts import the model, never the other way: here they are the scene's, imported when used
# (scipy and xarray only when fitting, matplotlib only when charting).


def fit(ds):
    """The scene's fit of a result (ensemble.scenes.body.fits.body_rates), an xarray Dataset over its members."""
    from .fits import body_rates  # scipy and xarray: only when fitting

    return body_rates(ds)


def charts(plt, ds, fits, rows, stem, members=None) -> list:
    """The scene's charts of its fit, PNG files STEM_<chart>.png (ensemble.scenes.body.plots.draw)."""
    from .plots import draw  # matplotlib: only when charting

    return draw(plt, ds, fits, rows, stem, members)

"""The torqued symmetric top: its model (equations, closed form, observables, theory) and, in `physics`, the
right-hand side and pieces its kernels are built from. The model's names are this package's, so
`ensemble.scenes.top.exact` is the closed form."""
from .model import *  # noqa: F403

# The fit and the charts import the model, never the other way: here they are the scene's, imported when used
# (scipy and xarray only when fitting, matplotlib only when charting).


def fit(ds):
    """The scene's fit of a result (ensemble.scenes.top.fits.tilt_decay), an xarray Dataset over its members."""
    from .fits import tilt_decay  # scipy and xarray: only when fitting

    return tilt_decay(ds)


def charts(plt, ds, fits, rows, stem, members=None) -> list:
    """The scene's charts of its fit, PNG files STEM_<chart>.png (ensemble.scenes.top.plots.draw)."""
    from .plots import draw  # matplotlib: only when charting

    return draw(plt, ds, fits, rows, stem, members)

"""Spring chains: their model (normal modes, modal solution, energy, theory) and, in `physics`, the compiled
acceleration their kernels are built from. The model's names are this package's, so
`ensemble.scenes.chain.normal_modes` works."""
from .model import *  # noqa: F403

# The fit and the charts import the model, never the other way: here they are the scene's, imported when used
# (scipy and xarray only when fitting, matplotlib only when charting).


def fit(ds):
    """The scene's fit of a result (ensemble.scenes.chain.fits.mode_frequencies), an xarray Dataset over its members."""
    from .fits import mode_frequencies  # scipy and xarray: only when fitting

    return mode_frequencies(ds)


def charts(plt, ds, fits, rows, stem, members=None) -> list:
    """The scene's charts of its fit, PNG files STEM_<chart>.png (ensemble.scenes.chain.plots.draw)."""
    from .plots import draw  # matplotlib: only when charting

    return draw(plt, ds, fits, rows, stem, members)

"""Progress bars: one kind for runs and long fits, a widget in Jupyter (with ipywidgets) and text elsewhere."""
from __future__ import annotations

import threading
import warnings

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # tqdm's note that, in Jupyter, it chose the notebook's widget bar
    from tqdm.autonotebook import tqdm


class Bar(tqdm):
    """A run's progress bar: tqdm (a widget in Jupyter with ipywidgets, text elsewhere) with a thread lock of its
    own. tqdm's default lock also guards bars of other processes, and importing multiprocessing for it took
    2.5 ms before a run's first kernel; a run's bar moves on its own process's threads only."""
    _lock = threading.RLock()


# The bar counts members, and moves within a launch as its blocks store their samples.
BAR = "{l_bar}{bar}| {n:.0f}/{total_fmt} members [{elapsed}<{remaining}{postfix}]"

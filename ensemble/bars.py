"""Progress bars: one kind for runs and long fits, a widget in Jupyter (with ipywidgets), text on a terminal,
and a plain line now and then on a file or a pipe."""
from __future__ import annotations

import sys
import threading
import warnings

from tqdm.std import tqdm as text_bar

with warnings.catch_warnings():
    warnings.simplefilter("ignore")  # tqdm's note that, in Jupyter, it chose the notebook's widget bar
    from tqdm.autonotebook import tqdm

PLAIN_FRACTION, PLAIN_SECONDS = 0.1, 30.0  # off a terminal, a line each tenth of the work or half minute


class Bar(tqdm):
    """A run's progress bar: tqdm (a widget in Jupyter with ipywidgets, text elsewhere) with a thread lock of its
    own. tqdm's default lock also guards bars of other processes, and importing multiprocessing for it took
    2.5 ms before a run's first kernel; a run's bar moves on its own process's threads only. Written to a file
    or a pipe (not a terminal), it writes a plain line each PLAIN_FRACTION of the total or PLAIN_SECONDS,
    instead of a carriage-return update every tenth of a second."""
    _lock = threading.RLock()

    def __init__(self, *args, **kwargs):
        file = kwargs.get("file") or sys.stderr
        self._plain = tqdm is text_bar and not (hasattr(file, "isatty") and file.isatty())
        self._said = (0.0, 0.0)  # the fraction done and the time of the last plain line
        super().__init__(*args, **kwargs)

    def display(self, msg=None, pos=None):
        if not self._plain:
            return super().display(msg, pos)
        if msg is not None:  # tqdm clearing the bar as it closes: nothing to clear
            return False
        if not self.total or not hasattr(self, "start_t"):  # starting
            return True
        fraction, now = self.n / self.total, self._time() - self.start_t
        if fraction >= 1 or (fraction < self._said[0] + PLAIN_FRACTION and now < self._said[1] + PLAIN_SECONDS):
            return True  # the run's summary says the end
        self._said = (fraction, now)
        left = f", about {self.format_interval(now / fraction - now)} left" if fraction > 0 else ""
        postfix = f" ({self.postfix})" if self.postfix else ""
        self.fp.write(f"{fraction:4.0%} of {self.total:.0f} {self.unit}s after {self.format_interval(now)}{left}"
                      f"{postfix}\n")
        self.fp.flush()
        return True


# The bar counts members, and moves within a launch as its blocks store their samples.
BAR = "{l_bar}{bar}| {n:.0f}/{total_fmt} members [{elapsed}<{remaining}{postfix}]"

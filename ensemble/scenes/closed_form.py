"""What every scene's closed form (`exact`) shares."""
from __future__ import annotations

import numpy as np


def times_by_members(t) -> np.ndarray:
    """exact's times (s) as a (times, 1) column from (times,), or as given, (times, members): each member's own
    (events on the closed form locate each member's crossings at its own times)."""
    t = np.asarray(t, dtype=float)
    return t[:, None] if t.ndim == 1 else t

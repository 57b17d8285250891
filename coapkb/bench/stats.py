"""Statistics of benchmark and experiment results, on numpy."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile (0..100) of ``values`` with numpy's default
    linear interpolation, or None for no values (an empty column, not an error).
    ``q`` outside 0..100 raises ValueError."""
    if len(values) == 0:
        return None
    return float(np.percentile(np.asarray(values, dtype=float), q))

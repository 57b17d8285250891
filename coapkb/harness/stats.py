"""Statistics of run, benchmark and experiment results, on numpy."""

from __future__ import annotations

from collections.abc import Sequence


def percentile(values: Sequence[float], q: float) -> float | None:
    """The ``q``-th percentile (0..100) of ``values`` with numpy's default
    linear interpolation, or None for no values (an empty column, not an error).
    ``q`` outside 0..100 raises ValueError."""
    if len(values) == 0:
        return None
    # Here, not at the top: ``coapkb bench``'s options are built by every
    # ``coapkb`` command, a robot's too, and a robot has no use for numpy.
    import numpy as np

    return float(np.percentile(np.asarray(values, dtype=float), q))

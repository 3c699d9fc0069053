"""The C2 log barrier of incremental potential contact, shared by the shell's barriers.

Li et al. 2020, "Incremental Potential Contact", their ``b(d, d_hat)``:

    b(d) = -(d - d_hat)^2 ln(d / d_hat)  for 0 < d < d_hat,  0 for d >= d_hat,  +inf for d <= 0,

    b'  = -2 (d - d_hat) ln(d / d_hat) - (d - d_hat)^2 / d   < 0,
    b'' = -2 ln(d / d_hat) - 4 (d - d_hat) / d + (d - d_hat)^2 / d^2   > 0   (0 < d < d_hat).

``b`` and its first two derivatives vanish at ``d = d_hat``: the barrier does not change a state
whose gaps all stay at or above ``d_hat``, and a line search never crosses ``d = 0``.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, inline="always")
def log_barrier(d: float, d_hat: float) -> tuple[float, float, float]:  # pragma: no cover
    """``(b, b', b'')`` at ``0 < d < d_hat`` (dimensionless in ``d``; the caller scales)."""
    t, lg = d - d_hat, np.log(d / d_hat)
    return -t * t * lg, -2.0 * t * lg - t * t / d, -2.0 * lg - 4.0 * t / d + t * t / (d * d)

"""Timing helpers of the benchmarks: wall and CPU stopwatches, power-law fits of growth."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

Timings = dict[str, dict[str, float]]


@contextmanager
def stopwatch(store: Timings, name: str) -> Iterator[None]:
    """Record the wall and process CPU seconds of the ``with`` body as ``store[name]``."""
    wall, cpu = time.perf_counter(), time.process_time()
    yield
    store[name] = {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu}


def power_fit(n: np.ndarray, y: np.ndarray) -> dict[str, float | list[float]]:
    """Least-squares ``log y = p log n + c`` with its residual and the local slopes.

    Returns ``p``, ``c``, ``rms_log_residual`` = sqrt(mean r_i^2) and ``max_log_residual`` =
    max |r_i| with ``r_i = log y_i - (p log n_i + c)`` (0 for two points: a line through
    them), and ``local`` = the slopes ``d log y / d log n`` between consecutive sizes.
    """
    ln, ly = np.log(n), np.log(y)
    p, c = np.polyfit(ln, ly, 1)
    res = ly - (p * ln + c)
    return {"p": float(p), "c": float(c), "rms_log_residual": float(np.sqrt(np.mean(res**2))),
            "max_log_residual": float(np.max(np.abs(res))),
            "local": [float(s) for s in np.diff(ly) / np.diff(ln)]}

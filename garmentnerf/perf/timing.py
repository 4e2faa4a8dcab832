"""Wall-clock timing shared by the benchmarks."""

from __future__ import annotations

import time

import numpy as np


def median_ms(fn, runs: int, warmup: int = 2) -> float:
    """Median wall-clock milliseconds of ``fn()`` over ``runs`` calls after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return float(np.median(times))

"""Latency figures, written once: the benchmarks, the load script and the evaluation all report
their timings (milliseconds) through ``latency_stats``, each choosing which figures it keeps."""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence

import numpy as np

FIGURES = ("count", "median_ms", "p95_ms", "mean_ms", "min_ms")  # the benchmarks' usual set
NAMED: dict[str, Callable[[np.ndarray], float]] = {
    "median_ms": np.median,
    "mean_ms": np.mean,
    "min_ms": np.min,
    "max_ms": np.max,
}
PERCENTILE = re.compile(r"p(\d{1,2})_ms")  # p25_ms, p95_ms, p99_ms: that percentile


def figure(name: str) -> Callable[[np.ndarray], float]:
    """The function computing the figure ``name`` of a non-empty array of latencies."""
    if name in NAMED:
        return NAMED[name]
    if match := PERCENTILE.fullmatch(name):
        return lambda values, q=int(match[1]): np.percentile(values, q)
    raise ValueError(f"no latency figure named {name!r}: count, {', '.join(NAMED)} or pNN_ms")


def latency_stats(
    values_ms: Iterable[float], figures: Sequence[str] = FIGURES, empty: float | None = None
) -> dict[str, float | int | None]:
    """The ``figures`` of ``values_ms``, in that order: ``count``, ``median_ms``, ``mean_ms``,
    ``min_ms``, ``max_ms`` or ``pNN_ms`` (the NN-th percentile, interpolated between samples as
    ``numpy.percentile`` does). With no values every figure but ``count`` is ``empty``."""
    values = np.asarray(list(values_ms), dtype=np.float64)
    stats: dict[str, float | int | None] = {}
    for name in figures:
        if name == "count":
            stats[name] = len(values)
            continue
        compute = figure(name)
        stats[name] = float(compute(values)) if len(values) else empty
    return stats


def median(values_ms: Iterable[float]) -> float | None:
    """``latency_stats``'s median alone."""
    return latency_stats(values_ms, ("median_ms",))["median_ms"]

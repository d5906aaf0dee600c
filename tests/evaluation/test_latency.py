"""``evaluation.latency``: the one place latency figures are computed, against numpy's own."""

from __future__ import annotations

import numpy as np
import pytest

from evaluation.latency import FIGURES, latency_stats, median


def test_the_figures_are_numpy_s_in_the_order_asked():
    values = np.random.default_rng(0).gamma(2.0, 3.0, 101)
    stats = latency_stats(values.tolist())
    assert list(stats) == list(FIGURES)
    assert stats["count"] == 101
    assert stats["median_ms"] == pytest.approx(np.median(values))
    assert stats["p95_ms"] == pytest.approx(np.percentile(values, 95))
    assert stats["mean_ms"] == pytest.approx(values.mean())
    assert stats["min_ms"] == values.min()
    asked = ("max_ms", "p25_ms", "p99_ms", "p50_ms")
    chosen = latency_stats(values, asked)
    assert list(chosen) == list(asked)
    assert chosen["max_ms"] == values.max()
    for q in (25, 99, 50):
        assert chosen[f"p{q}_ms"] == pytest.approx(np.percentile(values, q))
    assert median(iter(values)) == pytest.approx(np.median(values))


def test_no_values_give_the_empty_figure_and_a_count_of_zero():
    assert latency_stats([]) == {name: 0 if name == "count" else None for name in FIGURES}
    nan = latency_stats([], ("count", "p95_ms"), empty=float("nan"))
    assert nan["count"] == 0 and np.isnan(nan["p95_ms"])
    assert median([]) is None


@pytest.mark.parametrize("name", ["p95", "p100_ms", "median", "worst_ms", "p_ms"])
def test_an_unknown_figure_is_refused_by_name(name):
    with pytest.raises(ValueError, match=repr(name)):
        latency_stats([1.0, 2.0], ("count", name))
    with pytest.raises(ValueError, match=repr(name)):
        latency_stats([], (name,))

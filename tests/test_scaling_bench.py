import math

import numpy as np
import pytest

from evseg.scaling_bench import benchmark, growth_exponent, growth_exponents


def test_growth_exponent_reads_linear_and_sublinear_growth():
    """1 for time proportional to the events, 0 for constant time, log(2)/log(4) = 0.5 for
    twice the time at four times the events; NaN where a ratio is undefined."""
    assert growth_exponent(1e3, 5.0, 3e3, 15.0) == pytest.approx(1.0)
    assert growth_exponent(1e3, 5.0, 3e3, 5.0) == 0.0
    assert growth_exponent(1e3, 5.0, 4e3, 10.0) == pytest.approx(0.5)
    assert math.isnan(growth_exponent(1e3, 5.0, 1e3, 6.0))
    assert math.isnan(growth_exponent(0.0, 5.0, 1e3, 6.0))


def test_growth_exponents_are_taken_from_the_first_row():
    """Against the lowest rate, not the row before: rows at 1x, 2x, 4x the events taking 10,
    20, 20 ms give 1 and 0.5 (against the row before, the third would read 0)."""
    e = growth_exponents([1e3, 2e3, 4e3], [10.0, 20.0, 20.0])
    assert math.isnan(e[0]) and e[1:] == pytest.approx([1.0, 0.5])


def test_quick_scaling_table_rises_with_the_event_rate():
    """`evseg bench scaling --quick`: two simulated 346x260 streams (0.3 and 1 M events/s,
    within the 5 % the stream calibration aims at), one row each in rising order, with more
    events and nodes per window at the higher rate, the exponent computed from the two rows,
    and a total that is the sum of the stages (overlap off: one window after the other)."""
    rows = benchmark(repeats=1, quick=True)
    assert [r["input"] for r in rows] == ["simulated 346x260"] * 2
    assert [round(r["M events/s"], 1) for r in rows] == [0.3, 1.0]
    lo, hi = rows
    assert hi["events/window"] > 3 * lo["events/window"] and hi["nodes/window"] > lo["nodes/window"] > 0
    assert math.isnan(lo["growth exponent"])
    assert hi["growth exponent"] == pytest.approx(
        math.log(hi["total ms"] / lo["total ms"]) / math.log(hi["events/window"] / lo["events/window"]))
    for r in rows:
        assert r["windows"] == 10
        assert r["total ms per 1k events"] == pytest.approx(r["total ms"] / (r["events/window"] / 1e3))
        stages = sum(r[c] for c in ("flow ms", "preprocessing ms", "initialization ms", "labeling_fitting ms",
                                    "propagation ms"))
        # Medians of the stages need not add up to the median total exactly; the stages are
        # the window's work, the rest (windowing, ids, labels of every event) is small.
        assert 0.6 * r["total ms"] < stages < 1.2 * r["total ms"], (stages, r["total ms"])
        assert np.isfinite(r["total p90 ms"]) and r["total p90 ms"] >= r["total ms"]

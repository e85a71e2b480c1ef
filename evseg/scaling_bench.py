"""How the pipeline's time per window grows with the event rate (``evseg bench scaling``).

Simulated EVIMO-like streams at 346x260 whose contrast threshold is scaled to 0.1 - 5 M
events/s (:func:`evseg.pipeline_bench.simulated_stream`: the same scene and motion, more events
per edge crossing at lower thresholds, as a real sensor with a more sensitive setting), timed
with :func:`evseg.pipeline_bench.time_pipeline` one window after the other (``overlap`` off,
normal flow on 2 threads), so that ``total`` is the sum of the stages and each stage's growth
can be read off its column.

Each row gives the events and the median segmentation nodes per window, the stage medians
(ms per 10 ms window), the total per thousand events, and the growth exponent from the lowest
rate: ``log(total_i / total_0) / log(events_i / events_0)``. It is taken against the first row
rather than the row before because the VM's speed drifts by tens of percent within minutes,
and the ratio of two neighbouring rows is mostly that drift. An exponent of 1 is linear growth
in the event rate, below 1 sub-linear: the flow runs on at most one target per 2 px cell and
the segmentation on one node per 3 px cell, so the cost per event falls as the rate rises.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

from evseg.pipeline_bench import simulated_stream, time_pipeline

RATES_EV_S = (1e5, 3e5, 5e5, 1e6, 2e6, 3e6, 5e6)
"""Event rates of the full table (events/s); ``quick`` uses 3e5 and 1e6 over 100 ms."""

STAGE_COLUMNS = ("flow ms", "preprocessing ms", "initialization ms", "labeling_fitting ms", "propagation ms",
                 "total ms", "total p90 ms")


def growth_exponent(events_prev: float, total_prev: float, events: float, total: float) -> float:
    """Local exponent of time against events between two rows (1 = linear); NaN if undefined.

    >>> round(growth_exponent(1000, 10.0, 4000, 20.0), 3)
    0.5
    """
    if min(events_prev, total_prev, events, total) <= 0 or events == events_prev:
        return float("nan")
    return math.log(total / total_prev) / math.log(events / events_prev)


def growth_exponents(events: list[float], totals: list[float]) -> list[float]:
    """Each row's growth exponent from the first row (NaN for the first).

    >>> [round(e, 3) for e in growth_exponents([1000, 2000, 4000], [10.0, 12.0, 20.0])[1:]]
    [0.263, 0.5]
    """
    return [float("nan")] + [growth_exponent(events[0], totals[0], n, t) for n, t in zip(events[1:], totals[1:])]


def benchmark(repeats: int = 3, quick: bool = False) -> list[dict]:
    """One row per event rate, in rising order (see the module docstring)."""
    from evseg.io import write_npz

    rates = (3e5, 1e6) if quick else RATES_EV_S
    duration_us = 100_000 if quick else 300_000
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for rate in rates:
            rec = simulated_stream(rate, duration_us)
            path = Path(tmp) / f"sim_{int(rate)}.npz"
            write_npz(rec.stream, path)
            t = time_pipeline(path, repeats, overlap=False)
            row = {"input": "simulated 346x260", "M events/s": rec.stream.rate_ev_s / 1e6,
                   "events/window": t["events/window"], "nodes/window": t["nodes/window"],
                   "windows": t["windows"]}
            row.update({c: t[c] for c in STAGE_COLUMNS})
            row["total ms per 1k events"] = t["total ms"] / (t["events/window"] / 1e3)
            rows.append(row)
    exponents = growth_exponents([r["events/window"] for r in rows], [r["total ms"] for r in rows])
    for row, e in zip(rows, exponents):
        row["growth exponent"] = e
    return rows

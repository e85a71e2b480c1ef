"""`evseg bench live`: does the pipeline keep up with a live sensor, and how late are its labels?

A simulated EVIMO-like stream (346x260) at 0.3, 1 and 3 M events/s is replayed at the sensor's
pace (:func:`evseg.live.replay`, 1 ms packets) into :func:`evseg.live.run_live` with 10 ms
windows and a 20 ms lag bound, with the next window prepared by the worker process (the
default of ``evseg segment --realtime`` on a long recording) and without overlap. Per row: the share of the stream's windows segmented (the rest were dropped to keep
up), the latency from the arrival of the packet that completes a window to its labels (median
and p90), how far behind the newest event the segmented windows ended (median lag), and the
median wall time between two results. Medians over ``repeats`` replays of the same stream (one
pipeline, warmed up before the first: :meth:`~evseg.pipeline.MotionSegmentationPipeline.warm_up`).
"""

from __future__ import annotations

import time

import numpy as np

from evseg.live import replay, run_live
from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
from evseg.pipeline_bench import simulated_stream


def time_live(events: np.ndarray, sensor_size: tuple[int, int], repeats: int, max_lag_us: int | None = 20_000,
              speed: float = 1.0, **pipeline_options) -> dict:
    """Replay ``events`` ``repeats`` times through one warmed-up pipeline; the medians over the
    replays of each replay's figures. ``pipeline_options``: :class:`PipelineConfig` fields
    (default: the worker process, as ``evseg segment --realtime`` on a long recording)."""
    cfg = PipelineConfig(**{"worker": "process", **pipeline_options})
    stride_us = cfg.stride_us or cfg.window_us
    n_windows = int((int(events["t"][-1]) - int(events["t"][0])) // stride_us) + 1
    runs: dict[str, list[float]] = {k: [] for k in ("segmented", "latency", "latency_p90", "lag", "interval")}
    with MotionSegmentationPipeline(cfg, sensor_size=sensor_size) as pipe:
        pipe.warm_up()
        for _ in range(repeats):
            pipe.reset()
            results, done = [], []
            for res in run_live(pipe, replay([events], speed=speed), max_lag_us=max_lag_us):
                results.append(res)
                done.append(time.perf_counter())
            latency = np.array([r.latency_ms for r in results])
            runs["segmented"].append(len(results) / n_windows)
            runs["latency"].append(float(np.median(latency)))
            runs["latency_p90"].append(float(np.percentile(latency, 90)))
            runs["lag"].append(float(np.median([r.lag_us for r in results])) / 1e3)
            # Wall time between results: the output rate a consumer sees.
            runs["interval"].append(float(np.median(np.diff(done))) * 1e3 if len(done) > 1 else float("nan"))
    med = {k: float(np.median(v)) for k, v in runs.items()}
    return {
        "windows in stream": n_windows,
        "events/window": len(events) / n_windows,
        "segmented %": 100 * med["segmented"],
        "dropped %": 100 * (1 - med["segmented"]),
        "latency ms": med["latency"],
        "latency p90 ms": med["latency_p90"],
        "lag ms": med["lag"],
        "ms between results": med["interval"],
    }


def benchmark(repeats: int = 3, quick: bool = False) -> list[dict]:
    duration_us = 300_000 if quick else 2_000_000
    rates = [1e6] if quick else [3e5, 1e6, 3e6]
    rows = []
    for rate in rates:
        rec = simulated_stream(rate, duration_us)
        name = f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s"
        for overlap in (True, False):
            row = {"input": name, "worker": "process" if overlap else "none (overlap off)", "max lag ms": 20}
            row.update(time_live(rec.stream.events, rec.stream.sensor_size, repeats, max_lag_us=20_000,
                                 overlap=overlap))
            rows.append(row)
    return rows

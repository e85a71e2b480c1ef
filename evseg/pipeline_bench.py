"""Latency of the whole pipeline per stage, on simulated streams of set event rates and on
the real recordings in ``../shared/data`` (when present).

Simulated streams: the EVIMO-like scene at 346x260 with the contrast threshold scaled so that
the stream has about 0.3, 1 and 3 M events/s (fewer events per edge crossing = higher rate,
as a real sensor with a lower threshold). Each stream is written to an npz and read back
through the readers, so 'read' is real I/O. Every stage figure is the median (and p90) over
the windows of the stream, repeated ``repeats`` times over the same stream with the same
pipeline object (reset between repeats), so set-up costs paid once per stream weigh in only
the first repeat.

``total`` is the wall time per window as the stream goes through (time between results, plus
the window's share of reading): as ``evseg segment`` runs it, the next window's flow and
preparation run meanwhile in a worker process (``PipelineConfig.overlap``, ``worker``), so
the stage figures add up to more than it. The 1 M events/s stream is also timed with the
worker on a thread of the same process, with ``overlap`` off (one window after the other),
where ``total`` is also the time one window takes from its events to its labels, and with the
learned flow's slow-edge look (``PipelineConfig.slow_edges``, ``evseg segment --slow-edges``)
and with its 8 mirror looks (``PipelineConfig.mirrors``, ``evseg segment --mirrors 8``), and
with 8 looks inside the tracked boxes only (``PipelineConfig.tracked_mirrors``, ``evseg segment
--tracked-mirrors 8``, with and without a budget of 500 targets per window).
"""

from __future__ import annotations

import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from evseg.io import open_recording
from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

STAGES = ["read", "flow_encode", "flow_network", "flow", "preprocessing", "initialization",
          "labeling_fitting", "propagation", "total"]


def simulated_stream(rate_ev_s: float, duration_us: int, seed: int = 1100, rel_tol: float = 0.05,
                     max_rounds: int = 6):
    """A simulated EVIMO-like recording (346x260) of ``duration_us`` whose event rate is
    within ``rel_tol`` of ``rate_ev_s`` (events/s).

    The contrast thresholds are scaled until the rate of the span returned is close enough: a
    secant step in log threshold / log rate, starting from events ~ 1 / threshold. The rate is
    measured over the whole span because it is not steady: at high thresholds the first 50 ms
    fire nearly twice the rate of the next 250 ms. After ``max_rounds`` simulations the closest
    one is returned (benchmark rows print the rate they got).
    """
    from evseg.simulator import load_scene_preset, simulate

    if rate_ev_s <= 0 or duration_us <= 0:
        raise ValueError(f"simulated_stream: rate_ev_s and duration_us must be > 0, got {rate_ev_s}, {duration_us}")
    cfg = load_scene_preset("evimo_like")
    neg_over_pos = cfg.sensor.c_neg / cfg.sensor.c_pos
    tried: list[tuple[float, float]] = []  # (log threshold, log rate)
    best, best_err = None, np.inf
    for _ in range(max_rounds):
        rec = simulate(cfg, seed=seed, duration_us=duration_us)
        rate = rec.stream.rate_ev_s
        err = abs(rate / rate_ev_s - 1.0)
        if err < best_err:
            best, best_err = rec, err
        if err <= rel_tol:
            break
        tried.append((float(np.log(cfg.sensor.c_pos)), float(np.log(max(rate, 1.0)))))
        slope = -1.0
        if len(tried) >= 2 and tried[-1][0] != tried[-2][0]:
            # The rate must fall as the threshold rises; a flat or rising secant (noise events
            # dominate) falls back towards the 1 / threshold guess.
            slope = min(-0.25, (tried[-1][1] - tried[-2][1]) / (tried[-1][0] - tried[-2][0]))
        c_pos = float(np.exp(tried[-1][0] + (np.log(rate_ev_s) - tried[-1][1]) / slope))
        cfg = replace(cfg, sensor=replace(cfg.sensor, c_pos=c_pos, c_neg=c_pos * neg_over_pos))
    return best


def time_pipeline(path: Path, repeats: int, flow: str = "learned", threads: int | None = None,
                  overlap: bool = True, worker: str = "process", **pipeline_options) -> dict:
    """Per-stage median / p90 ms per window for one recording file, with the events and the
    median segmentation nodes per window. ``pipeline_options``: further
    :class:`~evseg.pipeline.PipelineConfig` fields (e.g. ``slow_edges=False``)."""
    per_stage: dict[str, list[float]] = {s: [] for s in STAGES}
    nodes: list[int] = []
    n_events = n_windows = 0
    pipe = None
    for _ in range(repeats):
        with open_recording(path) as rec:
            t0 = time.perf_counter()
            chunks = list(rec.chunks())
            read_s = time.perf_counter() - t0
            sensor = rec.sensor_size
        if pipe is None:
            # One pipeline for all repeats, as a live stream has, warmed up before timing as a
            # live camera's is: the one-time set-up (the encoder's per-pixel phase table, ~4 s
            # and 236 MB for a 1280x720 sensor; numba loading; the worker process, ~2 s) is in no
            # window's time (in --quick's 10 windows it was the p90).
            pipe = MotionSegmentationPipeline(PipelineConfig(flow=flow, threads=threads, overlap=overlap,
                                                             worker=worker, **pipeline_options), sensor_size=sensor)
            pipe.warm_up()
        pipe.reset()
        results = []
        it = pipe.run(chunks)
        while True:
            t0 = time.perf_counter()
            res = next(it, None)
            if res is None:
                break
            res.timings_ms["total"] = (time.perf_counter() - t0) * 1e3
            results.append(res)
        n_windows = len(results)
        n_events = sum(len(c) for c in chunks)
        for res in results:
            nodes.append(0 if res.segmentation is None else len(res.segmentation.node_x))
            tm = res.timings_ms
            tm["read"] = read_s * 1e3 / max(n_windows, 1)
            tm["total"] += tm["read"]
            tm["flow_encode"] = tm.get("flow_encode", float("nan"))
            tm["flow_network"] = tm.get("flow_network", float("nan"))
            for s in STAGES:
                per_stage[s].append(tm.get(s, 0.0))
    if pipe is not None:
        pipe.close()
    window_ms = PipelineConfig().window_us / 1e3
    out = {"events/window": n_events / max(n_windows, 1), "windows": n_windows,
           "nodes/window": float(np.median(nodes)) if nodes else float("nan")}
    for s in STAGES:
        v = np.asarray(per_stage[s])
        out[f"{s} ms"] = float(np.median(v)) if len(v) else float("nan")
    tot = np.asarray(per_stage["total"])
    out["total p90 ms"] = float(np.percentile(tot, 90)) if len(tot) else float("nan")
    out["events/s processed"] = out["events/window"] / (out["total ms"] * 1e-3)
    out["real-time factor"] = window_ms / out["total ms"]  # > 1: faster than the sensor
    return out


def benchmark(repeats: int = 3, quick: bool = False) -> list[dict]:
    from evseg.io import write_npz

    rows = []
    duration_us = 100_000 if quick else 300_000
    rates = [1e6] if quick else [3e5, 1e6, 3e6]
    with tempfile.TemporaryDirectory() as tmp:
        for rate in rates:
            rec = simulated_stream(rate, duration_us)
            path = Path(tmp) / f"sim_{int(rate)}.npz"
            write_npz(rec.stream, path)
            row = {"input": f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s"}
            row.update(time_pipeline(path, repeats))
            rows.append(row)
            if rate == 1e6:
                row = {"input": f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s, overlap on a thread"}
                row.update(time_pipeline(path, repeats, worker="thread"))
                rows.append(row)
                row = {"input": f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s, overlap off"}
                row.update(time_pipeline(path, repeats, overlap=False))
                rows.append(row)
                row = {"input": f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s, --slow-edges"}
                row.update(time_pipeline(path, repeats, slow_edges=True))
                rows.append(row)
                row = {"input": f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s, --mirrors 8"}
                row.update(time_pipeline(path, repeats, mirrors=8))
                rows.append(row)
                for most in (None, 500):
                    row = {"input": f"simulated 346x260, {rec.stream.rate_ev_s / 1e6:.2f} M ev/s, --tracked-mirrors 8"
                                    + ("" if most is None else f" --tracked-max-targets {most}")}
                    row.update(time_pipeline(path, repeats, tracked_mirrors=8, tracked_max_targets=most))
                    rows.append(row)
    if not quick:
        rows += _real_recordings(repeats)
    return rows


def _real_recordings(repeats: int) -> list[dict]:
    from evseg.train.evaluate import shared_data_dir

    shared = shared_data_dir()
    files = [
        "eed_what_is_background/events_t_us_x_y_on.npy",
        "dvxplorer_person_aedat4/sample.aedat4",
        "prophesee_evt_samples/evt3_sample.raw",
        "prophesee_sparks/evt2.raw",
    ]
    rows = []
    for name in files:
        path = shared / name
        if not path.is_file():
            continue
        row = {"input": name}
        row.update(time_pipeline(path, repeats))
        rows.append(row)
    return rows

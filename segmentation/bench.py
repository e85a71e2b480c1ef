"""Benchmark of the segmentation core (``evseg bench seg``).

Input: synthetic normal flow (:mod:`.synthetic`, background + 2 objects, random gradient
directions) on a 346x260 sensor, downsampled with ``cell_px = 0`` so the node count is the
flow count. Rows: time per stage (median over ``repeats``) against node count (1 k, ~1.5 k,
5 k, 20 k) at 12 sampled candidates, then against the candidate count at ~1.5 k nodes.
The first call of each configuration is a warm-up and is not timed. torch uses the caller's
thread setting (``OMP_NUM_THREADS`` / ``torch.set_num_threads``). Wall-clock columns are what
the call took; the ``_cpu`` columns are the process CPU time of the same stages, the cost on a
machine where no other process competes for the cores. ``candidates`` is what fast sampling
returned for ``candidates_asked`` (it returns fewer when the flows are not that varied) plus any
round-0b region candidates.
"""

from __future__ import annotations

import numpy as np

from evseg.segmentation.config import SegmentationConfig
from evseg.segmentation.solver import segment_normal_flow
from evseg.segmentation.synthetic import synthetic_scene


def _row(n_flows: int, n_sampled: int, repeats: int, seed: int = 0) -> dict:
    scene = synthetic_scene(n_flows=n_flows, n_objects=2, seed=seed)
    cfg = SegmentationConfig(cell_px=0.0, n_sampled=n_sampled)
    args = (scene.x, scene.y, scene.t, scene.nx, scene.ny)
    res = segment_normal_flow(*args, config=cfg, sensor_size=scene.sensor_size)  # warm-up
    times = {k: [] for k in ("preprocessing", "initialization", "labeling_fitting", "outputs",
                             "initialization_cpu", "labeling_fitting_cpu")}
    for _ in range(repeats):
        res = segment_normal_flow(*args, config=cfg, sensor_size=scene.sensor_size)
        for k in times:
            times[k].append(res.timings[k])
    med = {k: float(np.median(v)) for k, v in times.items()}
    return {
        "nodes": len(res.node_index),
        "edges": len(res.edges),
        "candidates_asked": n_sampled,
        "candidates": res.n_candidates,
        "objects_found": res.n_objects,
        "rounds": res.n_rounds,
        "preprocessing_ms": med["preprocessing"],
        "initialization_ms": med["initialization"],
        "labeling_fitting_ms": med["labeling_fitting"],
        "outputs_ms": med["outputs"],
        "total_ms": float(sum(med[k] for k in ("preprocessing", "initialization", "labeling_fitting", "outputs"))),
        "initialization_cpu_ms": med["initialization_cpu"],
        "labeling_fitting_cpu_ms": med["labeling_fitting_cpu"],
    }


def benchmark(repeats: int = 5, quick: bool = False) -> list[dict]:
    """Rows of median stage times (ms) by node count and by candidate count."""
    sizes = [1000, 1500] if quick else [1000, 1500, 5000, 20000]
    candidates = [6, 12] if quick else [6, 12, 24]
    rows = [_row(n, 12, repeats) for n in sizes]
    rows += [_row(1500, c, repeats) for c in candidates if c != 12]
    return rows

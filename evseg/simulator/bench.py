"""Benchmark of the simulator (``evseg bench sim``): wall time to simulate recordings.

The project's speed goal: 1 s of a 346x260 scene at about 1 M events/s in under 30 s on a
2-core machine. Each row simulates one preset (seed 0) and reports the event count, the event
rate of the recording and the median wall time over ``repeats`` runs.
"""

from __future__ import annotations

import time

import numpy as np

# (preset, sensor override or None, duration in s); quick runs use the first row, shortened.
CASES = [
    ("evimo_like", None, 1.0),
    ("eed_like", None, 1.0),
    ("ego_only", None, 1.0),
    ("driving_like", None, 0.5),
    ("driving_like", (1280, 720), 0.2),
]


def benchmark(repeats: int = 3, quick: bool = False) -> list[dict]:
    """Rows: preset, sensor, simulated seconds, events, rate (M ev/s), sub-steps, median wall
    time (s) and wall time per simulated second."""
    from evseg.simulator import load_scene_preset, simulate
    from evseg.simulator.engine import substep_count

    cases = [("evimo_like", None, 0.1)] if quick else CASES
    rows = []
    for preset, sensor, duration_s in cases:
        cfg = load_scene_preset(preset)
        if sensor is not None:
            cfg = cfg.with_sensor_size(*sensor)
        duration_us = int(duration_s * 1e6)
        times = []
        rec = None
        for _ in range(repeats):
            t0 = time.perf_counter()
            rec = simulate(cfg, seed=0, duration_us=duration_us)
            times.append(time.perf_counter() - t0)
        wall = float(np.median(times))
        rows.append({
            "preset": preset,
            "sensor": f"{cfg.sensor.width}x{cfg.sensor.height}",
            "sim_s": duration_s,
            "events": len(rec),
            "rate_Mev_s": len(rec) / duration_s / 1e6,
            "substeps": substep_count(rec.scene, cfg, duration_us),
            "wall_s": wall,
            "wall_per_sim_s": wall / duration_s,
        })
    return rows

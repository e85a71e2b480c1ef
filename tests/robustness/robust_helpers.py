"""Small input generators shared by the robustness tests."""

from __future__ import annotations

import numpy as np

from evseg.events import EVENT_DTYPE


def random_events(n: int, sensor_size: tuple[int, int], t0_us: int = 0, span_us: int = 10_000,
                  seed: int = 0) -> np.ndarray:
    """``n`` events uniform on the sensor and over ``[t0_us, t0_us + span_us)``, sorted by t."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["x"] = rng.integers(0, sensor_size[0], n)
    ev["y"] = rng.integers(0, sensor_size[1], n)
    ev["t"] = np.sort(rng.integers(t0_us, t0_us + span_us, n))
    ev["p"] = rng.choice([-1, 1], n)
    return ev

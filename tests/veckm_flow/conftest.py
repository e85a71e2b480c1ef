"""Fixtures of the normal-flow tests: small synthetic slices and a random-weights ONNX model."""

from __future__ import annotations

import numpy as np
import pytest

from evseg.events import EVENT_DTYPE


def random_slice(n: int, sensor_size: tuple[int, int], span_us: int = 20_000, seed: int = 0) -> np.ndarray:
    """``n`` events uniformly on the sensor and in time, sorted by t."""
    rng = np.random.default_rng(seed)
    ev = np.empty(n, EVENT_DTYPE)
    ev["x"] = rng.integers(0, sensor_size[0], n)
    ev["y"] = rng.integers(0, sensor_size[1], n)
    ev["t"] = np.sort(rng.integers(0, span_us, n)) + 1_000_000
    ev["p"] = rng.choice([-1, 1], n)
    return ev


@pytest.fixture
def make_slice():
    """The :func:`random_slice` factory."""
    return random_slice


@pytest.fixture(scope="session")
def random_onnx(tmp_path_factory):
    """(path, head, cfg) of a randomly initialised head exported to ONNX (small d for speed)."""
    from evseg.export import export_onnx
    from evseg.veckm_flow import EncodingConfig, build_head

    cfg = EncodingConfig(d=16, window_px=4, seed=3)
    head = build_head(cfg, seed=0, hidden=32)
    path = tmp_path_factory.mktemp("onnx") / "random_head.onnx"
    export_onnx(head, cfg, path)
    return path, head, cfg

"""Fixtures for the training tests: a tiny recording with known optical flow."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

EDGE_FLOW_PX_S = (800.0, 300.0)
EDGE_SENSOR = (40, 30)


def write_edge_recording(path: Path, dense: bool) -> int:
    """Vertical edges sweeping right at 800 px/s, true optical flow (800, 300) px/s.

    Only the x component is visible to an event camera (the aperture problem): the true
    normal flow is (800, 0). Written in the layout of :func:`evseg.train.data.load_flow_recording`
    with per-event flow or with two dense flow maps. Returns the number of events.
    """
    vx, vy = EDGE_FLOW_PX_S
    w, h = EDGE_SENSOR
    xs, ys, ts = [], [], []
    for x0 in (-30.0, -15.0, 0.0, 5.0):
        for col in range(w):
            t = (col - x0) / vx * 1e6
            if 0 <= t < 60_000:
                for row in range(h):
                    xs.append(col)
                    ys.append(row)
                    ts.append(int(t) + row % 3)  # a little timestamp jitter along the edge
    order = np.argsort(ts, kind="stable")
    x, y, t = np.array(xs)[order], np.array(ys)[order], np.array(ts, dtype=np.int64)[order]
    p = np.where(np.arange(len(x)) % 2 == 0, 1, 0)  # 0/1 polarity: the reader converts
    common = dict(x=x, y=y, t=t, p=p, sensor_size=np.array([w, h]))
    if dense:
        maps = np.zeros((2, h, w, 2), np.float32)
        maps[..., 0], maps[..., 1] = vx, vy
        np.savez(path, **common, flow_maps=maps, flow_t_us=np.array([0, 30_000]))
    else:
        np.savez(path, **common, flow=np.tile(np.float32([vx, vy]), (len(x), 1)))
    return len(x)


@pytest.fixture
def edge_recording(tmp_path: Path) -> Path:
    path = tmp_path / "edge.npz"
    write_edge_recording(path, dense=False)
    return path


@pytest.fixture
def edge_recording_dense(tmp_path: Path) -> Path:
    path = tmp_path / "edge_dense.npz"
    write_edge_recording(path, dense=True)
    return path


@pytest.fixture
def edge_truth() -> tuple[tuple[float, float], tuple[int, int]]:
    """(optical flow px/s, sensor size) of the edge recordings."""
    return EDGE_FLOW_PX_S, EDGE_SENSOR

"""The long recording of the memory benchmark is what it claims: tiles back to back, sorted."""

from __future__ import annotations

import numpy as np

from evseg.io import open_recording
from evseg.memory_bench import SENSOR, TILE_US, write_long_recording

from robust_helpers import random_events


def test_long_recording_repeats_the_tile_with_time_offsets(tmp_path):
    tile = random_events(500, SENSOR, span_us=TILE_US, seed=0)
    before = tile.copy()
    n = write_long_recording(tmp_path / "long.h5", tile, 3)
    assert n == 1500
    np.testing.assert_array_equal(tile, before)  # the tile is not shifted in place
    with open_recording(tmp_path / "long.h5", chunk_events=400) as rec:
        assert rec.sensor_size == SENSOR
        ev = np.concatenate(list(rec.chunks()))  # the reader checks the order across chunks
    assert len(ev) == 1500
    for k in range(3):
        part = ev[k * 500 : (k + 1) * 500]
        np.testing.assert_array_equal(part["t"], tile["t"] + k * TILE_US)
        np.testing.assert_array_equal(part[["x", "y", "p"]], tile[["x", "y", "p"]])

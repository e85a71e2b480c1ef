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


def test_result_writer_keeps_no_masks_in_memory(tmp_path):
    """Per window the writer holds only packed times and boxes (16 + 48 bytes per box), not the
    masks (11 kB each at 346x260): measured with tracemalloc over 300 windows x 3 objects."""
    import tracemalloc

    from evseg.results import ResultWriter, load_result

    size = (346, 260)
    mask = np.zeros(size[::-1], bool)
    mask[10:50, 20:80] = True
    boxes = {1: (20, 10, 79, 49), 2: (1, 1, 5, 5), 3: (100, 100, 120, 130)}
    w = ResultWriter(tmp_path / "r.npz", None, size, with_masks=True)
    tracemalloc.start()
    try:
        for k in range(300):
            w.add_labels(np.zeros(50, np.int16))
            w.add_window(k * 10_000, k * 10_000 + 10_000, boxes, {oid: mask for oid in boxes})
        held, _ = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # 300 x 3 masks would be 10 MB; packed boxes and times are 48 kB (array growth slack x2).
    assert held < 300 * 1024
    w.close()
    r = load_result(tmp_path / "r.npz")
    assert r.masks.shape == (900, (346 * 260 + 7) // 8) and len(r.boxes) == 900
    np.testing.assert_array_equal(r.mask(899), mask)


def test_long_recording_on_another_sensor(tmp_path):
    tile = random_events(50, (346, 260), span_us=TILE_US, seed=1)
    write_long_recording(tmp_path / "full.h5", tile, 2, sensor=(346, 260))
    with open_recording(tmp_path / "full.h5") as rec:
        assert rec.sensor_size == (346, 260)
        assert sum(len(c) for c in rec.chunks()) == 100


def test_unknown_tile_kind_is_refused_before_any_work():
    import pytest

    from evseg.memory_bench import benchmark

    with pytest.raises(ValueError, match="'huge'"):
        benchmark(cases=(("planefit", 10), ("learned", 10, "huge")))

import numpy as np
import pytest

from evseg.live_bench import benchmark, time_live


def test_quick_live_benchmark_row_names_its_input_and_adds_up():
    """`evseg bench live --quick`: the 1 M events/s stream replayed at the sensor's pace with a
    20 ms lag bound, with the worker process and without overlap; segmented and dropped windows
    make up the stream's windows."""
    rows = benchmark(repeats=1, quick=True)
    assert [r["worker"] for r in rows] == ["process", "none (overlap off)"]
    for row in rows:
        assert row["input"].startswith("simulated 346x260, ") and row["max lag ms"] == 20
        assert row["windows in stream"] == 30
        assert 0 < row["segmented %"] <= 100
        assert row["segmented %"] + row["dropped %"] == pytest.approx(100, abs=1e-9)  # float rounding only
        assert row["latency p90 ms"] >= row["latency ms"] > 0 and row["lag ms"] >= 0


def test_without_a_lag_bound_every_window_is_segmented():
    from evseg.simulator import load_scene_preset, simulate

    stream = simulate(load_scene_preset("evimo_like"), seed=1001, duration_us=40_000).stream
    row = time_live(stream.events, stream.sensor_size, repeats=1, max_lag_us=None, speed=4.0)
    assert row["windows in stream"] == 4 and row["segmented %"] == 100 and row["dropped %"] == 0
    assert np.isfinite(row["ms between results"])

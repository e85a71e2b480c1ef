import numpy as np

from evseg.veckm_flow.bench import SENSOR, benchmark, synthetic_slice
from evseg.events import validate_events


def test_synthetic_slice_has_exact_size_and_is_valid():
    ev = synthetic_slice(20_000, seed=3)
    assert len(ev) == 20_000
    validate_events(ev, SENSOR)
    assert ev["t"][-1] - ev["t"][0] < 20_000


def test_slow_slice_is_a_window_with_its_history():
    from evseg.veckm_flow.bench import slow_slice

    history, sl, targets = slow_slice(20_000)
    assert len(sl) == 20_000 and len(history) > 10_000
    validate_events(np.concatenate([history, sl]), SENSOR)
    assert history["t"][-1] <= sl["t"][0]
    assert sl["t"][targets].min() >= sl["t"][-1] - 10_000  # the targets lie in the last 10 ms


def test_quick_benchmark_rows_name_their_input():
    rows = benchmark(repeats=1, quick=True)
    assert len(rows) == 7 and all(r.keys() == rows[0].keys() for r in rows)
    assert [r["events"] for r in rows] == [10_000] + [100_000] * 6
    assert rows[1]["targets"] == 10_000 and rows[-1]["method"] == "plane-fit baseline"
    assert rows[2]["method"].endswith(", first look only)") and rows[2]["fast_edges_ms"] == 0
    # the synthetic edges move at 200-2,000 px/s: the headline slice gets the second look
    assert rows[1]["fast_edges_ms"] > 0 and rows[1]["slow_edges_ms"] == 0
    # slow edges: the slow look runs only with the history before the slice
    assert rows[3]["history_events"] == 0 and rows[3]["slow_edges_ms"] == 0
    assert rows[4]["history_events"] > 50_000 and rows[4]["slow_edges_ms"] > 0
    assert rows[3]["targets"] == rows[4]["targets"] == 10_000
    # the same slice and history through 8 mirror looks (evseg flow --mirrors 8)
    assert [r["mirrors"] for r in rows] == [1, 1, 1, 1, 1, 8, 1]
    assert rows[5]["method"].endswith("8 mirror looks)") and rows[5]["history_events"] == rows[4]["history_events"]
    assert rows[5]["slow_edges_ms"] > 0
    assert all(np.isfinite(r["total_ms"]) and r["total_ms"] > 0 for r in rows)


def test_benchmark_times_the_given_model(tmp_path):
    """`evseg bench flow --model M` times M, and its rows say so (a 16-wide head here)."""
    from evseg.export import export_onnx
    from evseg.veckm_flow import EncodingConfig, build_head

    cfg = EncodingConfig(polarity=True)
    path = tmp_path / "small_head.onnx"
    export_onnx(build_head(cfg, hidden=16), cfg, path)
    rows = benchmark(repeats=1, quick=True, model_path=path)
    assert [r["method"] for r in rows[:2]] == ["learned (model small_head.onnx)"] * 2

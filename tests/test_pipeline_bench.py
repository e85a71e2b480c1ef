import numpy as np

from evseg.pipeline_bench import benchmark


def test_quick_pipeline_benchmark_rows_name_their_input():
    """`evseg bench pipeline --quick`: the 1 M events/s stream with the worker process, on a
    thread, without overlap, with the slow-edge look, with 8 mirror looks and with 8 looks in the
    tracked boxes (all of them, and at most 500 targets); every row has the same stage columns
    and positive medians."""
    rows = benchmark(repeats=1, quick=True)
    assert [r["input"].split(", ", 2)[-1] for r in rows] == [
        rows[0]["input"].split(", ", 2)[-1], "overlap on a thread", "overlap off", "--slow-edges", "--mirrors 8",
        "--tracked-mirrors 8", "--tracked-mirrors 8 --tracked-max-targets 500"]
    assert rows[0]["input"].startswith("simulated 346x260, ")
    assert all(r.keys() == rows[0].keys() for r in rows)
    assert all(r["windows"] == 10 and np.isfinite(r["total ms"]) and r["total ms"] > 0 for r in rows)
    assert all(r["flow ms"] > 0 for r in rows)


def test_simulated_stream_has_the_rate_it_is_asked_for():
    """The latency benchmark's streams are the issue's 0.3 and 3 M events/s (346x260) over
    the span timed, within the 5 % the calibration aims at (it once gave 0.18 M for 0.3 M:
    the rate was measured on the first 50 ms only, which fire faster than the rest)."""
    from evseg.pipeline_bench import simulated_stream

    for rate in (3e5, 3e6):
        rec = simulated_stream(rate, 100_000)
        assert tuple(rec.stream.sensor_size) == (346, 260)
        assert abs(rec.stream.rate_ev_s / rate - 1) <= 0.05, rec.stream.rate_ev_s


def test_the_pipeline_is_warmed_up_once_before_any_window_is_timed(tmp_path, monkeypatch):
    """The one-time set-up (the worker process's ~2 s start) must be in no window's time: in
    --quick's 10 windows it was the p90."""
    from evseg.io import write_npz
    from evseg.pipeline import MotionSegmentationPipeline
    from evseg.pipeline_bench import simulated_stream, time_pipeline

    calls = []
    warm_up, run = MotionSegmentationPipeline.warm_up, MotionSegmentationPipeline.run
    monkeypatch.setattr(MotionSegmentationPipeline, "warm_up", lambda self: calls.append("warm_up") or warm_up(self))
    monkeypatch.setattr(MotionSegmentationPipeline, "run", lambda self, *a, **k: calls.append("run") or run(self, *a, **k))
    path = write_npz(simulated_stream(3e5, 30_000).stream, tmp_path / "s.npz")
    row = time_pipeline(path, repeats=2, flow="planefit", overlap=False)
    assert calls == ["warm_up", "run", "run"] and row["windows"] == 3

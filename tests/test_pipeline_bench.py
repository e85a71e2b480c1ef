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

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

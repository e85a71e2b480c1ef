"""Property-based tests (hypothesis) of everything downstream of the readers.

Inputs are drawn small (tiny sensors, at most a few hundred events) so that several hundred
examples run in seconds. Each test states the invariant it checks; an exception other than the
documented error types fails the test. Example counts (max_examples) are summed in the report
of issue 6; the readers' own fuzzing lives in tests/io.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, event, given, settings
from hypothesis import strategies as st

from evseg.errors import EventDataError
from evseg.events import EVENT_DTYPE, EventStream, make_events, validate_events
from evseg.windows import stream_time_windows, time_window_bounds, time_window_slices

FAST = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])


# ------------------------------------------------------------------ strategies
@st.composite
def sorted_times(draw, max_size: int = 80, max_step: int = 30_000):
    """Sorted int64 timestamps (us): duplicates, zero steps and big jumps all likely."""
    steps = draw(st.lists(st.one_of(st.just(0), st.integers(0, 50), st.integers(0, max_step),
                                    st.just(10_000_000)),  # a 10 s jump
                          max_size=max_size))
    start = draw(st.integers(0, 2**40))
    return start + np.cumsum(np.asarray(steps, dtype=np.int64)) if steps else np.empty(0, np.int64)


@st.composite
def event_arrays(draw, sensor=(16, 12), max_size: int = 80):
    t = draw(sorted_times(max_size=max_size))
    n = len(t)
    w, h = sensor
    x = draw(st.lists(st.integers(0, w - 1), min_size=n, max_size=n))
    y = draw(st.lists(st.integers(0, h - 1), min_size=n, max_size=n))
    p = draw(st.lists(st.sampled_from([-1, 1]), min_size=n, max_size=n))
    return make_events(x, y, t, p)


@st.composite
def chunkings(draw, n: int):
    """Cut points of ``range(n)`` into chunks, empty chunks included."""
    cuts = sorted(draw(st.lists(st.integers(0, n), max_size=8)))
    bounds = [0, *cuts, n]
    return list(zip(bounds[:-1], bounds[1:]))


WINDOWS_US = [1, 7, 100, 1_000, 10_000, 33_333, 10_000_000]
MAX_WINDOWS = 2_000  # per example: the checks below loop over windows in Python


def window_and_stride(data, t: np.ndarray) -> tuple[int, int | None]:
    """A window and stride (us) giving at most MAX_WINDOWS windows over the span of ``t``."""
    span = int(t[-1] - t[0]) if len(t) else 0
    fits = [w for w in WINDOWS_US if span // w < MAX_WINDOWS]  # 10 s always fits
    window = data.draw(st.sampled_from(fits), label="window_us")
    stride = data.draw(st.one_of(st.none(), st.sampled_from(fits)), label="stride_us")
    return window, stride


# ------------------------------------------------------------------ events and windows
@settings(max_examples=150, **FAST)
@given(data=st.data(), t=sorted_times())
def test_time_window_slices_cover_exactly_the_events_in_each_window(data, t):
    window, stride = window_and_stride(data, t)
    slices = time_window_slices(t, window, stride)
    if len(t) == 0:
        assert slices == []
        return
    starts = time_window_bounds(int(t[0]), int(t[-1]), window, stride)
    assert len(slices) == len(starts) and starts[0] == t[0] and starts[-1] <= t[-1]
    for s, t0 in zip(slices, starts):
        inside = np.flatnonzero((t >= t0) & (t < t0 + window))
        assert list(range(s.start, s.stop)) == inside.tolist()
    if stride is None or stride == window:  # back-to-back windows partition the events
        assert slices[0].start == 0 and slices[-1].stop == len(t)
        assert all(a.stop == b.start for a, b in zip(slices[:-1], slices[1:]))


@settings(max_examples=150, **FAST)
@given(data=st.data())
def test_stream_time_windows_equal_in_memory_slicing_for_any_chunking(data):
    ev = data.draw(event_arrays())
    window, stride = window_and_stride(data, ev["t"])
    before = ev.copy()
    chunks = [ev[a:b] for a, b in data.draw(chunkings(len(ev)))]
    streamed = list(stream_time_windows(chunks, window, stride))
    ref = time_window_slices(ev["t"], window, stride)
    assert len(streamed) == len(ref)
    for k, (w, s) in enumerate(zip(streamed, ref)):
        assert w.index == k and w.t1_us - w.t0_us == window
        assert w.first_event == s.start
        np.testing.assert_array_equal(w.events, ev[s])
    np.testing.assert_array_equal(ev, before)  # the input is never modified


@settings(max_examples=100, **FAST)
@given(data=st.data(), ev=event_arrays())
def test_event_stream_windows_are_views_covering_every_event_once(data, ev):
    window, _ = window_and_stride(data, ev["t"])
    stream = EventStream(ev, (16, 12)).validate()
    parts = list(stream.time_windows(window))
    assert sum(len(p) for p in parts) == len(ev)
    if len(ev):
        np.testing.assert_array_equal(np.concatenate([p.events for p in parts]), ev)
        assert all(p.events.base is not None for p in parts if len(p))  # views, not copies
        assert stream.duration_us == int(ev["t"][-1] - ev["t"][0]) >= 0


@settings(max_examples=100, **FAST)
@given(ev=event_arrays(), i=st.integers(0, 1000), what=st.sampled_from(["t", "x", "y"]))
def test_validate_events_names_the_first_bad_event(ev, i, what):
    """A valid 16x12 recording with one event corrupted (time going back, coordinate off the
    sensor) is rejected naming the field and that event's index; the clean one passes."""
    assume(len(ev) >= 2)
    validate_events(ev, (16, 12))
    bad = ev.copy()
    i = 1 + i % (len(ev) - 1)
    if what == "t":
        bad["t"][i] = bad["t"][i - 1] - 1
        with pytest.raises(EventDataError, match=f"field 't' is not sorted: event {i} has t="):
            validate_events(bad, (16, 12))
    else:
        bad[what][i] = 16 if what == "x" else 12
        with pytest.raises(EventDataError, match=f"field '{what}' = {bad[what][i]} at event {i} is outside"):
            validate_events(bad, (16, 12))
    validate_events(bad, None, check_sorted=what != "t")  # without the violated check: accepted
    np.testing.assert_array_equal(ev[:i], bad[:i])


@settings(max_examples=50, **FAST)
@given(p=st.lists(st.one_of(st.booleans(), st.integers(-3, 3)), max_size=20))
def test_make_events_polarity_is_signed_and_input_untouched(p):
    n = len(p)
    arr = np.asarray(p) if n else np.empty(0)
    before = arr.copy()
    ev = make_events(np.zeros(n), np.zeros(n), np.arange(n), arr)
    assert ev.dtype == EVENT_DTYPE and set(ev["p"].tolist()) <= {-1, 1}
    np.testing.assert_array_equal(ev["p"] == 1, arr > 0)
    np.testing.assert_array_equal(arr, before)


# ------------------------------------------------------------------ pre-processing / graph
@st.composite
def flow_points(draw):
    """Positions with duplicates / collinear runs / 0-3 points, flows with NaN, inf and zeros."""
    n = draw(st.one_of(st.integers(0, 3), st.integers(0, 60)))
    layout = draw(st.sampled_from(["grid", "float", "line", "pixel", "diagonal"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**31)))
    if layout == "grid":
        x, y = rng.integers(0, 6, n).astype(float), rng.integers(0, 4, n).astype(float)
    elif layout == "float":
        x, y = rng.uniform(0, 30, n), rng.uniform(0, 20, n)
    elif layout == "line":
        x, y = rng.uniform(0, 30, n), np.full(n, 7.0)
    elif layout == "pixel":
        x, y = np.full(n, 3.0), np.full(n, 4.0)
    else:
        x = rng.integers(0, 20, n).astype(float)
        y = 2.0 * x + 1.0
    special = np.array([np.nan, np.inf, -np.inf, 0.0, 1e-9, 1e6])
    nx, ny = rng.normal(0, 100, n), rng.normal(0, 100, n)
    hit = rng.random(n) < draw(st.sampled_from([0.0, 0.2, 1.0]))
    nx[hit] = rng.choice(special, hit.sum())
    unc = rng.uniform(0, 1, n) if draw(st.booleans()) else None
    t = np.sort(rng.integers(0, 10_000, n))
    return x, y, t, nx, ny, unc


@settings(max_examples=200, **FAST)
@given(pts=flow_points(), cell_px=st.sampled_from([0.0, 0.5, 1.0, 3.0]),
       node_window_us=st.sampled_from([None, 0, 2_000]))
def test_node_graph_is_valid_for_any_points(pts, cell_px, node_window_us):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from evseg.segmentation.preprocessing import build_node_graph

    x, y, t, nx, ny, unc = pts
    inputs = [a.copy() for a in (x, y, t, nx, ny)]
    g = build_node_graph(x, y, t, nx, ny, unc, cell_px=cell_px, node_window_us=node_window_us)
    m, e = len(g), g.edges
    for a, b in zip(inputs, (x, y, t, nx, ny)):
        np.testing.assert_array_equal(a, b)  # inputs not modified
    assert g.index.dtype == np.int64 and np.all(np.diff(g.index) > 0) and (m == 0 or g.index[-1] < len(x))
    assert np.isfinite(g.nx).all() and np.isfinite(g.ny).all()
    assert np.all(np.hypot(g.nx, g.ny) >= 1.0)  # min_flow_px_s: slow flows carry no direction
    assert np.all((g.confidence > 0) & (g.confidence <= 1))
    assert e.dtype == np.int64 and e.shape == (len(e), 2)
    assert np.all(e[:, 0] < e[:, 1]) and np.all(e[:, 1] < max(m, 1))
    assert len({tuple(r) for r in e.tolist()}) == len(e)
    assert len(np.unique(np.column_stack([g.x, g.y]), axis=0)) == m  # no duplicate node positions
    if m == 2:
        assert e.tolist() == [[0, 1]]
    if m >= 2:
        ncomp, _ = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m)))
        assert ncomp == 1
    else:
        assert len(e) == 0
    np.testing.assert_allclose(g.edge_length, np.hypot(g.x[e[:, 0]] - g.x[e[:, 1]], g.y[e[:, 0]] - g.y[e[:, 1]]))


# ------------------------------------------------------------------ result writer
@st.composite
def writer_ops(draw):
    """A sequence of writer calls: labels, unassigned runs, windows with boxes."""
    ops = []
    for _ in range(draw(st.integers(0, 8))):
        kind = draw(st.sampled_from(["labels", "unassigned", "window"]))
        if kind == "labels":
            ops.append(("labels", draw(st.lists(st.integers(-1, 300), max_size=20))))
        elif kind == "unassigned":
            ops.append(("unassigned", draw(st.integers(0, 30))))
        else:
            boxes = draw(st.dictionaries(st.integers(1, 50), st.tuples(st.integers(0, 7), st.integers(0, 4),
                                                                       st.integers(0, 7), st.integers(0, 4)),
                                         max_size=3))
            ops.append(("window", boxes))
    return ops


@settings(max_examples=100, **FAST)
@given(ops=writer_ops(), extra=st.one_of(st.none(), st.integers(0, 10)), partial=st.booleans(),
       masks=st.booleans())
def test_result_writer_round_trips_any_sequence(ops, extra, partial, masks):
    from evseg.results import ResultWriter, load_result

    size = (8, 5)
    labels: list[int] = []
    windows, boxes, mask_rows = [], [], []
    n_labels = sum(len(v) if k == "labels" else v for k, v in ops if k != "window")
    n_events = None if extra is None else n_labels + extra
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "sub" / "r.npz"
        w = ResultWriter(path, n_events, size, config_yaml="x: 1\n", with_masks=masks)
        for kind, v in ops:
            if kind == "labels":
                w.add_labels(np.asarray(v, dtype=np.int64))
                labels += v
            elif kind == "unassigned":
                w.add_unassigned(v)
                labels += [-1] * v
            else:
                k = len(windows)
                windows.append((10 * k, 10 * k + 10))
                m = {oid: np.arange(40).reshape(5, 8) % (oid + 1) == 0 for oid in v}
                w.add_window(10 * k, 10 * k + 10, v, m if masks else None)
                for oid in sorted(v):
                    boxes.append([k, oid, *v[oid]])
                    mask_rows.append(m[oid])
        w.close(partial=partial)
        r = load_result(path)
        assert sorted(p.name for p in path.parent.iterdir()) == ["r.npz"]
    expected = labels + [-1] * (extra or 0)
    assert r.label.dtype == np.int16 and r.label.tolist() == expected
    assert r.partial == partial and r.n_events_processed == len(labels)
    assert r.window_t0_us.tolist() == [a for a, _ in windows] and r.window_t1_us.tolist() == [b for _, b in windows]
    assert r.boxes.shape == (len(boxes), 6) and r.boxes.tolist() == boxes
    assert r.sensor_size == size and r.config == "x: 1\n"
    if masks:
        for row, m in enumerate(mask_rows):
            np.testing.assert_array_equal(r.mask(row), m)
    else:
        assert r.masks is None


# ------------------------------------------------------------------ tracker
boxes_strategy = st.dictionaries(
    st.integers(1, 6),
    st.tuples(st.integers(0, 30), st.integers(0, 20), st.integers(0, 15), st.integers(0, 15)).map(
        lambda b: (b[0], b[1], b[0] + b[2], b[1] + b[3])),
    max_size=5)


@settings(max_examples=150, **FAST)
@given(frames=st.lists(st.tuples(boxes_strategy, st.tuples(st.floats(-50, 50), st.floats(-50, 50))), max_size=8))
def test_tracker_ids_are_unique_and_never_reused(frames):
    from evseg.tracking import ObjectTracker

    tr = ObjectTracker()
    retired: set[int] = set()
    previous: set[int] = set()
    for boxes, (dx, dy) in frames:
        next_before = tr.next_id
        mapping = tr.update(boxes)
        assert set(mapping) == set(boxes)
        ids = list(mapping.values())
        assert len(set(ids)) == len(ids)  # one id per object per window
        assert not (set(ids) & retired)  # a dropped track's id never comes back
        new = [i for i in ids if i >= next_before]
        assert sorted(new) == list(range(next_before, next_before + len(new)))  # new ids in order
        assert all(1 <= i < tr.next_id for i in ids)
        retired |= previous - set(tr.tracks)
        previous = set(tr.tracks)
        assert set(ids) <= set(tr.tracks)
        tr.predict({oid: (dx, dy) for oid in ids}, sensor_size=(46, 36))
        for x0, y0, x1, y1 in tr.tracks.values():
            assert 0 <= x0 <= x1 <= 45 and 0 <= y0 <= y1 <= 35  # predicted boxes stay on the sensor


# ------------------------------------------------------------------ whole pipeline
PIPE_SIZE = (48, 32)


@st.composite
def pipeline_events(draw, dense: bool = False):
    """0 to 1500 events over 0 to 25 ms (up to 3 windows) in one of several layouts;
    ``dense``: 1500 uniform events in 5 ms (enough nodes for a 16x12 px object)."""
    n = 1500 if dense else draw(st.sampled_from([0, 1, 2, 3, 4, 7, 30, 150, 600, 1500]), label="n_events")
    span = 5_000 if dense else draw(st.sampled_from([0, 1, 5_000, 25_000]), label="span_us")
    layout = "uniform" if dense else draw(st.sampled_from(["uniform", "pixel", "row", "diagonal", "blob"]),
                                          label="layout")
    rng = np.random.default_rng(draw(st.integers(0, 2**31), label="seed"))
    w, h = PIPE_SIZE
    x, y = rng.integers(0, w, n), rng.integers(0, h, n)
    if layout == "pixel":
        x, y = np.full(n, 3), np.full(n, 5)
    elif layout == "row":
        y = np.full(n, 6)
    elif layout == "diagonal":
        y = x % h
    elif layout == "blob":
        x, y = rng.integers(6, 22, n), rng.integers(6, 18, n)
    t = np.sort(rng.integers(0, span + 1, n)) + draw(st.sampled_from([0, 2**40]), label="t_origin")
    return make_events(x, y, t, rng.choice([-1, 1], n))


@st.composite
def pipeline_inputs(draw):
    """Events (see pipeline_events) with random, often broken per-event flows; one example in
    three is a dense scene with a moving patch, so that the object paths run too."""
    patch_scene = draw(st.integers(0, 2), label="moving patch scene") == 0
    ev = draw(pipeline_events(dense=patch_scene))
    n = len(ev)
    rng = np.random.default_rng(draw(st.integers(0, 2**31), label="flow_seed"))
    mode = "two motions" if patch_scene else draw(st.sampled_from(["translation", "random", "two motions", "broken"]),
                                                   label="flow")
    if mode == "translation":
        a = rng.uniform(0, np.pi, n)
        s = np.cos(a) * 200 - np.sin(a) * 50
        nx, ny = s * np.cos(a), s * np.sin(a)
    elif mode == "random":
        nx, ny = rng.normal(0, 300, n), rng.normal(0, 300, n)
    elif mode == "two motions":
        # A 16x12 px patch moves right fast, the rest (the background) slowly left.
        patch = (ev["x"] >= 6) & (ev["x"] < 22) & (ev["y"] >= 6) & (ev["y"] < 18)
        a = rng.uniform(0, np.pi, n)
        s = np.cos(a) * np.where(patch, 400.0, -100.0)
        nx, ny = s * np.cos(a), s * np.sin(a)
    else:
        nx, ny = rng.normal(0, 300, n), rng.normal(0, 300, n)
        special = np.array([np.nan, np.inf, -np.inf, 0.0, 1e-12, 1e7, -1e7])
        hit = rng.random(n) < 0.5
        nx[hit] = rng.choice(special, hit.sum())
        ny[rng.random(n) < 0.2] = np.nan
    # Flow for a random subset of the events (a flow file need not cover every event).
    share = draw(st.sampled_from([1.0, 0.5, 0.0]), label="share with flow")
    keep = np.sort(rng.choice(n, size=int(round(share * n)), replace=False))
    flow = {"index": keep.astype(np.int64), "nx": nx[keep].astype(np.float32), "ny": ny[keep].astype(np.float32)}
    if draw(st.booleans(), label="uncertainty"):
        flow["uncertainty"] = rng.uniform(0, 1, len(keep)).astype(np.float32)
    return ev, flow


def _coverage(results, ev) -> None:
    """Label the example for --hypothesis-show-statistics (how many found objects, etc.)."""
    event(f"events: {'0' if len(ev) == 0 else '1-5' if len(ev) <= 5 else '6-50' if len(ev) <= 50 else '>50'}")
    event(f"objects found: {'yes' if any(r.boxes for r in results) else 'no'}")


def _check_run(results, ev) -> None:
    _coverage(results, ev)
    assert sum(len(r.events) for r in results) == len(ev)
    w, h = PIPE_SIZE
    for r in results:
        assert r.labels.dtype == np.int16 and len(r.labels) == len(r.events)
        assert set(np.unique(r.labels).tolist()) <= {-1, 0} | set(r.boxes)
        for x0, y0, x1, y1 in r.boxes.values():
            assert 0 <= x0 <= x1 < w and 0 <= y0 <= y1 < h
        assert set(r.masks) == set(r.boxes)


@settings(max_examples=150, **FAST)
@given(inp=pipeline_inputs(), window=st.sampled_from([2_000, 10_000]), stride=st.sampled_from([None, 5_000]))
def test_pipeline_with_precomputed_flow_gives_defined_labels(inp, window, stride):
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    ev, flow = inp
    before = {k: v.copy() for k, v in flow.items()}
    ev_before = ev.copy()
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed", window_us=window, stride_us=stride),
                                      sensor_size=PIPE_SIZE)
    results = list(pipe.run(EventStream(ev, PIPE_SIZE), precomputed_flow=flow))
    if stride is None:
        _check_run(results, ev)
    else:  # overlapping windows / gaps: events are not partitioned, per-window contract only
        _coverage(results, ev)
        for r in results:
            assert len(r.labels) == len(r.events)
            assert set(np.unique(r.labels).tolist()) <= {-1, 0} | set(r.boxes)
    np.testing.assert_array_equal(ev, ev_before)
    for k in flow:
        np.testing.assert_array_equal(flow[k], before[k])


@settings(max_examples=60, **FAST)
@given(ev=pipeline_events())
def test_pipeline_with_planefit_flow_gives_defined_labels(ev):
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    pipe = MotionSegmentationPipeline(PipelineConfig(flow="planefit"), sensor_size=PIPE_SIZE)
    _check_run(list(pipe.run(EventStream(ev, PIPE_SIZE))), ev)


@settings(max_examples=25, **FAST)
@given(ev=pipeline_events())
def test_pipeline_with_learned_flow_gives_defined_labels(ev, random_onnx):
    """The learned flow (a random-weights head: no trained model ships yet) on the same inputs."""
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    cfg = PipelineConfig(flow="learned", model_path=str(random_onnx), threads=1)
    pipe = MotionSegmentationPipeline(cfg, sensor_size=PIPE_SIZE)
    _check_run(list(pipe.run(EventStream(ev, PIPE_SIZE))), ev)

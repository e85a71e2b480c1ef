"""The streaming pipeline and the `evseg segment` job, on a short simulated recording."""

import re

from dataclasses import replace

import numpy as np
import pytest

from evseg.cli import main
from evseg.errors import ConfigError
from evseg.events import EventStream
from evseg.metrics import summarize
from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig, load_flow_file
from evseg.results import load_result


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    from evseg.simulator import load_scene_preset, save_recording, simulate

    rec = simulate(load_scene_preset("evimo_like"), seed=1001, duration_us=40_000)
    d = tmp_path_factory.mktemp("sim")
    save_recording(rec, d / "sim.npz")
    ok = np.flatnonzero(np.isfinite(rec.normal_flow[:, 0]))
    np.savez(d / "flow.npz", index=ok, nx=rec.normal_flow[ok, 0], ny=rec.normal_flow[ok, 1])
    return rec, d


def _run(rec, flow):
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)
    return list(pipe.run(rec.stream, precomputed_flow=flow))


def test_windows_cover_events_and_labels_are_deterministic(sim):
    rec, d = sim
    flow = load_flow_file(d / "flow.npz", n_events=len(rec.stream))
    a, b = _run(rec, flow), _run(rec, flow)
    t_first = int(rec.stream.events["t"][0])  # windows start at the first event
    assert [r.t0_us for r in a] == [t_first + k * 10_000 for k in range(4)]
    assert sum(len(r.events) for r in a) == len(rec.stream)
    for ra, rb in zip(a, b):
        assert ra.labels.dtype == np.int16 and len(ra.labels) == len(ra.events)
        np.testing.assert_array_equal(ra.labels, rb.labels)
        assert ra.boxes == rb.boxes
        assert set(np.unique(ra.labels)) <= {-1, 0} | set(ra.boxes)


def test_segment_command_writes_schema_with_precomputed_flow(sim, tmp_path):
    rec, d = sim
    out = tmp_path / "result.npz"
    assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--out", str(out),
                 "--masks", "--no-progress"]) == 0
    r = load_result(out)
    assert len(r.label) == len(rec.stream) and r.label.dtype == np.int16
    t_first = int(rec.stream.events["t"][0])
    assert r.window_t0_us.tolist() == [t_first + k * 10_000 for k in range(4)]
    assert (r.window_t1_us - r.window_t0_us == 10_000).all()
    assert r.boxes.shape[1] == 6 and not r.partial
    if len(r.boxes):
        assert r.masks.shape[0] == len(r.boxes)
    assert "window_us: 10000" in r.config


def test_gaps_between_windows_are_unassigned(sim, tmp_path):
    rec, d = sim
    out = tmp_path / "result.npz"
    assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--out", str(out),
                 "--window-ms", "5", "--stride-ms", "10", "--no-progress"]) == 0
    r = load_result(out)
    t = rec.stream.events["t"]
    in_gap = ((t - t[0]) % 10_000) >= 5_000
    assert (r.label[in_gap] == -1).all()


def test_bad_flow_file_and_config_fail_before_work(sim, tmp_path, capsys):
    rec, d = sim
    bad = tmp_path / "flow.npz"
    np.savez(bad, index=np.array([0, 10**9]), nx=np.zeros(2), ny=np.zeros(2))
    assert main(["segment", str(d / "sim.npz"), "--flow", str(bad), "--out", str(tmp_path / "r.npz")]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: key 'index' refers to event 1000000000 but the stream has {len(rec.stream)} events" in err
    assert load_result(tmp_path / "r.npz").partial  # the windows done are kept, flagged partial
    with pytest.raises(ConfigError, match="pipeline.flow"):
        PipelineConfig(flow="magic")


def test_precomputed_mode_needs_flow():
    ev = np.zeros(0, dtype=__import__("evseg").EVENT_DTYPE)
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=(10, 10))
    assert list(pipe.run(EventStream(ev, (10, 10)))) == []


def _calibration(distortion, size=(346, 260)):
    from evseg.calibration import Calibration

    K = np.array([[200.0, 0, size[0] / 2], [0, 200.0, size[1] / 2], [0, 0, 1]])
    return Calibration(K, np.asarray(distortion, dtype=float), size)


def test_calibrated_pipeline_labels_every_window(sim):
    rec, d = sim
    flow = load_flow_file(d / "flow.npz")
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size,
                                      calibration=_calibration([-0.05, 0.0, 0.0, 0.0]))
    results = list(pipe.run(rec.stream, precomputed_flow=flow))
    assert sum(len(r.labels) for r in results) == len(rec.stream)
    assert all((r.labels >= 0).mean() > 0.5 for r in results)  # most events near a node


def test_segment_picks_the_worker_by_recording_length(sim, tmp_path):
    """`evseg segment --worker auto` (the default): a recording known to be short overlaps on a
    thread (the process would not earn its start-up back), one of unknown length (text is read
    as a stream) in the worker process; --worker forces either. Labels are the same."""
    from evseg.io import write_text

    rec, d = sim
    write_text(rec.stream, tmp_path / "sim.txt")
    labels = {}
    for name, src, extra, worker in [("npz", d / "sim.npz", [], "thread"),
                                     ("txt", tmp_path / "sim.txt", ["--sensor-size", "346x260"], "process"),
                                     ("forced", d / "sim.npz", ["--worker", "process"], "process")]:
        out = tmp_path / f"{name}.npz"
        assert main(["segment", str(src), "--flow-method", "planefit", "--out", str(out), "--no-progress",
                     *extra]) == 0
        r = load_result(out)
        assert f"worker: {worker}" in r.config
        labels[name] = r.label
    np.testing.assert_array_equal(labels["npz"], labels["txt"])
    np.testing.assert_array_equal(labels["npz"], labels["forced"])


def test_segment_slow_edges_in_the_worker_process_equals_the_sequential_pipeline(sim, tmp_path):
    """`evseg segment --slow-edges --worker process`: the worker keeps the longer history itself
    and gives the labels of the sequential pipeline with `slow_edges=True`; the result's config
    records the setting (off without the option)."""
    rec, d = sim
    out = tmp_path / "slow.npz"
    assert main(["segment", str(d / "sim.npz"), "--slow-edges", "--worker", "process", "--out", str(out),
                 "--no-progress"]) == 0
    r = load_result(out)
    assert "slow_edges: true" in r.config
    pipe = MotionSegmentationPipeline(PipelineConfig(slow_edges=True, overlap=False), sensor_size=rec.stream.sensor_size)
    np.testing.assert_array_equal(r.label, np.concatenate([w.labels for w in pipe.run(rec.stream)]))
    assert main(["segment", str(d / "sim.npz"), "--out", str(out), "--no-progress"]) == 0
    assert "slow_edges: false" in load_result(out).config


def test_calibrated_pipeline_undistorts_alike_in_the_worker_process(short_stream):
    """The worker process gets the calibration: same labels and flows as sequentially."""
    runs = []
    for overlap in (False, True):
        cfg = PipelineConfig(flow="planefit", overlap=overlap, worker="process")
        calibration = _calibration([-0.05, 0.0, 0.0, 0.0], short_stream.sensor_size)
        with MotionSegmentationPipeline(cfg, sensor_size=short_stream.sensor_size,
                                        calibration=calibration) as pipe:
            runs.append(list(pipe.run(short_stream)))
    assert len(runs[0]) == len(runs[1]) == 5
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a.labels, b.labels)
        np.testing.assert_array_equal(a.flow, b.flow)


def test_learned_pipeline_flow_equals_the_flow_command_with_context(sim, tmp_path):
    """`evseg flow --no-slow-edges` (10 ms slices, 20 ms context: the defaults) computes exactly
    the flows the learned pipeline uses by default, so `evseg flow` + `evseg segment --flow` is
    the same system; and the context changes the flows of later windows (it is really used)."""
    rec, d = sim
    out = tmp_path / "flow.npz"
    assert main(["flow", str(d / "sim.npz"), "--out", str(out), "--no-progress", "--no-slow-edges"]) == 0
    z = np.load(out)
    results = {}
    assert PipelineConfig().flow_context_us == 20_000
    assert PipelineConfig().slow_edges is False
    for context_us in (20_000, 0):
        pipe = MotionSegmentationPipeline(PipelineConfig(flow_context_us=context_us), sensor_size=rec.stream.sensor_size)
        results[context_us] = list(pipe.run(rec.stream))
    idx = np.concatenate([r.flow_index + r.first_event for r in results[20_000]])
    flow = np.concatenate([r.flow for r in results[20_000]])
    np.testing.assert_array_equal(idx, z["index"])
    np.testing.assert_allclose(flow, np.stack([z["nx"], z["ny"]], 1), rtol=1e-5, atol=1e-3)
    first = results[0][0].flow, results[20_000][0].flow  # no events before the first window
    np.testing.assert_array_equal(*first)
    assert not np.allclose(results[0][2].flow, results[20_000][2].flow)


def test_flow_command_round_trip_is_exact_with_a_calibration(sim, tmp_path):
    """With a calibration too, `evseg flow --no-slow-edges` + `evseg segment --flow` is the
    system `evseg segment` runs: both encode undistorted positions and give flow on the sensor
    grid (the pipeline used to encode raw positions: 5 deg of median difference on the ECD
    poster, and other labels)."""
    from evseg.io import read_events, write_npz

    rec, _ = sim
    calibration = _calibration([-0.2, 0.05, 0.0, 0.0])
    path = write_npz(EventStream(rec.stream.events, rec.stream.sensor_size, calibration=calibration),
                     tmp_path / "cal.npz")
    stream = read_events(path)
    assert stream.calibration is not None
    flow_file = tmp_path / "flow.npz"
    assert main(["flow", str(path), "--out", str(flow_file), "--no-progress", "--no-slow-edges"]) == 0
    z = np.load(flow_file)
    pipe = MotionSegmentationPipeline(PipelineConfig(overlap=False), sensor_size=stream.sensor_size,
                                      calibration=calibration)
    results = list(pipe.run(stream))
    np.testing.assert_array_equal(np.concatenate([r.flow_index + r.first_event for r in results]), z["index"])
    direct, via_file = tmp_path / "direct.npz", tmp_path / "via_file.npz"
    assert main(["segment", str(path), "--out", str(direct), "--no-progress"]) == 0
    assert main(["segment", str(path), "--flow", str(flow_file), "--out", str(via_file), "--no-progress"]) == 0
    np.testing.assert_array_equal(load_result(direct).label, load_result(via_file).label)


@pytest.mark.parametrize("overlap", [False, True])
def test_slow_edges_in_the_pipeline_equal_the_flow_command(sim, tmp_path, overlap):
    """`evseg flow` (slow-edge look on by default) and `PipelineConfig(slow_edges=True)`
    (sequential or overlapped) give the same flows (not uncertainties: the pipeline keeps the
    first look's): both keep 30 ms of history before the 20 ms context; the flow file records
    the settings. The first windows, which have no history before
    their context, keep their flows; the last one (30-40 ms) has 10 ms of history, and its flows
    change."""
    import json

    rec, d = sim
    out = tmp_path / "flow.npz"
    assert main(["flow", str(d / "sim.npz"), "--out", str(out), "--no-progress"]) == 0
    z = np.load(out)
    info = json.loads(str(z["config"]))
    assert info["slow_edges"] == {"compress": 2.0, "speed_full": 1.0 / 3.0, "speed_to": 2.0 / 3.0,
                                  "uncertainty": "combined"}
    assert info["history_us"] == 30_000
    runs = {}
    for slow in (True, False):
        pipe = MotionSegmentationPipeline(PipelineConfig(slow_edges=slow, overlap=overlap),
                                          sensor_size=rec.stream.sensor_size)
        runs[slow] = list(pipe.run(rec.stream))
    flow = np.concatenate([r.flow for r in runs[True]])
    np.testing.assert_allclose(flow, np.stack([z["nx"], z["ny"]], 1), rtol=1e-5, atol=1e-3)
    for k in range(3):
        np.testing.assert_array_equal(runs[True][k].flow, runs[False][k].flow)
    assert runs[True][3].t0_us >= 30_000  # windows start at the first event (5 us)
    assert not np.allclose(runs[True][3].flow, runs[False][3].flow)
    out2 = tmp_path / "flow2.npz"
    assert main(["flow", str(d / "sim.npz"), "--out", str(out2), "--no-progress", "--no-slow-edges"]) == 0
    info = json.loads(str(np.load(out2)["config"]))
    assert info["slow_edges"] is None and info["history_us"] == 0


def test_process_with_kept_us_of_history_equals_run_with_slow_edges(sim):
    """A live caller feeding `process` windows with an EventHistory of `kept_us` (50 ms with the
    slow-edge look: 20 ms context + 30 ms history) gets the flows of `run`."""
    from evseg.windows import EventHistory, stream_time_windows

    rec, _ = sim
    assert MotionSegmentationPipeline(PipelineConfig(), sensor_size=rec.stream.sensor_size).kept_us == 20_000
    assert MotionSegmentationPipeline(PipelineConfig(flow="planefit", slow_edges=True),
                                      sensor_size=rec.stream.sensor_size).kept_us == 20_000
    cfg = PipelineConfig(slow_edges=True, overlap=False)
    pipe = MotionSegmentationPipeline(cfg, sensor_size=rec.stream.sensor_size)
    assert pipe.kept_us == 50_000
    expected = [r.flow for r in pipe.run(rec.stream)]
    pipe.reset()
    history, got = EventHistory(pipe.kept_us), []
    for window in stream_time_windows([rec.stream.events], cfg.window_us):
        got.append(pipe.process(window, context=history.before(window)).flow)
        history.add(window)
    assert len(got) == len(expected) == 4
    for a, b in zip(got, expected):
        np.testing.assert_array_equal(a, b)


def test_no_fast_edges_is_the_first_look_in_flow_command_and_pipeline(sim, tmp_path):
    """`evseg flow --no-fast-edges --no-slow-edges` and `PipelineConfig(fast_edges=False)` give the
    same flows, and the flow file records which estimator made them."""
    import json

    rec, d = sim
    out = tmp_path / "flow.npz"
    assert main(["flow", str(d / "sim.npz"), "--out", str(out), "--no-progress", "--no-fast-edges",
                 "--no-slow-edges"]) == 0
    z = np.load(out)
    assert json.loads(str(z["config"]))["fast_edges"] is None
    assert json.loads(str(z["config"]))["slow_edges"] is None
    pipe = MotionSegmentationPipeline(PipelineConfig(fast_edges=False), sensor_size=rec.stream.sensor_size)
    flow = np.concatenate([r.flow for r in pipe.run(rec.stream)])
    np.testing.assert_allclose(flow, np.stack([z["nx"], z["ny"]], 1), rtol=1e-5, atol=1e-3)
    out2 = tmp_path / "flow2.npz"
    assert main(["flow", str(d / "sim.npz"), "--out", str(out2), "--no-progress"]) == 0
    assert json.loads(str(np.load(out2)["config"]))["fast_edges"] == {"stretch": 2.0, "speed_from": 0.5,
                                                                       "speed_full": 11.0 / 15.0,
                                                                       "min_keep_us": 10_000.0}


def test_mirrors_give_the_flow_command_s_flows_in_the_pipeline_and_segment(sim, tmp_path):
    """`PipelineConfig(mirrors=4)` computes the flows of `evseg flow --mirrors 4 --no-slow-edges`,
    and `evseg segment --mirrors 4` runs it and records the setting."""
    import json

    rec, d = sim
    out = tmp_path / "flow.npz"
    assert main(["flow", str(d / "sim.npz"), "--out", str(out), "--no-progress", "--no-slow-edges",
                 "--mirrors", "4"]) == 0
    z = np.load(out)
    pipe = MotionSegmentationPipeline(PipelineConfig(mirrors=4), sensor_size=rec.stream.sensor_size)
    flow = np.concatenate([r.flow for r in pipe.run(rec.stream)])
    np.testing.assert_allclose(flow, np.stack([z["nx"], z["ny"]], 1), rtol=1e-5, atol=1e-3)
    one = MotionSegmentationPipeline(PipelineConfig(), sensor_size=rec.stream.sensor_size)
    assert not np.allclose(flow, np.concatenate([r.flow for r in one.run(rec.stream)]))
    res = tmp_path / "r.npz"
    assert main(["segment", str(d / "sim.npz"), "--out", str(res), "--mirrors", "4", "--no-progress",
                 "--worker", "thread"]) == 0
    assert "mirrors: 4" in str(np.load(res)["config"])


def test_tracked_mirrors_give_the_boxes_targets_their_8_looks(short_stream):
    """`tracked_mirrors=8`: a target inside a box the tracks predicted (two windows ahead, grown
    by the margin) gets exactly the flow of 8 mirror looks, every other target exactly the flow
    of one look; windows 0 and 1 have no such boxes yet."""
    from evseg.veckm_flow import select_targets

    sensor = short_stream.sensor_size
    one, eight = ([r.flow for r in MotionSegmentationPipeline(PipelineConfig(mirrors=m, overlap=False),
                                                              sensor_size=sensor).run(short_stream)]
                  for m in (1, 8))
    pipe = MotionSegmentationPipeline(PipelineConfig(tracked_mirrors=8, overlap=False), sensor_size=sensor)
    boxes_seen = []
    flow_fn = pipe._flow_fn
    pipe._flow_fn = lambda ev, size, kept, t0, boxes=None: (boxes_seen.append(boxes), flow_fn(ev, size, kept, t0, boxes))[1]
    results = list(pipe.run(short_stream))
    assert boxes_seen[0] is None and boxes_seen[1] is None
    n_tracked = 0
    for k, res in enumerate(results):
        targets = select_targets(res.events, sensor, cell_px=2)
        x, y = res.events["x"][targets], res.events["y"][targets]
        inside = np.zeros(len(targets), dtype=bool)
        for x0, y0, x1, y1 in (boxes_seen[k] if boxes_seen[k] is not None else []):
            inside |= (x >= x0 - 8) & (x <= x1 + 8) & (y >= y0 - 8) & (y <= y1 + 8)
        np.testing.assert_array_equal(res.flow_index, targets)  # all flows finite here
        np.testing.assert_array_equal(res.flow[inside], eight[k][inside])
        np.testing.assert_array_equal(res.flow[~inside], one[k][~inside])
        n_tracked += int(inside.sum())
    assert n_tracked > 20  # the scene's ball is tracked from window 0 on
    # The boxes of window t come from window t - 2's objects, moved on.
    for k in range(2, len(results)):
        if boxes_seen[k] is not None and len(boxes_seen[k]):
            assert results[k - 2].boxes


def test_tracked_max_targets_takes_the_smallest_boxes_whole(short_stream):
    """The budget: boxes smallest first, each whole or not at all, never more targets than it."""
    from evseg.veckm_flow import select_targets

    ev = short_stream.events[:3000]
    pipe = MotionSegmentationPipeline(PipelineConfig(tracked_mirrors=8, tracked_margin_px=0),
                                      sensor_size=short_stream.sensor_size)
    targets = select_targets(ev, short_stream.sensor_size, cell_px=2)
    x, y = ev["x"][targets], ev["y"][targets]
    boxes = np.array([[0, 0, 99, 99], [10, 10, 19, 19], [50, 50, 69, 69]], dtype=np.float64)
    def inside(b):
        return (x >= b[0]) & (x <= b[2]) & (y >= b[1]) & (y <= b[3])
    small, mid, big = inside(boxes[1]), inside(boxes[2]), inside(boxes[0])
    assert 0 < small.sum() < mid.sum() < big.sum()  # the events cover all three boxes
    np.testing.assert_array_equal(pipe._in_tracked_boxes(ev, targets, boxes), big | small | mid)
    for budget, expect in ((int(small.sum()), small), (int((small | mid).sum()), small | mid),
                           (int((small | mid).sum()) + 1, small | mid), (int(small.sum()) - 1, small & False)):
        pipe.config = replace(pipe.config, tracked_max_targets=budget)
        np.testing.assert_array_equal(pipe._in_tracked_boxes(ev, targets, boxes), expect)


def test_segment_tracked_mirrors_records_the_setting(sim, tmp_path):
    rec, d = sim
    res = tmp_path / "r.npz"
    assert main(["segment", str(d / "sim.npz"), "--out", str(res), "--tracked-mirrors", "8",
                 "--tracked-max-targets", "300", "--no-progress", "--worker", "thread"]) == 0
    config = str(np.load(res)["config"])
    assert "tracked_mirrors: 8" in config and "tracked_max_targets: 300" in config
    bad = tmp_path / "bad.npz"
    assert main(["segment", str(d / "sim.npz"), "--out", str(bad), "--tracked-max-targets", "-5", "--no-progress"]) == 2
    assert not bad.exists()


@pytest.mark.parametrize("field, bad, match", [
    ("tracked_max_targets", -5, r"pipeline.tracked_max_targets must be a non-negative integer or null, got -5"),
    ("tracked_mirrors", 3, r"pipeline.tracked_mirrors must be one of \[1, 2, 4, 8\], got 3"),
    ("tracked_margin_px", -1, r"pipeline.tracked_margin_px must be a non-negative integer \(px\), got -1"),
    ("tracked_margin_px", 2.5, r"pipeline.tracked_margin_px must be a non-negative integer \(px\), got 2.5")])
def test_bad_tracked_mirrors_settings_are_config_errors(field, bad, match):
    with pytest.raises(ConfigError, match=match):
        PipelineConfig(**{field: bad})


@pytest.mark.parametrize("bad", [3, 0, True, "4", 2.0])
def test_bad_mirrors_setting_is_a_config_error(bad):
    with pytest.raises(ConfigError, match=r"pipeline.mirrors must be one of \[1, 2, 4, 8\]"):
        PipelineConfig(mirrors=bad)


@pytest.mark.parametrize("bad", ["yes", 1, None])
def test_bad_slow_edges_setting_is_a_config_error(bad):
    with pytest.raises(ConfigError, match="pipeline.slow_edges must be true or false"):
        PipelineConfig(slow_edges=bad)


@pytest.mark.parametrize("bad", [-1, 2.5, float("nan"), "20"])
def test_bad_flow_context_is_a_config_error(bad):
    with pytest.raises(ConfigError, match="flow_context_us"):
        PipelineConfig(flow_context_us=bad)


def test_learned_flow_context_longer_than_the_encoder_takes_is_a_config_error():
    from evseg.veckm_flow.encoding import MAX_SLICE_SPAN_US

    with pytest.raises(ConfigError, match="window_us \\+ flow_context_us must be at most 1073741823 us"):
        PipelineConfig(window_us=10_000, flow_context_us=MAX_SLICE_SPAN_US)
    PipelineConfig(window_us=10_000, flow_context_us=MAX_SLICE_SPAN_US - 10_000)  # the longest taken
    PipelineConfig(flow="planefit", window_us=10_000, flow_context_us=MAX_SLICE_SPAN_US)  # no such limit


def _final_bar(err: str) -> str:
    return [line for line in err.replace("\r", "\n").splitlines() if "s of recording" in line][-1]


def test_progress_bar_counts_seconds_of_recording(sim, tmp_path, capsys):
    rec, d = sim
    t = rec.stream.events["t"]
    assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--out",
                 str(tmp_path / "r.npz")]) == 0
    captured = capsys.readouterr()
    last = _final_bar(captured.err)
    # the npz tells its time span, so the bar has a total: the recording's duration in s
    assert "100%" in last and f"{(t[-1] - t[0]) / 1e6:.2f}/{(t[-1] - t[0]) / 1e6:.2f} s of recording" in last
    assert "x real time, 4 windows" in last
    # the summary names the wall time and the real-time factor over the windows' 40 ms
    assert re.search(r"4 windows in \d+\.\d s \(\d+\.\d\dx real time\)", captured.out)


def test_progress_bar_without_a_known_duration(sim, tmp_path, capsys):
    from evseg.io import write_text

    rec, d = sim
    write_text(rec.stream, tmp_path / "sim.txt")  # text files do not tell their span up front
    assert main(["segment", str(tmp_path / "sim.txt"), "--sensor-size", "346x260", "--flow", str(d / "flow.npz"),
                 "--out", str(tmp_path / "r.npz")]) == 0
    last = _final_bar(capsys.readouterr().err)
    assert "%" not in last and "0.04 s of recording" in last and "4 windows" in last


def test_segment_infers_an_unknown_sensor_size_like_flow(sim, tmp_path, capsys):
    """An npz of bare event arrays gives no sensor size: `evseg segment` takes the events' pixel
    grid, as `evseg flow` does, and says so; labels are those of the run with that size given."""
    from evseg.results import load_result

    rec, d = sim
    ev = rec.stream.events
    np.savez(tmp_path / "sim.npz", t=ev["t"], x=ev["x"], y=ev["y"], p=ev["p"])
    size = f"{int(ev['x'].max()) + 1}x{int(ev['y'].max()) + 1}"
    assert main(["segment", str(tmp_path / "sim.npz"), "--flow", str(d / "flow.npz"), "--no-progress",
                 "--out", str(tmp_path / "a.npz")]) == 0
    assert f"sensor size {size} inferred from the events" in capsys.readouterr().out
    assert main(["segment", str(tmp_path / "sim.npz"), "--sensor-size", size, "--flow", str(d / "flow.npz"),
                 "--no-progress", "--out", str(tmp_path / "b.npz")]) == 0
    a, b = load_result(tmp_path / "a.npz"), load_result(tmp_path / "b.npz")
    np.testing.assert_array_equal(a.label, b.label)
    assert a.sensor_size == b.sensor_size == tuple(int(v) for v in size.split("x"))


@pytest.fixture(scope="module")
def short_stream():
    from evseg.simulator import load_scene_preset, simulate

    return simulate(load_scene_preset("eed_like"), seed=1002, duration_us=50_000).stream


@pytest.mark.parametrize("flow, worker, stride_us, tracked_mirrors", [
    ("learned", "thread", None, 1), ("planefit", "thread", None, 1), ("learned", "process", None, 1),
    ("learned", "process", 5_000, 1), ("learned", "thread", None, 8), ("learned", "process", None, 8)])
def test_overlapped_flow_gives_the_sequential_results(short_stream, flow, worker, stride_us, tracked_mirrors):
    """Same labels and flows with the next window prepared on a thread or in the worker process
    (which keeps its own copy of the flow's context events, also with overlapping windows), also
    with more mirror looks in the tracked boxes (which the worker gets with each window)."""
    runs = {}
    for overlap in (False, True):
        cfg = PipelineConfig(flow=flow, overlap=overlap, threads=1, worker=worker, stride_us=stride_us,
                             tracked_mirrors=tracked_mirrors)
        with MotionSegmentationPipeline(cfg, sensor_size=short_stream.sensor_size) as pipe:
            runs[overlap] = list(pipe.run(short_stream))
    assert len(runs[True]) == len(runs[False]) == (5 if stride_us is None else 10)
    for a, b in zip(runs[False], runs[True]):
        np.testing.assert_array_equal(a.labels, b.labels)
        if worker == "thread":
            np.testing.assert_array_equal(a.flow, b.flow)
        else:
            # The encoder's numba kernels as compiled in this process and as loaded from numba's
            # cache by the worker can round float32 sums differently (seen right after a fresh
            # install: features ~1e-5 apart, flows ~1e-3 px/s); same labels.
            np.testing.assert_allclose(a.flow, b.flow, rtol=1e-4, atol=1e-2)
        assert a.boxes == b.boxes and a.t0_us == b.t0_us
        assert b.timings_ms["flow"] > 0


def test_the_worker_process_is_kept_between_runs_and_stopped_by_close(short_stream):
    import multiprocessing

    pipe = MotionSegmentationPipeline(PipelineConfig(flow="planefit", worker="process"),
                                      sensor_size=short_stream.sensor_size)
    assert pipe._worker_process is None  # started by the first overlapped run, not before
    first = [r.labels for r in pipe.run(short_stream)]
    workers = multiprocessing.active_children()
    assert len(workers) == 1
    pipe.reset()
    again = [r.labels for r in pipe.run(short_stream)]
    assert multiprocessing.active_children() == workers  # the same process served the second run
    for a, b in zip(first, again):
        np.testing.assert_array_equal(a, b)
    pipe.close()
    assert multiprocessing.active_children() == []


def test_a_worker_process_that_dies_is_a_clear_error_and_the_next_run_starts_a_new_one(short_stream):
    import os
    import signal

    from evseg.errors import EvsegError

    with MotionSegmentationPipeline(PipelineConfig(flow="planefit", worker="process"),
                                    sensor_size=short_stream.sensor_size) as pipe:
        done = []
        with pytest.raises(EvsegError, match="worker process stopped unexpectedly"):
            for res in pipe.run(short_stream):
                done.append(res.index)
                if res.index == 1:
                    for pid in list(pipe._worker_process._processes):
                        os.kill(pid, signal.SIGKILL)
        assert done[:2] == [0, 1] and len(done) < 5
        pipe.reset()
        assert [r.index for r in pipe.run(short_stream)] == [0, 1, 2, 3, 4]


def test_min_track_windows_reports_an_object_from_its_second_window(sim):
    """min_track_windows=2: the first window's objects are not reported (their events are
    background, no box); from the next window on the same tracks appear with the same ids and
    labels as without the rule, and the segmentation itself is unchanged."""
    rec, d = sim
    flow = load_flow_file(d / "flow.npz", n_events=len(rec.stream))
    plain = _run(rec, flow)
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed", min_track_windows=2),
                                      sensor_size=rec.stream.sensor_size)
    late = list(pipe.run(rec.stream, precomputed_flow=flow))
    assert plain[0].boxes and late[0].boxes == {}
    first = plain[0].labels
    np.testing.assert_array_equal(late[0].labels, np.where(first > 0, 0, first))
    seen = set(plain[0].boxes)
    for p, q in zip(plain[1:], late[1:]):
        np.testing.assert_array_equal(p.segmentation.node_labels, q.segmentation.node_labels)
        shown = {oid for oid in p.boxes if oid in seen}  # tracks found in an earlier window
        assert set(q.boxes) == shown
        keep = np.isin(p.labels, list(shown)) | (p.labels <= 0)
        np.testing.assert_array_equal(q.labels, np.where(keep, p.labels, 0))
        seen |= set(p.boxes)


@pytest.mark.parametrize("bad", [0, -1, 1.5])
def test_bad_min_track_windows_is_a_config_error(bad, sim, tmp_path, capsys):
    with pytest.raises(ConfigError, match="min_track_windows"):
        PipelineConfig(min_track_windows=bad)
    rec, d = sim
    if isinstance(bad, int):
        assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--out",
                     str(tmp_path / "r.npz"), "--min-track-windows", str(bad), "--no-progress"]) != 0
        assert "--min-track-windows must be >= 1" in capsys.readouterr().err
        assert not (tmp_path / "r.npz").exists()


def test_unknown_worker_is_a_config_error():
    with pytest.raises(ConfigError, match="pipeline.worker must be one of thread, process, got 'gpu'"):
        PipelineConfig(worker="gpu")


def _failing_chunks(events, n_ok):
    yield events[:n_ok]
    raise OSError("disk gone")


@pytest.mark.parametrize("overlap, worker", [(False, "thread"), (True, "thread"), (True, "process")])
def test_a_read_error_surfaces_after_the_windows_read_before_it(short_stream, overlap, worker):
    ev = short_stream.events
    n_ok = int(np.searchsorted(ev["t"], ev["t"][0] + 25_000))  # windows 0, 1 complete, 2 partial
    done = []
    with MotionSegmentationPipeline(PipelineConfig(flow="planefit", overlap=overlap, worker=worker),
                                    sensor_size=short_stream.sensor_size) as pipe:
        with pytest.raises(OSError, match="disk gone"):
            for res in pipe.run(_failing_chunks(ev, n_ok)):
                done.append(res.index)
    assert done == [0, 1]


@pytest.mark.parametrize("overlap", [False, True])
def test_a_flow_error_surfaces_at_its_window(short_stream, overlap, monkeypatch):
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="planefit", overlap=overlap),
                                      sensor_size=short_stream.sensor_size)
    calls = []
    inner = pipe._flow_fn

    def flaky(events, sensor_size, context, t0_us):
        calls.append(len(calls))
        if len(calls) == 3:
            raise RuntimeError("estimator failed on window 2")
        return inner(events, sensor_size, context, t0_us)

    monkeypatch.setattr(pipe, "_flow_fn", flaky)
    done = []
    with pytest.raises(RuntimeError, match="window 2"):
        for res in pipe.run(short_stream):
            done.append(res.index)
    assert done == [0, 1]
    # the pipeline is usable again after the failure, and an abandoned run leaves nothing behind
    monkeypatch.setattr(pipe, "_flow_fn", inner)
    pipe.reset()
    first = next(iter(pipe.run(short_stream)))
    assert first.index == 0 and len(list(pipe.run(short_stream))) == 5


def test_a_callers_flow_fn_runs_on_the_callers_thread(short_stream):
    import threading

    seen = set()

    def my_flow(events, sensor_size):
        from evseg.veckm_flow import PlaneFitNormalFlow, select_targets

        seen.add(threading.current_thread().name)
        return PlaneFitNormalFlow()(events, sensor_size, select_targets(events, sensor_size, cell_px=2))

    pipe = MotionSegmentationPipeline(PipelineConfig(), sensor_size=short_stream.sensor_size, flow_fn=my_flow)
    assert len(list(pipe.run(short_stream))) == 5
    assert seen == {threading.current_thread().name}


def test_eval_static_compares_the_settings_on_still_camera_scenes(tmp_path):
    """`evseg eval static --quick`: the static_camera preset finds the objects that the default
    settings (largest motion = background) miss, with ground-truth and with learned flow."""
    from evseg.pipeline_eval import evaluate_static_camera

    rows = {r["scene"]: r for r in evaluate_static_camera(quick=True)}
    assert set(rows) == {f"{f} flow, {s} settings" for f in ("ground-truth", "learned")
                         for s in ("default", "static_camera")}
    # Measured (seeds 1000-1001, 100 ms): ground truth 16.7 -> 76.7 %, learned 18.3 -> 60.0 %.
    for f, gain in (("ground-truth", 50), ("learned", 25)):
        assert rows[f"{f} flow, static_camera settings"]["detection rate %"] > \
            rows[f"{f} flow, default settings"]["detection rate %"] + gain


def test_evaluate_pipeline_passes_pipeline_options_on():
    """evaluate_pipeline(**options) builds each scene's PipelineConfig with them (checked by the
    config: a bad value fails at the first scene, before any segmentation)."""
    from evseg.pipeline_eval import evaluate_pipeline

    with pytest.raises(ConfigError, match="min_track_windows"):
        evaluate_pipeline(quick=True, min_track_windows=0)


def test_evaluate_pipeline_sets_segmentation_overrides_on_every_preset(monkeypatch):
    """evaluate_pipeline(overrides=...) compares a segmentation setting with the presets' own,
    as evaluate_oracle does: a misspelt field is named before any scene is simulated, and the
    field reaches each scene's config (the recording evaluation is stubbed to record it)."""
    import evseg.pipeline_eval as pe
    import evseg.simulator

    monkeypatch.setattr(evseg.simulator, "simulate", lambda *a, **k: pytest.fail("simulated"))
    with pytest.raises(ConfigError, match="max_objekt_extent"):
        pe.evaluate_pipeline(quick=True, overrides={"max_objekt_extent": 0.35})

    seen = []

    def stop(rec, cfg, keep_results=False):
        seen.append(cfg.segmentation.max_object_extent)
        raise RuntimeError("stop")

    monkeypatch.setattr(evseg.simulator, "simulate", lambda *a, **k: None)
    monkeypatch.setattr(pe, "evaluate_recording", stop)
    with pytest.raises(RuntimeError, match="stop"):
        pe.evaluate_pipeline(quick=True, overrides={"max_object_extent": 0.35})
    assert seen == [0.35]


def test_evaluate_static_camera_takes_seeds_and_overrides(monkeypatch):
    """evaluate_static_camera(seeds=..., overrides=...) (`evseg eval static --seeds --set`)
    simulates the seeds asked and sets the fields on both settings, the default and the
    static_camera preset (the recording evaluation is stubbed to record them)."""
    import evseg.pipeline_eval as pe
    import evseg.simulator

    asked, seen = [], []
    monkeypatch.setattr(evseg.simulator, "simulate", lambda preset, seed, duration_us: asked.append(seed))

    def record(rec, cfg, keep_results=False):
        seen.append((cfg.segmentation.static_camera, cfg.segmentation.uncertainty_angle_gain))
        return pe.RecordingEvaluation(scores=[], results=[], flow_median_ae_deg=float("nan"), ms_per_window=float("nan"))

    monkeypatch.setattr(pe, "evaluate_recording", record)
    pe.evaluate_static_camera(seeds=[903], overrides={"uncertainty_angle_gain": 0.5})
    assert asked == [903]
    assert seen == [(False, 0.5), (True, 0.5)] * 2  # ground-truth, then learned flow


def test_real_recording_pipeline_sets_overrides_on_the_preset():
    """evaluate_pipeline_real(overrides=...) (`evseg eval pipeline-real --set`): each recording's
    preset with the fields set on it."""
    from evseg.pipeline_real import _pipeline

    seg = _pipeline((64, 48), "eed_like", overrides={"lambda_m": 55}).config.segmentation
    assert seg.lambda_m == 55.0 and seg.residual_scale_noise == 2.0  # eed_like's own field kept
    assert _pipeline((64, 48), None).config.segmentation.lambda_m == 80.0


def test_evaluate_pipeline_simulates_the_seeds_asked(monkeypatch):
    """evaluate_pipeline(seeds=...) simulates those scenes (validation seeds, not the held-out
    1000-1007); the simulator is stubbed to record the first scene asked and stop."""
    import evseg.simulator
    from evseg.pipeline_eval import evaluate_pipeline

    asked = []

    def stop(preset, seed, duration_us):
        asked.append((seed, duration_us))
        raise RuntimeError("stop")

    monkeypatch.setattr(evseg.simulator, "simulate", stop)
    with pytest.raises(RuntimeError, match="stop"):
        evaluate_pipeline(seeds=range(900, 910))
    assert asked == [(900, 300_000)]


def test_eval_pipeline_table_adds_the_pooled_rows_with_ground_truth_flow(monkeypatch):
    """`evseg eval pipeline` = the learned-flow rows, then only the pooled rows of the same run
    with the simulator's flow, labelled as such (stubbed runs: this checks the table's make-up)."""
    import evseg.pipeline_eval as pe
    from evseg.commands.eval import TARGETS

    assert TARGETS["pipeline"] == "evseg.pipeline_eval:evaluate_pipeline_and_oracle"
    calls = []

    def fake(quick=False, flow="learned", seeds=None, **options):
        calls.append((quick, flow))
        return [{"scene": f"eed_like #1000 {flow}"}, {"scene": "**scenes with objects**", "flow": flow}]

    monkeypatch.setattr(pe, "evaluate_pipeline", fake)
    rows = pe.evaluate_pipeline_and_oracle(quick=True)
    assert calls == [(True, "learned"), (True, "precomputed")]
    assert [r["scene"] for r in rows] == ["eed_like #1000 learned", "**scenes with objects**",
                                          "**scenes with objects, ground-truth flow**"]
    assert rows[-1]["flow"] == "precomputed"


def test_evaluate_recording_counts_each_truth_objects_own_events(sim):
    """The scores of evaluate_recording carry, per visible ground-truth object, the events the
    simulator labelled with its id in that window (what the table's 'under 50 events' and
    'detection rate, >= 50 events' columns use), and one outcome per object."""
    from evseg.pipeline_eval import evaluate_recording

    rec, _ = sim
    ev = evaluate_recording(rec, PipelineConfig(flow="precomputed"), keep_results=True)
    assert len(ev.scores) == len(ev.results) == 4
    for score, res in zip(ev.scores, ev.results):
        truth = rec.window_truth(res.t0_us, res.t1_us)
        ids = [oid for oid in truth.object_ids if oid in truth.boxes]
        t = rec.stream.events["t"]
        in_window = (t >= res.t0_us) & (t < res.t1_us)
        assert score.truth_events == tuple(int(np.sum(in_window & (rec.label == oid))) for oid in ids)
        assert len(score.outcomes) == score.n_truth and score.outcomes.count("detected") == score.n_detected_ok
    s = summarize(ev.scores)
    assert s.detection_rate + s.missed_not_found + s.missed_too_small + s.missed_spills_out == pytest.approx(1.0)
    assert 0.0 <= s.sparse_share <= 1.0


def test_run_checks_what_it_is_given(sim):
    from evseg.errors import EventDataError, FormatError

    rec, d = sim
    ev = rec.stream.events
    flow = load_flow_file(d / "flow.npz")

    def pipe():
        return MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)

    # One event array is a stream of one chunk: the same windows as the EventStream.
    as_array = list(pipe().run(ev, precomputed_flow=flow))
    assert [r.labels.tolist() for r in as_array] == [r.labels.tolist() for r in _run(rec, flow)]
    # Chunks out of time order would be dropped unseen by the windowing: refused.
    half = len(ev) // 2
    with pytest.raises(EventDataError, match=r"chunk 1 starts at t=\d+ us, before the previous chunk's last event"):
        list(pipe().run([ev[half:], ev[:half]], precomputed_flow=flow))
    back = ev.copy()
    back["t"][100] = back["t"][99] - 1
    with pytest.raises(EventDataError, match=r"chunk 0: field 't' goes back in time at event 100"):
        list(pipe().run([back], precomputed_flow=flow))
    with pytest.raises(EventDataError, match=r"an array of dtype float64 is not events"):
        list(pipe().run(np.zeros((10, 4)), precomputed_flow=flow))
    with pytest.raises(EventDataError, match=r"chunk 0 must be an event array .* got dtype float64"):
        list(pipe().run([np.zeros((10, 4))], precomputed_flow=flow))
    # A flow index past the last event: refused once the stream has ended, naming the flow.
    shifted = dict(flow, index=flow["index"] + len(ev) // 4)
    with pytest.raises(FormatError, match=rf"my_flow: key 'index' refers to event \d+ but the stream has {len(ev)} events"):
        list(pipe().run(rec.stream, precomputed_flow=shifted, flow_source="my_flow"))


def test_each_run_starts_afresh(sim):
    # A notebook cell run twice: the same labels and object ids, not ids counting on.
    rec, d = sim
    flow = load_flow_file(d / "flow.npz")
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)
    first = [(r.labels.copy(), dict(r.boxes)) for r in pipe.run(rec.stream, precomputed_flow=flow)]
    assert any(r[1] for r in first)  # objects were found
    # Another stream between: the same scene mirrored left to right, whose objects end where
    # no object of the first stream starts (tracks carried over would not match: new ids).
    mirrored = rec.stream.events.copy()
    mirrored["x"] = rec.stream.sensor_size[0] - 1 - mirrored["x"]
    list(pipe.run(mirrored, precomputed_flow=dict(flow, nx=-flow["nx"])))
    again = [(r.labels, dict(r.boxes)) for r in pipe.run(rec.stream, precomputed_flow=flow)]
    assert len(again) == len(first)
    for (la, ba), (lb, bb) in zip(first, again):
        np.testing.assert_array_equal(la, lb)
        assert ba == bb


def test_a_calibration_of_another_sensor_is_refused():
    from evseg.calibration import Calibration
    from evseg.errors import CalibrationError

    cal = Calibration(K=np.array([[200.0, 0, 160], [0, 200.0, 120], [0, 0, 1]]), D=np.zeros(4), sensor_size=(320, 240))
    with pytest.raises(CalibrationError, match=r"the calibration is for 320x240 px, the sensor is 190x180"):
        MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=(190, 180), calibration=cal)


def test_a_results_stored_configuration_runs_again(sim, tmp_path, capsys):
    # The stored YAML rebuilds the PipelineConfig in Python, and the result file (or its YAML)
    # given as --config reuses its segmentation settings: the same labels.
    import yaml

    rec, d = sim
    first = tmp_path / "first.npz"
    assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--config", "eed_like",
                 "--out", str(first), "--no-progress"]) == 0
    stored = load_result(first).config
    cfg = PipelineConfig(**yaml.safe_load(stored))
    from evseg.segmentation import load_segmentation_config

    assert cfg.segmentation == load_segmentation_config("eed_like") and cfg.flow == "precomputed"
    (tmp_path / "stored.yaml").write_text(stored)
    for source in (first, tmp_path / "stored.yaml"):
        again = tmp_path / f"again_{source.suffix[1:]}.npz"
        assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--config", str(source),
                     "--out", str(again), "--no-progress"]) == 0, capsys.readouterr().err
        np.testing.assert_array_equal(load_result(again).label, load_result(first).label)
        assert load_result(again).config == stored
    assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--config", str(first),
                 "--out", str(first), "--no-progress"]) == 2
    assert "is the configuration (--config)" in capsys.readouterr().err


@pytest.mark.parametrize("kwargs, message", [
    (dict(overlap="no"), "pipeline.overlap must be true or false, got 'no'"),
    (dict(threads=0), "pipeline.threads must be an integer >= 1 or null, got 0"),
    (dict(window_us=10.5), "pipeline.window_us must be a positive whole number of microseconds, got 10.5"),
    (dict(stride_us=True), "pipeline.stride_us must be a positive whole number"),
    (dict(target_cell_px=0), "pipeline.target_cell_px must be an integer >= 1 or null, got 0"),
    (dict(segmentation=3), "pipeline.segmentation must be a SegmentationConfig, a preset name or a mapping"),
    (dict(segmentation={"cell_px": "3"}), "pipeline.segmentation: field 'cell_px'"),
])
def test_pipeline_config_refuses_values_that_would_fail_later(kwargs, message):
    with pytest.raises(ConfigError, match=re.escape(message)):
        PipelineConfig(**kwargs)
    assert PipelineConfig(window_us=10_000.0).window_us == 10_000  # a whole float (YAML, arithmetic) is fine


def test_reported_boxes_are_the_extent_of_the_reported_masks(sim):
    # The evaluations score the mask; a box 1 px larger than it would score differently.
    from evseg.undistortion import raw_box

    rec, d = sim
    results = _run(rec, load_flow_file(d / "flow.npz", n_events=len(rec.stream)))
    n = 0
    for r in results:
        for oid, box in r.boxes.items():
            assert box == raw_box(r.masks[oid]), (r.index, oid)
            n += 1
    assert n >= 4  # objects in every window of this scene


def test_the_summarys_real_time_factor_counts_recording_time_not_window_time(sim, tmp_path, capsys, monkeypatch):
    # One 1 s window over a 40 ms recording: the run covered 40 ms of recording, not 1 s.
    import types

    import evseg.runner

    rec, d = sim
    t = rec.stream.events["t"]
    calls = []

    def clock():  # the job's wall clock: 0 at the start, 1 s at the end
        calls.append(None)
        return 0.0 if len(calls) == 1 else 1.0

    monkeypatch.setattr(evseg.runner, "time", types.SimpleNamespace(perf_counter=clock))
    assert main(["segment", str(d / "sim.npz"), "--flow", str(d / "flow.npz"), "--window-ms", "1000",
                 "--out", str(tmp_path / "r.npz"), "--no-progress"]) == 0
    span_s = (t[-1] - t[0]) / 1e6
    assert f"1 window in 1.0 s ({span_s:.2f}x real time)" in capsys.readouterr().out


def test_the_result_keeps_the_recordings_absolute_time_offset(sim, tmp_path):
    from evseg.io import write_h5

    rec, d = sim
    stream = EventStream(rec.stream.events, rec.stream.sensor_size, t_offset_us=1_600_000_000_000_000)
    write_h5(stream, tmp_path / "abs.h5")
    out = tmp_path / "r.npz"
    assert main(["segment", str(tmp_path / "abs.h5"), "--flow", str(d / "flow.npz"), "--out", str(out),
                 "--no-progress"]) == 0
    r = load_result(out)
    assert r.t_offset_us == 1_600_000_000_000_000
    assert r.window_t0_us[0] == rec.stream.events["t"][0]  # windows stay relative, as the labels' events


def test_a_run_superseded_by_another_on_the_same_pipeline_says_so(sim):
    # Two run() generators on one pipeline share its tracks: interleaved, the first one's
    # labels would come from the second one's state. Resuming it raises instead.
    rec, d = sim
    flow = load_flow_file(d / "flow.npz", n_events=len(rec.stream))
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)
    first = pipe.run(rec.stream, precomputed_flow=flow)
    next(first)
    second = pipe.run(rec.stream, precomputed_flow=flow)
    alone = [r.labels for r in _run(rec, flow)]
    np.testing.assert_array_equal(next(second).labels, alone[0])
    with pytest.raises(ConfigError, match="this run of the pipeline was superseded"):
        next(first)
    for r, expected in zip(second, alone[1:]):  # the later run is whole and unaffected
        np.testing.assert_array_equal(r.labels, expected)


def test_propagating_labels_refuses_points_of_two_lengths(sim):
    # The compiled nearest-node search has no bounds checks: mismatched x and y crashed the
    # interpreter (2 M points against 10) or returned garbage.
    from evseg.errors import EventDataError
    from evseg.segmentation import propagate_labels

    rec, d = sim
    res = _run(rec, load_flow_file(d / "flow.npz", n_events=len(rec.stream)))[0].segmentation
    with pytest.raises(EventDataError, match=r"the points' x and y must be 1-D of one length, got shapes \(3,\) and \(1,\)"):
        propagate_labels(res, np.array([100.0, 100.0, 100.0]), np.array([100.0]))
    with pytest.raises(EventDataError, match="must be finite positions"):
        propagate_labels(res, np.array([np.nan]), np.array([1.0]))


def test_the_pipeline_names_wrong_arguments_instead_of_failing_inside(sim, tmp_path):
    from evseg.errors import EventDataError
    from evseg.segmentation import SegmentationConfig
    from evseg.windows import Window

    rec, d = sim
    size = rec.stream.sensor_size
    with pytest.raises(ConfigError, match=r"config must be a PipelineConfig, got SegmentationConfig \(segmentation settings"):
        MotionSegmentationPipeline(SegmentationConfig(), sensor_size=size)
    with pytest.raises(ConfigError, match="calibration must be a Calibration or a calibration file, got int"):
        MotionSegmentationPipeline(PipelineConfig(flow="planefit"), sensor_size=size, calibration=3)
    pipe = MotionSegmentationPipeline(None, sensor_size=size)  # None: the defaults
    assert pipe.config.flow == "learned"
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="planefit"), sensor_size=size)
    with pytest.raises(ConfigError, match="process\\(\\) takes a Window .* got EventStream; to segment events, use run"):
        pipe.process(rec.stream)
    window = Window(0, 0, 10_000, rec.stream.events[:100], 0)
    flow = {"index": np.array([-1]), "nx": np.array([1.0]), "ny": np.array([0.0])}
    with pytest.raises(EventDataError, match="window 0: the flow: 'index' -1 is not one of the window's 100 events"):
        pipe.process(window, flow)
    flow = {"index": np.array([0, 1]), "nx": np.array([1.0]), "ny": np.array([0.0, 0.0])}
    with pytest.raises(EventDataError, match=r"window 0: the flow: 'nx' has shape \(1,\), 'index' \(2,\)"):
        pipe.process(window, flow)

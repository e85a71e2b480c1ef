"""Live sources (evseg.live): pacing a replay, dropping a backlog, keeping object ids over the
gap, and `evseg segment --realtime`."""

import threading

import numpy as np
import pytest

from evseg.cli import main
from evseg.errors import ConfigError, EventDataError
from evseg.events import make_events
from evseg.live import newest_window_start, replay, run_live
from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
from evseg.results import load_result
from evseg.tracking import shift_box


@pytest.fixture(scope="module")
def stream():
    from evseg.simulator import load_scene_preset, simulate

    return simulate(load_scene_preset("eed_like"), seed=1002, duration_us=60_000).stream


def _pipeline(stream, **kw):
    kw = {"overlap": False, **kw}
    return MotionSegmentationPipeline(PipelineConfig(threads=1, **kw), sensor_size=stream.sensor_size)


MODES = [{"overlap": False}, {"overlap": True, "worker": "thread"}, {"overlap": True, "worker": "process"}]


def test_replay_hands_out_each_packet_once_the_sensor_clock_passed_its_end():
    """With a fake clock that only sleeping advances, every packet leaves at exactly
    (packet index + 1) * packet_us / speed after the first event, and holds one packet's span."""
    now = [100.0]
    sleeps = []

    def sleep(s):
        sleeps.append(s)
        now[0] += s

    t = np.array([5_000, 5_100, 5_999, 6_000, 8_500, 8_999, 9_000])
    ev = make_events(np.zeros(7), np.zeros(7), t, np.ones(7))
    released = []
    for packet in replay([ev[:3], ev[3:]], speed=2.0, packet_us=1_000, clock=lambda: now[0], sleep=sleep):
        released.append((packet["t"].tolist(), now[0] - 100.0))
    # bins from the first event (5,000 us): [5000, 6000) [6000, 7000) [8000, 9000) [9000, 10000)
    assert [p for p, _ in released] == [[5_000, 5_100, 5_999], [6_000], [8_500, 8_999], [9_000]]
    # wall seconds after the first event; 1e-12 s: the float rounding of adding the sleeps up
    assert [w for _, w in released] == pytest.approx([0.0005, 0.001, 0.002, 0.0025], abs=1e-12)
    assert len(sleeps) == 4
    assert [p["t"].tolist() for p in replay([ev], speed=float("inf"))] == [[5_000, 5_100, 5_999], [6_000],
                                                                          [8_500, 8_999], [9_000]]


@pytest.mark.parametrize("bad, match", [({"speed": 0}, "speed must be a positive number"),
                                        ({"packet_us": 0}, "packet_us must be a positive integer")])
def test_bad_replay_settings_are_config_errors(bad, match):
    with pytest.raises(ConfigError, match=match):
        next(replay([make_events([0], [0], [0], [1])], **bad))


def test_newest_window_start():
    # complete: the window's end at or before the newest event; at the end: holds an event
    assert newest_window_start(0, 95, 10, 10, final=False) == 80
    assert newest_window_start(0, 90, 10, 10, final=False) == 80
    assert newest_window_start(0, 95, 10, 10, final=True) == 90
    assert newest_window_start(0, 95, 10, 5, final=False) == 85
    assert newest_window_start(40, 45, 10, 10, final=False) == 40  # never before the next window


@pytest.mark.parametrize("mode, stride_us", [(MODES[0], None), (MODES[1], None), (MODES[2], None),
                                             (MODES[0], 5_000)],
                         ids=["sequential", "thread", "process", "overlapping windows"])
def test_without_dropping_a_live_run_gives_the_sequential_pipeline_s_results(stream, mode, stride_us):
    """max_lag_us=None: every window, with the same context, labels, boxes and positions as
    pipeline.run (overlap off), whatever the packets' sizes, also with the next window
    prepared by the worker thread or process, and with overlapping windows."""
    expected = list(_pipeline(stream, stride_us=stride_us).run(stream))
    packets = [stream.events[i:i + 1_000] for i in range(0, len(stream.events), 1_000)]
    with _pipeline(stream, stride_us=stride_us, **mode) as pipe:
        live = list(run_live(pipe, packets, max_lag_us=None))
    n = 6 if stride_us is None else 12
    assert [r.window.index for r in live] == [r.index for r in expected] == list(range(n))
    for a, b in zip(expected, live):
        assert b.dropped == 0 and b.latency_ms >= 0
        assert (a.t0_us, a.first_event, a.boxes) == (b.window.t0_us, b.window.first_event, b.window.boxes)
        np.testing.assert_array_equal(a.labels, b.window.labels)


@pytest.mark.parametrize("mode", MODES, ids=["sequential", "thread", "process"])
def test_a_backlog_is_dropped_down_to_the_newest_complete_window(stream, mode):
    """The source hands over 45 ms of events at once and then waits: the live run drops the
    windows before the newest complete one ([30, 40) ms), segments it, then, once the rest (up
    to 60 ms) has come, the two windows after it without dropping: [40, 50) ends 10 ms before
    the newest event, within max_lag_us."""
    ev = stream.events
    t0 = int(ev["t"][0])
    first = ev[ev["t"] < t0 + 45_000]
    go_on = threading.Event()

    def source():
        yield first
        assert go_on.wait(timeout=30), "the first window's labels waited for the next window"
        yield ev[len(first):]

    results = []
    with _pipeline(stream, **mode) as pipe:
        # overlapped, the first window's labels must not wait for the next window to be complete
        for res in run_live(pipe, source(), max_lag_us=12_000):
            results.append(res)
            go_on.set()
    assert [(r.window.index, r.dropped) for r in results] == [(3, 3), (4, 0), (5, 0)]
    assert results[0].window.t0_us == t0 + 30_000
    assert results[0].lag_us == int(first["t"][-1]) - (t0 + 40_000)
    # positions in the source are kept: the dropped windows' events are skipped, not renumbered
    assert results[0].window.first_event == int(np.searchsorted(ev["t"], t0 + 30_000))
    assert sum(len(r.window.events) for r in results) == len(ev) - results[0].window.first_event


def test_skip_windows_moves_each_track_on_by_as_many_strides(stream):
    pipe = _pipeline(stream)
    for _ in zip(range(3), pipe.run(stream)):
        pass
    assert pipe._tracker.tracks, "the scene's ball is tracked after 3 windows"
    before = dict(pipe._tracker.tracks)
    missed_before = dict(pipe._tracker.missed)
    steps = {oid: motion[1] for oid, motion in pipe._track_motion.items()}
    pipe.skip_windows(4)
    for oid, box in before.items():
        dx, dy = steps.get(oid, (0.0, 0.0))
        assert pipe._tracker.tracks[oid] == shift_box(box, 4 * dx, 4 * dy, stream.sensor_size)
    assert pipe._tracker.missed == missed_before  # skipped windows are not misses


def test_warm_up_leaves_no_trace_in_the_results(stream):
    pipe = _pipeline(stream)
    assert pipe.warm_up() > 0
    warmed = list(pipe.run(stream))
    fresh = list(_pipeline(stream).run(stream))
    for a, b in zip(fresh, warmed):
        np.testing.assert_array_equal(a.labels, b.labels)
        assert a.boxes == b.boxes


def test_bad_live_input_is_a_clear_error(stream):
    ev = stream.events
    with pytest.raises(EventDataError, match="packet starts at .* before the previous packet's last event"):
        list(run_live(_pipeline(stream), [ev[1000:2000], ev[:1000]], max_lag_us=None))
    wrong = np.zeros(3, dtype=[("t", "<i8"), ("x", "<i4"), ("y", "<i4"), ("p", "<i4")])
    with pytest.raises(EventDataError, match="a packet must be an event array of dtype"):
        list(run_live(_pipeline(stream), [wrong], max_lag_us=None))
    off = ev[2000:2100].copy()
    off["x"][7] = stream.sensor_size[0]  # one column past the sensor
    w, h = stream.sensor_size
    with pytest.raises(EventDataError, match=rf"live source: packet 2: event 7 at \({w}, \d+\) \(t=\d+ us at its "
                                             rf"start\) is outside the {w}x{h} sensor"):
        list(run_live(_pipeline(stream), [ev[:1000], ev[1000:2000], off], max_lag_us=None))
    with pytest.raises(EventDataError, match=rf"MotionSegmentationPipeline.run: chunk 1: event 7 at \({w}, \d+\) "
                                             rf"is outside the {w}x{h} sensor"):
        list(_pipeline(stream).run([ev[:2000], off]))
    with pytest.raises(ConfigError, match="precomputed"):
        list(run_live(_pipeline(stream, flow="precomputed"), [ev], max_lag_us=None))
    with pytest.raises(ConfigError, match="max_lag_us"):
        list(run_live(_pipeline(stream), [ev], max_lag_us=-1))

    def broken():
        yield ev[:1000]
        raise OSError("camera unplugged")

    with pytest.raises(OSError, match="camera unplugged"):  # the reader thread's error reaches the caller
        list(run_live(_pipeline(stream), broken(), max_lag_us=None))


@pytest.mark.parametrize("mode", MODES, ids=["sequential", "thread", "process"])
@pytest.mark.parametrize("delay_s", [0.0, 0.05])
def test_a_failing_source_still_gives_the_windows_complete_before_it_failed(stream, mode, delay_s):
    """A camera unplugged (the source raises) after 35 ms of events: the three windows complete
    by then are segmented and yielded, as pipeline.run does, then the error is raised; before,
    an error arriving while they waited was raised at once and they were lost."""
    import time

    ev = stream.events
    cut = int(np.searchsorted(ev["t"], int(ev["t"][0]) + 35_000))

    def failing():
        yield ev[:cut]
        time.sleep(delay_s)
        raise OSError("camera unplugged")

    expected = []
    with pytest.raises(OSError, match="camera unplugged"):
        for r in _pipeline(stream).run(failing()):
            expected.append(r.t0_us)
    assert len(expected) == 3
    got = []
    with _pipeline(stream, **mode) as pipe:
        with pytest.raises(OSError, match="camera unplugged"):
            for r in run_live(pipe, failing(), max_lag_us=None):
                got.append(r.window.t0_us)
    assert got == expected


def test_a_late_packet_is_refused_even_after_its_window_was_taken(stream):
    """Without flow context and with gaps between windows (stride > window) the buffer is
    empty between windows; a packet older than one already received must still be refused,
    not counted twice into first_event."""
    import time

    ev, t0 = stream.events, int(stream.events["t"][0])
    a = ev[ev["t"] < t0 + 15_000]
    b = ev[(ev["t"] >= t0 + 5_000) & (ev["t"] < t0 + 60_000)]

    def source():
        yield a
        time.sleep(0.3)  # the first window is taken before b arrives
        yield b

    pipe = _pipeline(stream, window_us=10_000, stride_us=20_000, flow_context_us=0)
    with pytest.raises(EventDataError, match=r"a packet starts at \d+ us, before the previous packet's last event"):
        list(run_live(pipe, source(), max_lag_us=None))


def test_replay_checks_its_chunks(stream):
    ev = stream.events
    with pytest.raises(EventDataError, match=r"replay: a packet must be an event array of dtype .* got list"):
        list(replay([[1, 2, 3]], speed=float("inf")))
    with pytest.raises(EventDataError, match=r"replay: packet timestamps go back in time"):
        list(replay([ev[:100][::-1]], speed=float("inf")))
    with pytest.raises(EventDataError, match=r"replay: a packet starts at \d+ us, before the previous"):
        list(replay([ev[100:200], ev[:100]], speed=float("inf")))


def test_segment_realtime_labels_dropped_windows_unassigned_and_reports_them(stream, tmp_path, capsys):
    from evseg.io import write_npz

    rec = tmp_path / "rec.npz"
    write_npz(stream, rec)
    out = tmp_path / "result.npz"
    # 1000x the sensor's pace: the whole recording arrives during the first window's segmentation.
    assert main(["segment", str(rec), "--realtime", "--speed", "1000", "--max-lag-ms", "0", "--out", str(out),
                 "--no-progress"]) == 0
    summary = capsys.readouterr().out
    r = load_result(out)
    assert len(r.label) == len(stream.events) and not r.partial
    n_seg = len(r.window_t0_us)
    assert f"{n_seg} of 6 windows segmented, {6 - n_seg} dropped to keep up" in summary
    assert n_seg < 6
    t = stream.events["t"]
    segmented = np.zeros(len(t), dtype=bool)
    for a, b in zip(r.window_t0_us, r.window_t1_us):
        segmented |= (t >= a) & (t < b)
    assert (r.label[~segmented] == -1).all()  # dropped windows' events


def test_segment_realtime_refuses_precomputed_flow(stream, tmp_path, capsys):
    from evseg.io import write_npz

    rec = tmp_path / "rec.npz"
    write_npz(stream, rec)
    flow = tmp_path / "flow.npz"
    np.savez(flow, index=np.arange(3), nx=np.ones(3), ny=np.ones(3))
    assert main(["segment", str(rec), "--realtime", "--flow", str(flow), "--out", str(tmp_path / "r.npz")]) == 2
    assert "--realtime replays a recording as a live camera" in capsys.readouterr().err
    assert not (tmp_path / "r.npz").exists()


def test_replay_and_run_live_take_one_array_of_events():
    # Iterating one array hands out single events (numpy records): it is taken as one chunk.
    from evseg.events import make_events
    from evseg.live import replay

    ev = make_events(list(range(5)), [0] * 5, [0, 500, 1500, 2500, 3500], [1] * 5)
    packets = list(replay(ev, speed=float("inf")))
    assert [len(p) for p in packets] == [2, 1, 1, 1] and np.concatenate(packets).tolist() == ev.tolist()
    with pytest.raises(ConfigError, match="replay speed must be a positive number, got '2'"):
        list(replay([ev], speed="2"))


def test_onnx_flow_threads_must_be_a_count():
    from evseg.veckm_flow import OnnxNormalFlow

    for bad in (0, -3, "2", 1.5):
        with pytest.raises(ConfigError, match="threads must be an integer >= 1 or None"):
            OnnxNormalFlow(threads=bad)

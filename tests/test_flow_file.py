"""Per-event normal flow files (evseg.flow_file): the layout users write for `evseg segment --flow`."""

import numpy as np
import pytest

from evseg.cli import main
from evseg.errors import EvsegError, FormatError
from evseg.flow_file import check_flow, load_flow_file, save_flow_file, slice_flow


def test_round_trip_sorts_rows_by_index_and_keeps_metadata(tmp_path):
    path = tmp_path / "flow.npz"
    save_flow_file(path, index=[9, 0, 5], nx=[120.0, -3.5, 0.0], ny=[0.0, 40.0, 80.0], uncertainty=[0.1, 0.2, 0.3],
                   sensor_size=(346, 260), window_us=10_000, method="mine", config={"k": 1})
    flow = load_flow_file(path, n_events=10)
    assert flow["index"].dtype == np.int64 and flow["nx"].dtype == np.float32
    np.testing.assert_array_equal(flow["index"], [0, 5, 9])
    np.testing.assert_array_equal(flow["nx"], np.float32([-3.5, 0.0, 120.0]))
    np.testing.assert_array_equal(flow["ny"], np.float32([40.0, 80.0, 0.0]))
    np.testing.assert_array_equal(flow["uncertainty"], np.float32([0.2, 0.3, 0.1]))
    with np.load(path) as z:
        assert z["sensor_size"].tolist() == [346, 260] and int(z["window_us"]) == 10_000
        assert str(z["method"]) == "mine" and str(z["config"]) == '{"k": 1}'


def test_uncertainty_is_optional(tmp_path):
    save_flow_file(tmp_path / "f.npz", [1, 2], [1.0, 2.0], [0.0, 0.0])
    assert set(load_flow_file(tmp_path / "f.npz")) == {"index", "nx", "ny"}


def test_a_failed_save_leaves_the_existing_file(tmp_path):
    path = tmp_path / "flow.npz"
    save_flow_file(path, [0, 1], [1.0, 2.0], [3.0, 4.0])
    before = path.read_bytes()
    with pytest.raises(EvsegError, match=r"key 'ny' has 1 rows, 'index' has 2"):
        save_flow_file(path, [0, 1], [1.0, 2.0], [3.0])
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["flow.npz"]  # no temporary file left


@pytest.mark.parametrize("data, message", [
    ({"index": [0], "nx": [1.0]}, r"no key 'ny'"),
    ({"index": [0, 1], "nx": [1.0, 2.0], "ny": [[1.0, 2.0]]}, r"key 'ny' must be 1-D .* shape \(1, 2\)"),
    ({"index": [0], "nx": ["a"], "ny": [1.0]}, r"key 'nx' must hold real numbers, got dtype <U1"),
    ({"index": [0.5], "nx": [1.0], "ny": [1.0]}, r"key 'index' must hold event positions \(integers\), got 0.5"),
    ({"index": [-1], "nx": [1.0], "ny": [1.0]}, r"key 'index' has value -1 outside"),
    ({"index": [0, 7], "nx": [1.0, 1.0], "ny": [1.0, 1.0], "uncertainty": [0.1]}, r"key 'uncertainty' has 1 rows"),
])
def test_bad_flow_arrays_are_refused_naming_the_key(data, message):
    with pytest.raises(EvsegError, match=message):
        check_flow(data, source="test")


def test_load_names_the_file_and_checks_the_recording_length(tmp_path):
    path = tmp_path / "flow.npz"
    np.savez(path, index=np.array([0, 12]), nx=np.ones(2), ny=np.ones(2))
    with pytest.raises(FormatError, match=rf"{path}: key 'index' has value 12 outside the recording's 10 events"):
        load_flow_file(path, n_events=10)
    np.savez(path, index=np.array([0]), nx=np.ones(1))
    with pytest.raises(FormatError, match=rf"{path}: no key 'ny'"):
        load_flow_file(path)
    npy = tmp_path / "flow.npy"
    np.save(npy, np.zeros((3, 3)))
    with pytest.raises(FormatError, match=r"an .npz archive with keys index, nx, ny"):
        load_flow_file(npy)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match=r"junk.npz: not an .npz archive .* starts with b'not '"):
        load_flow_file(tmp_path / "junk.npz")
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[:40])  # a zip cut short
    with pytest.raises(FormatError, match=r"cut.npz: cannot read flow file"):
        load_flow_file(tmp_path / "cut.npz")
    h5 = tmp_path / "events.h5"
    h5.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    with pytest.raises(FormatError, match=r"events.h5: not an .npz archive"):
        load_flow_file(h5)


def test_a_negative_uncertainty_and_a_repeated_event_are_refused():
    with pytest.raises(EvsegError, match=r"key 'uncertainty' has value -0.5 < 0"):
        check_flow({"index": [0, 1], "nx": [1.0, 1.0], "ny": [0.0, 0.0], "uncertainty": [0.1, -0.5]})
    with pytest.raises(EvsegError, match=r"key 'index' holds event 3 more than once \(1 repeated rows\)"):
        check_flow({"index": [3, 0, 3], "nx": [1.0, 1.0, 2.0], "ny": [0.0, 0.0, 0.0]})


def test_slice_flow_reindexes_one_window():
    flow = check_flow({"index": [0, 3, 4, 8], "nx": [1.0, 2.0, 3.0, 4.0], "ny": [0.0, 0.0, 0.0, 0.0]})
    part = slice_flow(flow, first=3, n=5)  # events 3..7
    np.testing.assert_array_equal(part.index, [0, 1])
    np.testing.assert_array_equal(part.nx, np.float32([2.0, 3.0]))
    assert part.uncertainty is None


@pytest.fixture(scope="module")
def sim():
    from evseg.simulator import load_scene_preset, simulate

    rec = simulate(load_scene_preset("evimo_like"), seed=1001, duration_us=20_000)
    ok = np.flatnonzero(np.isfinite(rec.normal_flow[:, 0]))
    return rec, {"index": ok, "nx": rec.normal_flow[ok, 0], "ny": rec.normal_flow[ok, 1]}


def test_pipeline_takes_flow_rows_in_any_order(sim):
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    rec, flow = sim
    perm = np.random.default_rng(0).permutation(len(flow["index"]))
    shuffled = {k: v[perm] for k, v in flow.items()}
    runs = []
    for f in (flow, shuffled):
        pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)
        runs.append([r.labels for r in pipe.run(rec.stream, precomputed_flow=f)])
    assert len(runs[0]) == 2
    for a, b in zip(*runs):
        np.testing.assert_array_equal(a, b)


def test_pipeline_refuses_flow_without_a_key(sim):
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig

    rec, flow = sim
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=rec.stream.sensor_size)
    with pytest.raises(EvsegError, match=r"run: precomputed_flow: no key 'ny'"):
        next(pipe.run(rec.stream, precomputed_flow={"index": flow["index"], "nx": flow["nx"]}))


def test_segment_cli_reports_a_bad_flow_file_in_one_line(sim, tmp_path, capsys):
    from evseg.simulator import save_recording

    rec, flow = sim
    save_recording(rec, tmp_path / "sim.npz")
    np.savez(tmp_path / "flow.npz", index=flow["index"], nx=flow["nx"], vy=flow["ny"])  # a misnamed key
    assert main(["segment", str(tmp_path / "sim.npz"), "--flow", str(tmp_path / "flow.npz"),
                 "--out", str(tmp_path / "out.npz"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "flow.npz: no key 'ny' (expected index, nx, ny[, uncertainty])" in err[0], err
    assert not (tmp_path / "out.npz").exists()


def test_a_nan_uncertainty_is_refused_not_dropped_silently():
    data = {"index": np.array([0, 1]), "nx": np.array([1.0, 2.0]), "ny": np.array([0.0, 0.0]),
            "uncertainty": np.array([0.1, np.nan])}
    with pytest.raises(EvsegError, match=r"key 'uncertainty' is NaN for event 1 \(use inf for a flow to ignore"):
        check_flow(data)
    data["uncertainty"] = np.array([0.1, np.inf])  # inf: a flow to ignore, as the plane fit marks rejected fits
    assert np.isinf(check_flow(data)["uncertainty"][1])


@pytest.mark.parametrize("kwargs, message", [
    (dict(index=None), "no key 'index'"),
    (dict(config={"f": object()}), "config must be JSON-serialisable settings"),
    (dict(window_us="10ms"), "window_us must be a positive integer \\(us\\), got '10ms'"),
    (dict(sensor_size="346x260"), "sensor_size must be \\(width, height\\)"),
])
def test_save_flow_file_names_a_bad_argument(tmp_path, kwargs, message):
    args = dict(index=np.array([0, 1]), nx=np.array([1.0, 2.0]), ny=np.array([0.0, 1.0]))
    args.update(kwargs)
    with pytest.raises(EvsegError, match=message):
        save_flow_file(tmp_path / "f.npz", **args)
    assert not (tmp_path / "f.npz").exists()


def test_writers_refuse_a_folder_before_writing(tmp_path):
    from evseg.events import EventStream, make_events
    from evseg.io import write_npz

    (tmp_path / "out.npz").mkdir()
    with pytest.raises(EvsegError, match="out.npz: is a folder; give a file name to write"):
        save_flow_file(tmp_path / "out.npz", np.array([0]), np.array([1.0]), np.array([0.0]))
    with pytest.raises(EvsegError, match="is a folder"):
        write_npz(EventStream(make_events([0], [0], [0], [1]), (4, 4)), tmp_path / "out.npz")


@pytest.mark.parametrize("key, meant", [("uncertainity", "uncertainty"), ("sigma", "uncertainty"),
                                        ("Confidence", "uncertainty"), ("idx", "index"), ("n_x", "nx")])
def test_a_misnamed_flow_key_is_refused_not_ignored(tmp_path, key, meant):
    # A misspelt uncertainty was dropped silently: the flow then counted as exact, and the
    # segmentation reported 15 objects instead of 3 on a simulated recording.
    flow = {"index": np.array([0, 1]), "nx": np.array([1.0, 2.0]), "ny": np.array([0.0, 0.0]),
            "uncertainty": np.array([0.1, 0.1])}
    flow[key] = flow.pop(meant)
    with pytest.raises(EvsegError, match=rf"precomputed flow: key '{key}' is not a flow key; did you mean '{meant}'\?"):
        check_flow(flow)
    np.savez(tmp_path / "f.npz", **flow)
    with pytest.raises(FormatError, match=rf"f.npz: key '{key}' is not a flow key"):
        load_flow_file(tmp_path / "f.npz")


def test_extra_keys_that_mean_nothing_else_are_kept_out_of_the_way():
    flow = check_flow({"index": np.array([0]), "nx": np.array([1.0]), "ny": np.array([0.0]),
                       "t": np.array([5]), "x": np.array([1]), "sensor_size": np.array([4, 4])})
    assert sorted(flow) == ["index", "nx", "ny"]


def test_a_path_where_the_arrays_belong_points_to_load_flow_file():
    with pytest.raises(EvsegError, match=r"precomputed flow: expected a mapping of arrays index, nx, ny\[, uncertainty\], "
                                         r"got str \(a file: load_flow_file\(path\) reads it\)"):
        check_flow("flow.npz")

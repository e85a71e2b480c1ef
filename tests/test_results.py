import numpy as np
import pytest

from evseg.errors import FormatError
from evseg.results import ResultWriter, load_result


def test_writer_roundtrip_with_masks(tmp_path):
    path = tmp_path / "out" / "result.npz"
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:5] = True
    with ResultWriter(path, n_events=7, sensor_size=(6, 4), config_yaml="a: 1\n", with_masks=True) as w:
        w.add_labels([0, 0, 1])
        w.add_window(0, 10, {1: (2, 1, 4, 2)}, {1: mask})
        w.add_labels([1, 0])
        w.add_window(10, 20, {})
    r = load_result(path)
    assert r.label.dtype == np.int16
    assert r.label.tolist() == [0, 0, 1, 1, 0, -1, -1]  # events beyond the windows: -1
    assert r.window_t0_us.tolist() == [0, 10] and r.window_t1_us.tolist() == [10, 20]
    assert r.boxes.tolist() == [[0, 1, 2, 1, 4, 2]]
    np.testing.assert_array_equal(r.mask(0), mask)
    assert not r.partial and r.n_events_processed == 5 and r.config == "a: 1\n"
    assert [p.name for p in path.parent.iterdir()] == ["result.npz"]  # no temp files left


def test_interrupted_run_leaves_readable_partial_result(tmp_path):
    path = tmp_path / "result.npz"
    with pytest.raises(KeyboardInterrupt):
        with ResultWriter(path, n_events=4, sensor_size=(2, 2)) as w:
            w.add_labels([0, 2])
            w.add_window(0, 10, {2: (0, 0, 1, 1)})
            raise KeyboardInterrupt
    r = load_result(path)
    assert r.partial and r.n_events_processed == 2
    assert r.label.tolist() == [0, 2, -1, -1]


def test_existing_file_untouched_until_close(tmp_path):
    path = tmp_path / "result.npz"
    path.write_bytes(b"previous")
    w = ResultWriter(path, n_events=1, sensor_size=(1, 1))
    w.add_labels([0])
    assert path.read_bytes() == b"previous"
    w.abort()
    assert path.read_bytes() == b"previous"


def test_load_rejects_other_npz(tmp_path):
    p = tmp_path / "x.npz"
    np.savez(p, a=np.zeros(2))
    with pytest.raises(FormatError, match="not an evseg result"):
        load_result(p)


def test_unknown_length_stream_and_gap_fill(tmp_path):
    path = tmp_path / "r.npz"
    with ResultWriter(path, n_events=None, sensor_size=(2, 2)) as w:
        w.add_labels([0])
        w.add_unassigned(3)
        w.add_labels([1])
    assert load_result(path).label.tolist() == [0, -1, -1, -1, 1]


def test_load_names_a_file_that_is_no_npz(tmp_path):
    h5 = tmp_path / "events.h5"
    h5.write_bytes(b"\x89HDF\r\n\x1a\n" + bytes(64))
    with pytest.raises(FormatError, match=r"events.h5: not an .npz archive \(a segmentation result is one"):
        load_result(h5)


def test_labels_of_a_sorted_copy_go_back_to_file_order(tmp_path):
    # File events 0..4 came in time order 3, 0, 4, 1, 2 (input_order): labels arrive in that order.
    path = tmp_path / "r.npz"
    with ResultWriter(path, n_events=None, sensor_size=(2, 2)) as w:
        w.set_input_order(np.array([3, 0, 4, 1, 2]))
        w.add_labels([30, 0, 40, 10, 20])
        w.add_window(0, 10, {})
    assert load_result(path).label.tolist() == [0, 10, 20, 30, 40]
    # Interrupted after 2 events: the first two in time order are labelled, the rest -1.
    with pytest.raises(KeyboardInterrupt):
        with ResultWriter(path, n_events=None, sensor_size=(2, 2)) as w:
            w.set_input_order(np.array([3, 0, 4, 1, 2]))
            w.add_labels([30, 0])
            w.add_window(0, 10, {})
            raise KeyboardInterrupt
    r = load_result(path)
    assert r.partial and r.label.tolist() == [0, -1, -1, 30, -1]


def test_labels_of_a_window_whose_successor_was_dropped_stand(tmp_path):
    # 20 ms windows every 10 ms, events every ms: window 1 [10, 30) ms is segmented, window 2
    # [20, 40) is dropped (a live run falling behind), window 3 [30, 50) is segmented.
    from types import SimpleNamespace

    from evseg.runner import write_window_labels

    t = np.arange(0, 50_000, 1_000)

    def window(index):
        t0 = index * 10_000
        first = int(np.searchsorted(t, t0))
        ev = np.zeros(int(np.searchsorted(t, t0 + 20_000)) - first, dtype=[("t", "<i8")])
        ev["t"] = t[first : first + len(ev)]
        return SimpleNamespace(index=index, first_event=first, events=ev, t0_us=t0,
                               labels=np.full(len(ev), index, dtype=np.int16))

    path = tmp_path / "r.npz"
    with ResultWriter(path, n_events=len(t), sensor_size=(2, 2)) as w:
        for res in write_window_labels(w, [window(1), window(3)], stride_us=10_000):
            w.add_window(res.t0_us, res.t0_us + 20_000, {})
    label = load_result(path).label
    assert (label[:10] == -1).all()  # before window 1
    assert (label[10:30] == 1).all()  # window 1, and its second half, which dropped window 2 left
    assert (label[30:50] == 3).all()  # window 3 to the end (no window after it)
    # Without a drop each window keeps only its first stride.
    with ResultWriter(path, n_events=len(t), sensor_size=(2, 2)) as w:
        for res in write_window_labels(w, [window(i) for i in range(5)], stride_us=10_000):
            w.add_window(res.t0_us, res.t0_us + 20_000, {})
    assert load_result(path).label.tolist() == [i for i in range(5) for _ in range(10)]


def test_a_mask_of_another_shape_is_refused_not_stored_shifted(tmp_path):
    w = ResultWriter(tmp_path / "r.npz", None, (8, 6), with_masks=True)
    w.add_labels(np.zeros(3, np.int16))
    with pytest.raises(ValueError, match=r"window 0: the mask of object 1 has shape \(8, 6\), expected \(height, width\) = \(6, 8\)"):
        w.add_window(0, 10, {1: (0, 0, 1, 1)}, {1: np.zeros((8, 6), bool)})
    w.abort()


def test_load_result_refuses_arrays_that_do_not_fit_the_schema(tmp_path):
    good = dict(label=np.zeros(3, np.int16), window_t0_us=np.zeros(1, np.int64), window_t1_us=np.ones(1, np.int64),
                boxes=np.zeros((0, 6), np.int64), sensor_size=np.array([8, 6]))
    for key, value, message in (("label", np.zeros(3), "key 'label' must be 1-D integers"),
                                ("boxes", np.zeros((2, 3), np.int64), "key 'boxes' must have rows"),
                                ("sensor_size", np.array([8, 6, 1]), "key 'sensor_size' must be \\[width, height\\]")):
        np.savez(tmp_path / "r.npz", **{**good, key: value})
        with pytest.raises(FormatError, match=message):
            load_result(tmp_path / "r.npz")

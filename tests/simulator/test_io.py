"""Saving and loading simulated recordings."""


import numpy as np
import pytest

from evseg.errors import FormatError
from evseg.simulator import load_recording, load_scene_preset, save_recording, simulate


@pytest.fixture(scope="module")
def rec():
    return simulate(load_scene_preset("evimo_like").with_sensor_size(96, 72), seed=7, duration_us=20_000)


def test_round_trip_keeps_events_ground_truth_config_and_masks(rec, tmp_path):
    path = save_recording(rec, tmp_path / "sim.npz")
    back = load_recording(path)
    np.testing.assert_array_equal(back.events, rec.events)
    np.testing.assert_array_equal(back.label, rec.label)
    np.testing.assert_array_equal(back.flow, rec.flow)
    np.testing.assert_array_equal(back.normal_flow, rec.normal_flow)
    assert back.config == rec.config and back.seed == rec.seed and back.duration_us == rec.duration_us
    assert back.object_ids == rec.object_ids and back.stream.sensor_size == rec.stream.sensor_size
    # masks are re-rendered from config + seed + duration: identical
    for t in (0, 9_000, 19_999):
        np.testing.assert_array_equal(back.object_masks(t), rec.object_masks(t))
        assert back.object_boxes(t) == rec.object_boxes(t)
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*.tmp"))  # atomic write left nothing behind


def test_saved_file_gets_the_usual_permissions(rec, tmp_path):
    # mkstemp's temporary file is 0600: a recording others on the machine could not read.
    import os

    old = os.umask(0o022)
    try:
        path = save_recording(rec, tmp_path / "sim.npz")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o644


def test_saved_file_is_a_plain_event_npz(rec, tmp_path):
    path = save_recording(rec, tmp_path / "plain.npz")
    with np.load(path, allow_pickle=False) as z:  # no pickles: readable anywhere
        assert z["events"].dtype.names == ("x", "y", "t", "p")
        assert z["label"].dtype == np.int16


def test_bad_files_raise_format_error(rec, tmp_path):
    with pytest.raises(FormatError, match="no such file"):
        load_recording(tmp_path / "missing.npz")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip at all")
    with pytest.raises(FormatError, match=r"junk.npz: not an .npz archive") as info:
        load_recording(junk)
    assert "pickle" not in str(info.value)  # numpy's advice to unpickle a text file is not passed on
    other = tmp_path / "other.npz"
    np.savez(other, events=rec.events)
    with pytest.raises(FormatError, match="entry 'label' is missing"):
        load_recording(other)
    path = save_recording(rec, tmp_path / "trunc.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(FormatError, match="trunc.npz"):
        load_recording(path)


def test_shape_mismatch_is_reported(rec, tmp_path):
    path = tmp_path / "bad.npz"
    save_recording(rec, path)
    with np.load(path) as z:
        d = dict(z)
    d["flow"] = d["flow"][:-1]
    np.savez(path, **d)
    with pytest.raises(FormatError, match="entry 'flow' has shape"):
        load_recording(path)


def test_a_file_of_an_older_ground_truth_loads_with_a_warning_naming_it(rec, tmp_path):
    # Files written before the ground-truth version was stored are version 1, whose labels
    # gave objects' rims to the background: still readable, but the user must know.
    path = save_recording(rec, tmp_path / "new.npz")
    assert load_recording(path).ground_truth_version == rec.ground_truth_version == 2
    with np.load(path) as z:
        d = {k: z[k] for k in z.files if k != "ground_truth_version"}
    old = tmp_path / "old.npz"
    np.savez(old, **d)
    with pytest.warns(UserWarning, match=r"old.npz: simulated with ground-truth version 1.*rim.*--seed 7"):
        loaded = load_recording(old)
    assert loaded.ground_truth_version == 1
    np.testing.assert_array_equal(loaded.label, rec.label)  # the labels as stored, not redone
    for bad in (np.int64(3), np.array([2, 2]), np.array("2")):
        np.savez(old, **d, ground_truth_version=bad)
        with pytest.raises(FormatError, match="entry 'ground_truth_version'"):
            load_recording(old)

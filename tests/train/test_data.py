"""Training data: recordings with optical flow, slices, shards, seeds, the datamodule."""

from __future__ import annotations

import numpy as np
import pytest

from evseg.errors import ConfigError, EventDataError, FormatError
from evseg.train.augment import NO_AUGMENTATION, AugmentConfig, FlowSlice
from evseg.train.data import (
    FlowTargetDataset,
    NormalFlowDataModule,
    SliceSpec,
    build_shards,
    check_training_seeds,
    draw_slices,
    load_flow_recording,
    load_shard,
    recording_examples,
    slice_examples,
)

EDGE_FLOW_PX_S, EDGE_SENSOR = (800.0, 300.0), (40, 30)  # as written by conftest.write_edge_recording

SMALL = SliceSpec(slice_us=(10_000, 20_000), slices_per_scene=3, max_targets_per_slice=64, targets={"cell_px": 2})


def test_per_event_and_dense_flow_layouts_agree(edge_recording, edge_recording_dense):
    a = load_flow_recording(edge_recording)
    b = load_flow_recording(edge_recording_dense)
    assert a.sensor_size == EDGE_SENSOR
    np.testing.assert_array_equal(a.events, b.events)
    np.testing.assert_array_equal(a.optical_flow, b.optical_flow)
    np.testing.assert_array_equal(a.optical_flow[0], EDGE_FLOW_PX_S)
    assert a.normal_flow is None
    assert set(np.unique(a.events["p"])) == {-1, 1}  # 0/1 converted


def test_recording_errors_name_the_field(tmp_path):
    p = tmp_path / "bad.npz"
    np.savez(p, x=[1], y=[1], t=[0], p=[1], sensor_size=np.array([4, 4]), flow=np.zeros((2, 2)))
    with pytest.raises(FormatError, match="'flow' has shape"):
        load_flow_recording(p)
    np.savez(p, x=[1], y=[1], t=[0], p=[1], sensor_size=np.array([4, 4]))
    with pytest.raises(FormatError, match="flow_maps"):
        load_flow_recording(p)
    np.savez(p, x=[1], y=[1], t=[0], p=[1], flow=np.zeros((1, 2)))
    with pytest.raises(FormatError, match="sensor_size"):
        load_flow_recording(p)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="junk.npz"):
        load_flow_recording(tmp_path / "junk.npz")


def test_float_time_no_flow_and_events_before_the_first_map(edge_recording, tmp_path):
    with np.load(edge_recording) as z:
        rec = dict(z)
    p = tmp_path / "r.npz"
    np.savez(p, **{**rec, "t": rec["t"] / 1e6})  # seconds: casting would make every time 0
    with pytest.raises(FormatError, match=r"r.npz: field 't' must be integer microseconds, got dtype float64"):
        load_flow_recording(p)
    np.savez(p, **{**rec, "flow": np.full_like(rec["flow"], np.nan)})
    with pytest.raises(FormatError, match=r"r.npz: no event has a finite ground-truth flow"):
        load_flow_recording(p)
    # Maps from 20 ms on: the events before have no ground truth (not map 0's flow).
    w, h = EDGE_SENSOR
    maps = np.tile(np.float32(EDGE_FLOW_PX_S), (2, h, w, 1))
    common = {k: rec[k] for k in ("x", "y", "t", "p", "sensor_size")}
    np.savez(p, **common, flow_maps=maps, flow_t_us=np.array([20_000, 40_000]))
    flow = load_flow_recording(p).optical_flow
    early = rec["t"] < 20_000
    assert early.sum() > 100 and np.isnan(flow[early]).all()
    np.testing.assert_array_equal(flow[~early], np.tile(np.float32(EDGE_FLOW_PX_S), ((~early).sum(), 1)))


def test_a_recording_changed_under_its_name_is_encoded_again(edge_recording, tmp_path):
    import os

    dm = NormalFlowDataModule(presets=[], real_recordings=[str(edge_recording)], slices=SMALL,
                              cache_dir=str(tmp_path / "cache"), batch_size=16, build_workers=1)
    before = [job[4] for job in dm._jobs(True)]
    assert before == [job[4] for job in dm._jobs(True)]  # same file: same shard
    st = edge_recording.stat()
    os.utime(edge_recording, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # exported again
    assert [job[4] for job in dm._jobs(True)] != before


def test_held_out_seeds_are_refused():
    check_training_seeds([0, 999], "x")
    with pytest.raises(ConfigError, match="held out"):
        check_training_seeds([998, 1000], "data.train_seeds")
    with pytest.raises(ConfigError, match="held out"):
        NormalFlowDataModule(train_seeds=(0, 1001))
    with pytest.raises(ConfigError, match="overlap"):
        NormalFlowDataModule(train_seeds=(0, 10), val_seeds=(5, 6))


def test_slices_have_the_requested_duration_after_time_scaling(edge_recording):
    rec = load_flow_recording(edge_recording)
    aug = AugmentConfig(rotation=False, flip=False, keep_range=(1, 1), noise_rate_range=(0, 0))
    for s in draw_slices(rec, SMALL, aug, np.random.default_rng(1)):
        span = int(s.events["t"][-1] - s.events["t"][0])
        assert span <= SMALL.slice_us[1] + 1  # +1: rounding of stretched timestamps (us)


def test_examples_skip_targets_without_ground_truth(edge_recording):
    rec = load_flow_recording(edge_recording)
    of = rec.optical_flow.copy()
    of[: len(of) // 2] = np.nan  # first half of the events: unknown flow
    s = FlowSlice(rec.events, rec.sensor_size, None, of)
    ex = slice_examples(s, {}, SliceSpec(max_targets_per_slice=10_000, targets={"cell_px": None}), np.random.default_rng(0))
    assert len(ex["features"]) == len(of) - len(of) // 2
    assert ex["features"].shape[1] == 65  # 2 d + 1 with the default d = 32
    assert np.isfinite(ex["optical_flow"]).all() and np.isnan(ex["normal_flow"]).all()


def test_targets_come_from_the_last_target_us_only(edge_recording):
    """With target_us, earlier events are neighbours only (the pipeline's context): mark each
    event's flow with its time and check that every target lies in the slice's tail."""
    rec = load_flow_recording(edge_recording)
    t = rec.events["t"]
    of = np.stack([t.astype(np.float32), np.ones(len(t), np.float32)], 1)
    s = FlowSlice(rec.events, rec.sensor_size, None, of)
    spec = SliceSpec(max_targets_per_slice=10**6, targets={"cell_px": None}, target_us=3_000)
    ex = slice_examples(s, {}, spec, np.random.default_rng(0))
    tail = t >= t[-1] - 3_000
    assert 0 < len(ex["features"]) == tail.sum() < len(t)
    np.testing.assert_array_equal(ex["optical_flow"][:, 0], t[tail])


def test_examples_are_deterministic_per_seed(edge_recording):
    rec = load_flow_recording(edge_recording)
    a = recording_examples(rec, "edge", 0, {}, SMALL, AugmentConfig())
    b = recording_examples(rec, "edge", 0, {}, SMALL, AugmentConfig())
    c = recording_examples(rec, "edge", 1, {}, SMALL, AugmentConfig())
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a["features"].shape != c["features"].shape or not np.array_equal(a["features"], c["features"])
    # Augmentation rotates the GT optical flow with the events: its magnitude is kept
    # (up to the time/space scale factors, within [0.8/2, 1.25*2] of the original).
    speed = np.linalg.norm(a["optical_flow"], axis=1) / np.hypot(*EDGE_FLOW_PX_S)
    assert np.all((speed > 0.39) & (speed < 2.6))


def test_shards_are_built_once(edge_recording, tmp_path):
    path = tmp_path / "cache" / "edge.npz"
    job = ("real", str(edge_recording), 0, 0, str(path), {}, SMALL, NO_AUGMENTATION)
    (p,) = build_shards([job], num_workers=1)
    assert p == path and path.exists()
    first = path.stat().st_mtime_ns
    build_shards([job], num_workers=1)
    assert path.stat().st_mtime_ns == first
    rows = load_shard(path)
    ds = FlowTargetDataset(rows)
    batch = ds.__getitems__([0, 1, 2])
    assert batch["features"].shape == (3, 65) and str(batch["features"].dtype) == "torch.float32"
    np.testing.assert_allclose(batch["optical_flow"].numpy(), np.tile(EDGE_FLOW_PX_S, (3, 1)))


def test_datamodule_with_a_real_recording_only(edge_recording, tmp_path):
    dm = NormalFlowDataModule(
        presets=[], real_recordings=[str(edge_recording)], real_repeats=2,
        slices=SMALL, cache_dir=str(tmp_path / "cache"), batch_size=16, build_workers=1,
    )
    dm.prepare_data()
    dm.setup("fit")
    assert len(dm.train_set) > 0 and len(dm.val_set) == 0
    batch = next(iter(dm.train_dataloader()))
    assert batch["features"].shape == (16, 65)
    with pytest.raises(ConfigError, match="not found"):
        NormalFlowDataModule(real_recordings=[str(tmp_path / "missing.npz")])


def test_simulated_scene_shard(tmp_path):
    dm = NormalFlowDataModule(
        presets=["evimo_like"], train_seeds=(0, 1), val_seeds=(900, 901), duration_us=40_000,
        slices=SMALL, cache_dir=str(tmp_path / "cache"), batch_size=32, build_workers=1,
    )
    dm.setup("fit")
    rows = dm.train_set.rows
    assert 0 < len(rows["features"]) <= SMALL.slices_per_scene * SMALL.max_targets_per_slice
    # Simulated targets always carry GT normal flow (noise events are never targets).
    assert np.isfinite(rows["normal_flow"]).all()
    assert np.all(np.linalg.norm(rows["normal_flow"], axis=1) > 0)
    # EVIMO-like scenes hold objects: some targets lie on them, the others on the background.
    assert set(np.unique(rows["is_object"]).tolist()) == {0, 1}


def test_shards_of_another_simulator_version_or_preset_are_not_reused(tmp_path, monkeypatch):
    # A user's cache outlives upgrades: shards simulated under an older ground-truth rule, or
    # from a preset since edited, must be rebuilt, not silently trained on.
    import dataclasses

    import evseg.simulator as sim
    import evseg.simulator.ground_truth as gt

    dm = NormalFlowDataModule(presets=["evimo_like"], train_seeds=(0, 1), val_seeds=(900, 901), duration_us=40_000,
                              slices=SMALL, cache_dir=str(tmp_path / "cache"), batch_size=32, build_workers=1)
    before = dm._jobs(True)[0][4]
    assert dm._jobs(True)[0][4] == before
    monkeypatch.setattr(gt, "GROUND_TRUTH_VERSION", gt.GROUND_TRUTH_VERSION + 1)
    assert dm._jobs(True)[0][4] != before
    monkeypatch.undo()
    original = sim.load_scene_preset
    monkeypatch.setattr(sim, "load_scene_preset",
                        lambda name: dataclasses.replace(original(name), max_step_px=0.25))
    assert dm._jobs(True)[0][4] != before


def test_target_selection_drawn_per_slice(edge_recording):
    rec = load_flow_recording(edge_recording)
    spec = SliceSpec(max_targets_per_slice=10**6, targets=[{"cell_px": None}, {"cell_px": 4}])
    counts = {len(slice_examples(rec, {}, spec, np.random.default_rng(i))["features"]) for i in range(12)}
    # all events with flow vs the latest event of each 4x4 cell (10 x 8 cells on 40 x 30 px)
    assert counts == {len(rec), 80}


def _edge_fields(edge_recording) -> dict:
    with np.load(edge_recording) as z:
        return dict(z)


def _broken_recordings(rec: dict) -> dict:
    """name -> (fields of a broken variant of the edge recording, the error's words)."""
    w, h = EDGE_SENSOR
    cols = {k: rec[k] for k in ("x", "y", "t", "p", "sensor_size")}
    maps = np.tile(np.float32(EDGE_FLOW_PX_S), (2, h, w, 1))
    t_maps = np.array([0, 30_000])
    return {
        # events off the sensor are named before the maps are indexed with them (IndexError)
        "off_sensor_maps": ({**cols, "x": rec["x"] + 5, "flow_maps": maps, "flow_t_us": t_maps},
                            r"field 'x' = 40 at event \d+ is outside the sensor \(40x30"),
        "pickled": ({**cols, "flow": np.array([{"a": 1}] * len(rec["x"]), dtype=object)},
                    r"field 'flow' holds Python objects \(a pickled object array\)"),
        "text_flow": ({**cols, "flow": np.array([["a", "b"]] * len(rec["x"]))},
                      r"field 'flow' must hold floating point px/s, got dtype <U1"),
        "t_maps_2d": ({**cols, "flow_maps": maps, "flow_t_us": t_maps[:, None]},
                      r"field 'flow_t_us' has shape \(2, 1\), expected \(K,\)"),
        "t_maps_seconds": ({**cols, "flow_maps": maps, "flow_t_us": t_maps / 1e6},
                           r"field 'flow_t_us' must be integer microseconds, got dtype float64 \(time in seconds"),
        "raw_dsec_maps": ({**cols, "flow_maps": (maps / 100 * 128 + 2**15).astype(np.uint16), "flow_t_us": t_maps},
                          r"field 'flow_maps' has integer dtype uint16; optical flow must be floating point px/s "
                          r".*python -m evseg.train.dsec"),
        "t_nanoseconds": ({**cols, "t": rec["t"].astype(np.int64) * 1000 + 1_700_000_000_000_000_000,
                           "flow": rec["flow"]},
                          r"field 't' = 1700000000000\d+ at 0 is after the year 2100 as microseconds: nanoseconds\?"),
        "empty": ({**{k: v[:0] for k, v in cols.items() if k != "sensor_size"}, "sensor_size": cols["sensor_size"],
                   "flow": rec["flow"][:0]}, r"holds no events"),
        "negative_sensor": ({**cols, "sensor_size": -cols["sensor_size"], "flow": rec["flow"]},
                            r"field 'sensor_size' must be \[width, height\] in whole pixels > 0, got \[-40, -30\]"),
        "fractional_sensor": ({**cols, "sensor_size": cols["sensor_size"] + 0.5, "flow": rec["flow"]},
                              r"field 'sensor_size' must be \[width, height\] in whole pixels > 0, got \[40.5, 30.5\]"),
    }


@pytest.mark.parametrize("name", ["off_sensor_maps", "pickled", "text_flow", "t_maps_2d", "t_maps_seconds",
                                  "t_nanoseconds", "raw_dsec_maps", "empty", "negative_sensor", "fractional_sensor"])
def test_broken_recordings_are_refused_naming_file_and_field(edge_recording, tmp_path, name):
    from evseg.errors import EvsegError

    fields, words = _broken_recordings(_edge_fields(edge_recording))[name]
    path = tmp_path / f"{name}.npz"
    np.savez(path, **fields)
    with pytest.raises(EvsegError, match=rf"^{path}: {words}"):
        load_flow_recording(path)


def test_files_that_are_no_npz_archive_are_named_as_such(tmp_path):
    (tmp_path / "hello.npz").write_text("hello")
    with pytest.raises(FormatError, match=r"hello.npz: not an .npz file \(not a zip archive\)"):
        load_flow_recording(tmp_path / "hello.npz")
    np.save(tmp_path / "one.npy", np.zeros(3))
    with pytest.raises(FormatError, match=r"one.npy: not an .npz file \(a single .npy array\)"):
        load_flow_recording(tmp_path / "one.npy")


def test_a_broken_real_recording_fails_before_any_shard_is_built(edge_recording, tmp_path):
    """The simulated scenes come first in the build and take minutes: a broken real recording
    must fail before them, naming itself, and leave no shard behind."""
    fields, _ = _broken_recordings(_edge_fields(edge_recording))["off_sensor_maps"]
    bad = tmp_path / "bad.npz"
    np.savez(bad, **fields)
    dm = NormalFlowDataModule(presets=["eed_like"], train_seeds=(0, 1), val_seeds=(900, 901), duration_us=40_000,
                              real_recordings=[str(edge_recording), str(bad)], slices=SMALL,
                              cache_dir=str(tmp_path / "cache"), batch_size=16, build_workers=1)
    for step in (dm.prepare_data, lambda: dm.setup("fit")):
        with pytest.raises(EventDataError, match=rf"^{bad}: field 'x'"):
            step()
        assert not list((tmp_path / "cache").rglob("*.npz"))


@pytest.mark.parametrize("kwargs, message", [
    ({"slices": SliceSpec(slice_us=(30_000, 10_000))},
     r"data.slices.slice_us must be \[min, max\] whole microseconds with 0 < min <= max, got \[30000, 10000\]"),
    ({"slices": SliceSpec(slices_per_scene=0)}, r"data.slices.slices_per_scene must be a whole number >= 1, got 0"),
    ({"slices": SliceSpec(targets=[{"cell_px": 2}, {"cellpx": 4}])},
     r"data.slices.targets: unknown option\(s\) \['cellpx'\]"),
    ({"augment": AugmentConfig(keep_range=(0.0, 1.0))},
     r"data.augment.keep_range must be \[low, high\] with low <= high, both in \(0, 1\], got \[0.0, 1.0\]"),
    ({"batch_size": 0}, r"data.batch_size must be a whole number >= 1, got 0"),
    ({"real_repeats": 0}, r"data.real_repeats must be a whole number >= 1, got 0"),
    ({"duration_us": 1.5}, r"data.duration_us must be a whole number >= 1, got 1.5"),
    ({"presets": ["nope"]}, r"data.presets: unknown scene preset\(s\) \['nope'\]; known: .*eed_like"),
    ({"train_seeds": (64, 0)}, r"data.train_seeds must be \[start, stop\) with whole numbers start <= stop, "
                               r"got \[64, 0\]"),
])
def test_bad_data_settings_are_refused_by_name(kwargs, message):
    with pytest.raises(ConfigError, match=message):
        NormalFlowDataModule(**kwargs)

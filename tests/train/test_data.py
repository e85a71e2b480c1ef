"""Training data: recordings with optical flow, slices, shards, seeds, the datamodule."""

from __future__ import annotations

import numpy as np
import pytest

from evseg.errors import ConfigError, FormatError
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


def test_target_selection_drawn_per_slice(edge_recording):
    rec = load_flow_recording(edge_recording)
    spec = SliceSpec(max_targets_per_slice=10**6, targets=[{"cell_px": None}, {"cell_px": 4}])
    counts = {len(slice_examples(rec, {}, spec, np.random.default_rng(i))["features"]) for i in range(12)}
    # all events with flow vs the latest event of each 4x4 cell (10 x 8 cells on 40 x 30 px)
    assert counts == {len(rec), 80}

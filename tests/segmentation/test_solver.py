"""End-to-end segmentation of synthetic normal flow (no simulator needed)."""

import numpy as np
import pytest

from evseg.segmentation import SegmentationConfig, load_segmentation_config, propagate_labels, segment_normal_flow
from evseg.segmentation.motion_model import flow_field
from evseg.segmentation.synthetic import synthetic_scene


def majority(true_labels, found, k):
    vals, counts = np.unique(found[true_labels == k], return_counts=True)
    return vals[np.argmax(counts)], counts.max() / counts.sum()


@pytest.mark.parametrize("seed", [0, 1, 3])
def test_two_objects_are_found_with_their_models(seed):
    s = synthetic_scene(n_flows=2500, n_objects=2, seed=seed)
    # Noise-free flow allows a tight residual scale; with the default (0.2 x median |n|, set
    # for simulated sensors) the two objects of seed 1, whose flows differ by ~3 sigma at their
    # centres, cost less as one label than as two, and the energy rightly merges them.
    cfg = SegmentationConfig(residual_scale_rel=0.1)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
    truth = s.label[r.node_index]
    assert r.n_objects == 2
    labels_of = {}
    for k in (0, 1, 2):
        lab, share = majority(truth, r.node_labels, k)
        # nodes near an object's boundary may take the neighbour's label: 95 % agreement
        assert share > 0.95
        labels_of[k] = lab
    assert labels_of[0] == 0 and sorted([labels_of[1], labels_of[2]]) == [1, 2]
    for k, lab in labels_of.items():
        # Flow at the object's centre (the background's: sensor centre). A few boundary nodes
        # of the neighbour bias the robust fit a little: 3 px/s is < 1 % of the speeds here.
        cx, cy = (s.centers[k - 1] if k else np.array(s.sensor_size) / 2.0) - np.array(s.origin_px)
        got = flow_field(r.models[lab : lab + 1], np.array([cx]), np.array([cy]))
        want = flow_field(s.models[k : k + 1], np.array([cx]), np.array([cy]))
        np.testing.assert_allclose(np.ravel(got), np.ravel(want), atol=3.0)
    assert set(r.boxes) == {1, 2} and set(r.masks) == {1, 2}
    for obj in (1, 2):
        lab = labels_of[obj]
        cx, cy = s.centers[obj - 1]
        x0, y0, x1, y1 = r.boxes[lab]
        assert x0 <= cx <= x1 and y0 <= cy <= y1
        assert r.masks[lab][int(cy), int(cx)]
        assert r.masks[lab].shape == (s.sensor_size[1], s.sensor_size[0])
    for key in ("preprocessing", "initialization", "labeling_fitting"):
        assert r.timings[key] >= 0


def test_cpu_timings_count_cpu_time_only(monkeypatch):
    """The '_cpu' stage timings (`evseg bench seg`'s cpu columns) are CPU time: a wall clock
    that runs far ahead of the CPU, as on a machine where other processes take the cores,
    must not leak into them (round 0's fits were moved from initialization to labeling and
    fitting by their wall time, which made initialization_cpu negative under load)."""
    import itertools
    import time

    s = synthetic_scene(n_flows=1500, n_objects=2, seed=0)
    fake = itertools.count(0.0, 1000.0)  # each perf_counter() call: 1000 s later
    monkeypatch.setattr(time, "perf_counter", lambda: next(fake))
    t0 = time.process_time()
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)
    cpu_ms = (time.process_time() - t0) * 1e3
    for key in ("preprocessing_cpu", "initialization_cpu", "labeling_fitting_cpu", "outputs_cpu"):
        assert 0 <= r.timings[key] <= cpu_ms + 1.0, (key, r.timings[key], cpu_ms)
    assert r.timings["labeling_fitting"] >= 1e6  # the fake wall clock did run


def test_propagate_labels_nearest_node_and_distance_limit():
    s = synthetic_scene(n_flows=1500, n_objects=1, seed=2)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)
    lab = propagate_labels(r, r.node_x, r.node_y)
    np.testing.assert_array_equal(lab, r.node_labels)
    far = propagate_labels(r, np.array([-1000.0]), np.array([-1000.0]))
    assert far.tolist() == [-1]
    every = propagate_labels(r, s.x, s.y)
    assert every.shape == s.x.shape


def test_motion_prediction_supplies_candidates():
    s = synthetic_scene(n_flows=2500, n_objects=2, seed=1)
    cfg = SegmentationConfig()
    first = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
    second = segment_normal_flow(s.x, s.y, s.t + 10_000, s.nx, s.ny, config=cfg,
                                 sensor_size=s.sensor_size, previous=first)
    assert second.n_predicted >= 2  # background + at least one object
    assert second.n_candidates <= second.n_predicted + cfg.n_sampled_with_prediction
    assert second.n_objects == 2


def test_tracked_objects_supply_candidates_fast_sampling_does_not():
    """A tracker's box and model (the pipeline's tracks, alive through a missed window) give
    the object its candidate; with one sampled candidate (the background's) and no track the
    object cannot be found."""
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=4)
    # A coarse residual scale (wide sampling bins) makes the background's translations the
    # one sampled mode; with the default fine scale this spinning background spreads over
    # many bins and the object's translation would be the mode.
    cfg = SegmentationConfig(n_sampled=1, n_sampled_with_prediction=1, n_resampled=0,
                             residual_scale_rel=0.2, residual_scale_noise=0.0)
    alone = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
    assert alone.n_objects == 0
    np.testing.assert_allclose(alone.models[0], s.models[0], rtol=1e-3, atol=0.5)
    on = s.label == 1
    box = np.array([[s.x[on].min(), s.y[on].min(), s.x[on].max(), s.y[on].max()]])
    tracked = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size,
                                  tracked_objects=(box, s.models[1:2]))
    assert tracked.n_predicted == 1 and tracked.n_objects == 1
    lab, share = majority(s.label[tracked.node_index], tracked.node_labels, 1)
    assert lab == 1 and share > 0.9


def test_outliers_do_not_create_objects():
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=4, outlier_fraction=0.3)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)
    assert r.n_objects == 1
    truth = s.label[r.node_index]
    lab, share = majority(truth, r.node_labels, 1)
    assert lab == 1 and share > 0.8


@pytest.mark.parametrize("n", [0, 1, 2, 3])
def test_tiny_and_degenerate_inputs(n):
    x = np.arange(n, dtype=float) * 10
    y = np.arange(n, dtype=float) * 10  # collinear
    r = segment_normal_flow(x, y, np.arange(n), np.full(n, 30.0), np.zeros(n), sensor_size=(64, 48))
    assert len(r.node_labels) == n
    assert np.all(r.node_labels <= 0)
    assert r.models.shape[1] == 4 and len(r.models) <= 1


def test_inputs_not_modified_and_bad_shapes_rejected():
    from evseg.errors import EventDataError

    s = synthetic_scene(n_flows=800, n_objects=1, seed=5)
    arrays = [s.x, s.y, s.t, s.nx, s.ny]
    copies = [a.copy() for a in arrays]
    segment_normal_flow(*arrays, sensor_size=s.sensor_size)
    for a, b in zip(arrays, copies):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(EventDataError, match="ny"):
        segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny[:-1])


def test_two_objects_with_the_same_motion_are_two_objects():
    models = np.array([[1.0, 0.0, 40.0, 10.0], [1.0, 0.0, -300.0, 200.0], [1.0, 0.0, -300.0, 200.0]])
    s = synthetic_scene(n_flows=3000, n_objects=2, seed=7, models=models)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)
    if np.hypot(*(s.centers[0] - s.centers[1])) < s.radii.sum() + 5:
        pytest.skip("the random discs touch")  # seed 7 keeps them apart; guard anyway
    assert r.n_objects == 2
    np.testing.assert_allclose(r.models[1], r.models[2])  # one motion, two objects
    truth = s.label[r.node_index]
    assert {majority(truth, r.node_labels, 1)[0], majority(truth, r.node_labels, 2)[0]} == {1, 2}


def test_split_objects_unit():
    from evseg.segmentation.outputs import split_objects

    # chain 0-1-2-3-4-5-6: label 1 on {0,1,2} and {5,6} (two parts), 0 on {3,4}
    labels = np.array([1, 1, 1, 0, 0, 1, 1])
    edges = np.array([[i, i + 1] for i in range(6)])
    models = np.array([[1.0, 0, 0, 0], [1.0, 0, 5, 5]])
    new, mod, regions = split_objects(labels, edges, models, min_nodes=2)
    np.testing.assert_array_equal(new, [1, 1, 1, 0, 0, 2, 2])
    assert len(mod) == 3 and sorted(regions) == [1, 2]
    new, mod, regions = split_objects(labels, edges, models, min_nodes=3)
    np.testing.assert_array_equal(new, [1, 1, 1, 0, 0, 1, 1])  # fragment stays with its label
    np.testing.assert_array_equal(regions[1], [0, 1, 2])


def test_split_objects_joins_nearby_pieces_of_one_label():
    from evseg.segmentation.outputs import split_objects

    # label 1 in three pieces along a line: {0,1,2} at x 0..2, {4,5,6} at x 6..8 (gap 4 px),
    # {8,9,10} at x 40..42; label 0 between them
    x = np.array([0, 1, 2, 4, 6, 7, 8, 20, 40, 41, 42], dtype=float)
    y = np.zeros(11)
    labels = np.array([1, 1, 1, 0, 1, 1, 1, 0, 1, 1, 1])
    edges = np.array([[i, i + 1] for i in range(10)])
    models = np.array([[1.0, 0, 0, 0], [1.0, 0, 5, 5]])
    new, mod, regions = split_objects(labels, edges, models, 3, x, y, gap_px=5.0)
    np.testing.assert_array_equal(new, [1, 1, 1, 0, 1, 1, 1, 0, 2, 2, 2])
    new, _, _ = split_objects(labels, edges, models, 3, x, y, gap_px=0.0)
    assert len(np.unique(new[new > 0])) == 3


def test_split_objects_joins_the_parts_of_an_occluded_object():
    """Two pieces of label 1, 20 px apart, are one object when label 2 (an object in front)
    touches both; the same pieces with background between them stay two objects, and a stray
    node of label 1 inside the occluder never joins (it has fewer than min_nodes nodes)."""
    from evseg.segmentation.outputs import split_objects

    # chain along x: label 1 on x 0..2, the gap x 6..18, label 1 on x 22..24, a lone 1 at x 30
    x = np.array([0, 1, 2, 6, 10, 14, 18, 22, 23, 24, 30], dtype=float)
    y = np.zeros(11)
    edges = np.array([[i, i + 1] for i in range(10)])
    models = np.array([[1.0, 0, 0, 0], [1.0, 0, 5, 5], [1.0, 0, -5, 0]])
    occluded = np.array([1, 1, 1, 2, 2, 2, 2, 1, 1, 1, 2])
    kw = dict(min_nodes=3, x=x, y=y, gap_px=5.0, occlusion_gap_px=24.0)
    new, mod, regions = split_objects(occluded, edges, models, **kw)
    np.testing.assert_array_equal(new, [1, 1, 1, 2, 2, 2, 2, 1, 1, 1, 2])
    np.testing.assert_array_equal(regions[1], [0, 1, 2, 7, 8, 9])
    # beyond occlusion_gap_px (19 px gap > 18), or with the rule off: two objects
    for far in (dict(kw, occlusion_gap_px=18.0), dict(kw, occlusion_gap_px=0.0)):
        new, _, regions = split_objects(occluded, edges, models, **far)
        assert sorted(regions) == [1, 2, 3]
    # background between the pieces: two objects moving alike
    apart = np.where(occluded == 2, 0, occluded)
    new, _, regions = split_objects(apart, edges, models[:2], **kw)
    np.testing.assert_array_equal(new, [1, 1, 1, 0, 0, 0, 0, 2, 2, 2, 0])
    # a stray node of label 1 inside the occluder (node 11, tied to 4 and 5) touches it like
    # the left piece does, but is no part: it stays out of the piece's region
    xs, ys = np.append(x, 12.0), np.append(y, 1.0)
    es = np.vstack([edges, [[4, 11], [5, 11]]])
    stray = np.append(np.where(np.arange(11) == 6, 0, occluded), 1)  # node 6: background
    new, _, regions = split_objects(stray, es, models, **dict(kw, x=xs, y=ys))
    np.testing.assert_array_equal(regions[1], [0, 1, 2])
    assert new[11] == 1 and sorted(regions) == [1, 2, 3]


def test_split_objects_turns_a_scattered_label_into_background():
    """A label in three separate pieces is a patch of a background layer when at most two
    objects may share a label (max_parts=2); two pieces stay two objects."""
    from evseg.segmentation.outputs import split_objects

    # chain: label 1 on {0,1,2}, {4,5,6}, {8,9,10}; label 0 on 3 and 7
    labels = np.array([1, 1, 1, 0, 1, 1, 1, 0, 1, 1, 1])
    edges = np.array([[i, i + 1] for i in range(10)])
    models = np.array([[1.0, 0, 0, 0], [1.0, 0, 5, 5]])
    new, mod, regions = split_objects(labels, edges, models, 3, max_parts=2)
    np.testing.assert_array_equal(new, np.zeros(11))
    assert len(mod) == 1 and regions == {}
    new, _, regions = split_objects(labels, edges, models, 3, max_parts=3)
    assert sorted(regions) == [1, 2, 3]
    two = np.where(np.arange(11) >= 8, 0, labels)
    new, _, regions = split_objects(two, edges, models, 3, max_parts=2)
    np.testing.assert_array_equal(new, [1, 1, 1, 0, 2, 2, 2, 0, 0, 0, 0])


def test_tracked_label_cost_keeps_a_tracked_object_that_a_full_label_cost_removes():
    """With a label cost far above what the object saves, only a tracked object whose label
    pays the reduced share survives (hysteresis); untracked candidates still pay in full."""
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=4)
    on = s.label == 1
    box = np.array([[s.x[on].min(), s.y[on].min(), s.x[on].max(), s.y[on].max()]])
    saving = 9.0 * on.sum()  # at most tau^2 per object node
    kw = dict(sensor_size=s.sensor_size, tracked_objects=(box, s.models[1:2]))
    full = SegmentationConfig(lambda_m=2.0 * saving)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=full, **kw)
    assert r.n_objects == 0
    kept = SegmentationConfig(lambda_m=2.0 * saving, tracked_label_cost=0.01)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=kept, **kw)
    assert r.n_objects == 1
    lab, share = majority(s.label[r.node_index], r.node_labels, 1)
    assert lab == 1 and share > 0.9
    # Without a track nothing is discounted: the object still cannot pay its label.
    alone = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=kept, sensor_size=s.sensor_size)
    assert alone.n_objects == 0


def test_data_cost_with_node_scale_is_exact():
    """cost = c * min((r / (sigma * s_k))^2, tau^2): hand-computed for one node, one model."""
    from evseg.segmentation.energy import data_costs

    # Model: pure translation (10, 0) px/s (rho = theta = 0). Node flow (4, 0): residual
    # n.u/|n| - |n| = 10 - 4 = 6 px/s.
    model = np.array([[0.0, 0.0, 10.0, 0.0]])
    one = np.array([0.0])
    args = (model, one, one, np.array([4.0]), one, 2.0, 3.0)
    assert data_costs(*args)[0, 0] == pytest.approx(9.0)  # (6 / 2)^2 = 9 = tau^2
    assert data_costs(*args, node_scale=np.array([2.0]))[0, 0] == pytest.approx(2.25)  # (6 / 4)^2
    assert data_costs(*args, confidence=np.array([0.5]), node_scale=np.array([1.5]))[0, 0] == pytest.approx(2.0)


def test_data_cost_with_angular_uncertainty_is_exact():
    """The angular uncertainty a propagated through each model (uncertainty_angle_gain):
    s^2 = (sigma s_k)^2 + (a * flow along the edge)^2, cost r^2 / s^2 + log(s^2 / (sigma s_k)^2)."""
    from evseg.segmentation.energy import data_costs

    # Node at the origin, flow (4, 0) (edge along y). Models: translation (10, 0) (along the
    # normal: residual 6, nothing along the edge) and (10, 8) (same residual, 8 px/s along it).
    models = np.array([[0.0, 0.0, 10.0, 0.0], [0.0, 0.0, 10.0, 8.0]])
    one = np.array([0.0])
    args = (models, one, one, np.array([4.0]), one, 2.0, 5.0)
    plain = data_costs(*args, node_scale=np.array([1.5]))
    assert plain[0] == pytest.approx([4.0, 4.0])  # (6 / 3)^2
    # a = 0.5 rad: 0.5 * 8 = 4 px/s along the edge; s^2 = 9 + 16 = 25.
    cost = data_costs(*args, node_scale=np.array([1.5]), node_angle=np.array([0.5]))
    assert cost[0] == pytest.approx([4.0, 36 / 25 + np.log(25 / 9)])
    # No angular uncertainty is exactly the plain cost (same floats), and truncation still caps it.
    assert np.array_equal(data_costs(*args, node_scale=np.array([1.5]), node_angle=np.zeros(1)), plain)
    huge = data_costs(*args, node_scale=np.array([1.5]), node_angle=np.array([1e6]))
    assert huge[0, 0] == pytest.approx(4.0) and huge[0, 1] == pytest.approx(25.0)  # tau^2


def test_angular_uncertainty_is_used_and_keeps_the_fast_object():
    """With uncertainty_angle_gain the uncertain fast object of the scene below is still found,
    and the labelling is not the one without the term (it is used)."""
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=2)
    rng = np.random.default_rng(0)
    u = np.where(s.label == 1, 0.3, 0.05)
    gain = 1.0 + u * rng.standard_normal(len(u))
    nx, ny = s.nx * gain, s.ny * gain
    kw = dict(uncertainty=u, sensor_size=s.sensor_size)
    r = segment_normal_flow(s.x, s.y, s.t, nx, ny, config=SegmentationConfig(uncertainty_angle_gain=1.0), **kw)
    assert r.n_objects == 1
    lab, share = majority(s.label[r.node_index], r.node_labels, 1)
    assert lab == 1 and share > 0.9
    r0 = segment_normal_flow(s.x, s.y, s.t, nx, ny, config=SegmentationConfig(uncertainty_angle_gain=0.0), **kw)
    assert not np.array_equal(r0.node_labels, r.node_labels)


def test_uncertain_fast_object_keeps_its_pull_in_scale_mode():
    """Flows with a relative magnitude error of about their uncertainty (the learned flow: a
    fast object's flows are the least certain) still give the object, with 'scale' use of the
    uncertainty; every node's residual scale is sigma_k = sqrt(sigma^2 + (|n_k| u_k)^2)."""
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=2)
    rng = np.random.default_rng(0)
    u = np.where(s.label == 1, 0.3, 0.05)
    gain = 1.0 + u * rng.standard_normal(len(u))
    nx, ny = s.nx * gain, s.ny * gain
    r = segment_normal_flow(s.x, s.y, s.t, nx, ny, uncertainty=u, sensor_size=s.sensor_size,
                            config=SegmentationConfig(uncertainty_use="scale"))
    assert r.n_objects == 1
    lab, share = majority(s.label[r.node_index], r.node_labels, 1)
    assert lab == 1 and share > 0.9
    # The same flows without their uncertainty must not be segmented identically (it is used).
    r0 = segment_normal_flow(s.x, s.y, s.t, nx, ny, sensor_size=s.sensor_size)
    assert not np.array_equal(r0.node_labels, r.node_labels)


def test_residual_scale_follows_the_flow_noise():
    """Exact flow keeps sigma near its floor; noisy flow of the same scene widens it."""
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=4)
    exact = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)
    rng = np.random.default_rng(0)
    norm = np.hypot(s.nx, s.ny)
    noisy_mag = norm + rng.normal(0.0, 20.0, len(norm))
    noisy = segment_normal_flow(s.x, s.y, s.t, s.nx / norm * noisy_mag, s.ny / norm * noisy_mag,
                                sensor_size=s.sensor_size)
    rel = SegmentationConfig().residual_scale_rel * float(np.median(norm[exact.node_index]))
    assert exact.sigma_px_s == pytest.approx(max(2.0, rel), rel=0.05)
    # 20 px/s of noise: ring noise ~14-16 px/s (biased low, see ring_noise), x 1.5.
    assert 15.0 < noisy.sigma_px_s < 32.0


def test_node_budget_on_a_large_sensor_keeps_the_objects():
    """A 1280x720 window of 60 k exact flows: with a budget of 6,000 nodes the cell grows,
    the propagation limit grows alike, and both objects are still found."""
    from evseg.segmentation import SegmentationConfig, segment_normal_flow
    from evseg.segmentation.synthetic import synthetic_scene

    sc = synthetic_scene(n_flows=60_000, n_objects=2, sensor_size=(1280, 720), seed=5,
                         radius_px=(120.0, 160.0))
    cfg = SegmentationConfig(max_nodes=6_000)
    res = segment_normal_flow(sc.x, sc.y, sc.t, sc.nx, sc.ny, config=cfg, sensor_size=sc.sensor_size)
    assert len(res.node_labels) <= 6_000
    assert res.max_propagation_px > cfg.max_propagation_px
    assert res.n_objects == 2
    # each true object is mostly one detected object
    lab = res.node_labels
    truth = sc.label[res.node_index]
    for k in (1, 2):
        vals, counts = np.unique(lab[truth == k], return_counts=True)
        assert vals[np.argmax(counts)] >= 1 and counts.max() >= 0.9 * (truth == k).sum()


def test_support_weighting_finds_a_dense_object_whose_nodes_alone_cannot_pay_its_label():
    """Node support (events per cell): the same flows, but the object's cells fired 16x more
    events than the background's. Its nodes then weigh (16)^0.25 = 2 each, so a label cost
    above what its nodes save at weight 1 (tau^2 = 9 each) is paid at weight 2."""
    s = synthetic_scene(n_flows=2500, n_objects=1, seed=4)
    on = s.label == 1
    saving = 9.0 * on.sum()  # an upper bound on the object's saving at weight 1
    # Events of the window: every flow's position, and 15 more events at each object flow.
    ex = np.concatenate([s.x, np.repeat(s.x[on], 15)])
    ey = np.concatenate([s.y, np.repeat(s.y[on], 15)])
    kw = dict(sensor_size=s.sensor_size, event_xy=(ex, ey))
    flat = SegmentationConfig(lambda_m=1.3 * saving, support_exponent=0.0)
    assert segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=flat, **kw).n_objects == 0
    weighted = SegmentationConfig(lambda_m=1.3 * saving, support_exponent=0.25)
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=weighted, **kw)
    assert r.n_objects == 1
    lab, share = majority(s.label[r.node_index], r.node_labels, 1)
    assert lab == 1 and share > 0.9
    # Without the events, each flow counts once: uniform support, the object cannot pay.
    r = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=weighted, sensor_size=s.sensor_size)
    assert r.n_objects == 0


def test_prepared_window_segments_exactly_like_the_one_call():
    """prepare_window + segment_prepared (the pipeline prepares window t + 1 on its worker
    thread) give the same result as segment_normal_flow, with and without a previous window."""
    from evseg.segmentation import prepare_window, segment_prepared

    s = synthetic_scene(n_flows=2000, n_objects=2, seed=5)
    cfg = SegmentationConfig()
    first = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
    for previous in (None, first):
        one = segment_normal_flow(s.x, s.y, s.t + 10_000, s.nx, s.ny, config=cfg,
                                  sensor_size=s.sensor_size, previous=previous)
        prepared = prepare_window(s.x, s.y, s.t + 10_000, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
        two = segment_prepared(prepared, previous=previous)
        np.testing.assert_array_equal(one.node_labels, two.node_labels)
        np.testing.assert_array_equal(one.models, two.models)
        assert one.boxes == two.boxes and one.n_objects == two.n_objects >= 2
    assert two.n_predicted >= 2  # the previous window's objects were predicted


def test_precomputed_sampled_candidates_segment_exactly_like_computing_them(monkeypatch):
    """with_sampled_candidates (what the pipeline's worker process adds to a prepared window)
    holds round 0's candidates for both counts; segment_prepared takes the one it needs instead
    of sampling and fitting again, with the same result, with (6 sampled) and without (12)
    predicted objects."""
    import evseg.segmentation.solver as solver
    from evseg.segmentation import prepare_window, segment_prepared
    from evseg.segmentation.window import with_sampled_candidates

    s = synthetic_scene(n_flows=2000, n_objects=2, seed=5)
    cfg = SegmentationConfig()
    assert (cfg.n_sampled, cfg.n_sampled_with_prediction) == (12, 6)
    first = segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
    prepared = prepare_window(s.x, s.y, s.t + 10_000, s.nx, s.ny, config=cfg, sensor_size=s.sensor_size)
    ready = with_sampled_candidates(prepared)
    assert sorted(c.n_asked for c in ready.sampled) == [6, 12] and prepared.sampled == ()
    assert all(c.data.shape == (len(prepared.graph), len(c.models)) for c in ready.sampled)
    expected = {prev is None: segment_prepared(prepared, previous=prev) for prev in (None, first)}

    def no_sampling(*args, **kwargs):
        raise AssertionError("sampled again")

    monkeypatch.setattr(solver, "sample_candidates", no_sampling)
    for prev in (None, first):
        got = segment_prepared(ready, previous=prev)
        want = expected[prev is None]
        np.testing.assert_array_equal(got.node_labels, want.node_labels)
        np.testing.assert_array_equal(got.models, want.models)
        assert got.boxes == want.boxes and got.n_candidates == want.n_candidates


def test_a_still_camera_keeps_zero_motion_as_background():
    """Simulated static-camera scene (held-out seed, ground-truth normal flow): with the default
    settings the largest moving object is taken for the background and nothing is detected;
    with the static_camera preset every object is found (50 ms, 10 object-windows)."""
    from evseg.segmentation.evaluate import evaluate_scene

    moving = evaluate_scene("static_camera", 1000, 50_000, config=SegmentationConfig())
    still = evaluate_scene("static_camera", 1000, 50_000, config=load_segmentation_config("static_camera"))
    assert moving["objects"] == still["objects"] == 10
    assert moving["detection_rate"] == 0.0
    assert still["detection_rate"] == 1.0 and still["count_correct"] == 1.0


def test_still_labels_merge_into_an_empty_background_and_objects_sort_by_size():
    from evseg.segmentation.solver import STILL_MODEL, _still_background

    models = np.array([[1.0, 0.0, 200.0, 0.0],     # moving, 2 nodes
                       [1.0, 0.0, 3.0, -2.0],      # still (3.6 px/s), 1 node
                       [1.0, 0.0, 0.0, -150.0],    # moving, 3 nodes
                       [1.0, 0.001, 0.0, 0.0]])    # 0.001 rad/s x 200 px = 0.2 px/s: still, 0 nodes
    labels = np.array([0, 2, 1, 2, 0, 2])
    new, new_models, sizes = _still_background(labels, models, radius_px=200.0, still_px_s=10.0)
    assert new.tolist() == [2, 1, 0, 1, 2, 1]
    np.testing.assert_array_equal(new_models, [STILL_MODEL, models[2], models[0]])
    assert sizes.tolist() == [1, 3, 2]
    none_still, _, sizes = _still_background(np.array([0, 0, 2]), models[[0, 0, 2]], 200.0, 10.0)
    assert sizes[0] == 0 and set(none_still.tolist()) == {1, 2}  # an empty background label 0


def test_round0_refits_grow_a_translation_candidate_over_a_spinning_object():
    """A spinning object (2 rad/s about its centre, radius 12 px, exact normal flow) and a
    candidate that is its centre's translation: the candidate explains the nodes near the
    centre only (35 of 48); refitting it to them tilts it towards the rotation, and the nodes
    choose again: it explains 41 of them, and no background node. (Until 2026-12-05 the
    simulator's EED-like seed 1005 showed this end to end: its ball, whose rim events were
    then labelled background, was lost without the refits; with rim events labelled right the
    ball is found either way, so the mechanism is checked here on its own.)"""
    from evseg.segmentation.solver import _round0_refits
    from evseg.segmentation.window import lm_kwargs, prepare_window, window_costs

    w, h = 346, 260
    origin = np.array([(w - 1) / 2, (h - 1) / 2])
    bg = [1.0, 0.0, 120.0, -40.0]
    centre = synthetic_scene(n_flows=20000, n_objects=1, seed=2, radius_px=(12.0, 12.0), models=np.array([bg, bg]))
    c = np.array([centre.x[centre.label == 1].mean(), centre.y[centre.label == 1].mean()])
    omega, v_c = 2.0, np.array([-150.0, 150.0])
    t = v_c - np.array([[0.0, -omega], [omega, 0.0]]) @ (c - origin)  # u(c) = v_c
    spin = [np.hypot(1.0, omega), np.arctan2(omega, 1.0), t[0], t[1]]
    s = synthetic_scene(n_flows=20000, n_objects=1, seed=2, radius_px=(12.0, 12.0), models=np.array([bg, spin]))
    pw = prepare_window(s.x, s.y, s.t, s.nx, s.ny, config=SegmentationConfig(residual_scale_px_s=2.0),
                        sensor_size=s.sensor_size)
    costs = lambda m: window_costs(pw, m)  # noqa: E731
    start = np.array([bg, [1.0, 0.0, *v_c]])
    data = costs(start)
    labels = np.argmin(data, axis=1)
    obj = s.label[pw.graph.index] == 1
    ar = np.arange(len(labels))

    def explained(data, labels):
        return (data[ar, labels] < 0.99 * pw.config.truncation ** 2 * pw.conf) & (labels == 1)

    assert obj.sum() == 48 and (explained(data, labels) & obj).sum() == 35
    models, data_after, labels_after = _round0_refits(start, data, labels, pw, lm_kwargs(pw), costs)
    grown = explained(data_after, labels_after)
    assert (grown & obj).sum() == 41 and not (grown & ~obj).any()
    assert not np.array_equal(models[1], start[1]) and np.array_equal(models[0], start[0])


def test_round0_refit_that_does_not_grow_its_candidate_is_undone():
    """A candidate 1.5 px/s off its object's motion already explains every node of the object,
    so refitting it moves it but cannot grow it: the refit is undone and the model comes back
    bit for bit (refits exist to grow, not to sharpen a candidate on the nodes it has)."""
    from evseg.segmentation.solver import _round0_refits
    from evseg.segmentation.window import lm_kwargs, prepare_window, window_costs

    s = synthetic_scene(n_flows=4000, n_objects=1, seed=2, radius_px=(10.0, 10.0))
    pw = prepare_window(s.x, s.y, s.t, s.nx, s.ny, config=SegmentationConfig(residual_scale_px_s=2.0),
                        sensor_size=s.sensor_size)
    costs = lambda m: window_costs(pw, m)  # noqa: E731
    start = s.models.copy()
    start[1, 2] += 1.5  # px/s: within the residual scale's reach of every object node
    data = costs(start)
    labels = np.argmin(data, axis=1)
    n_object = int((labels == 1).sum())
    assert 6 <= n_object <= 48  # a small candidate: the refit is tried
    assert n_object == int((s.label[pw.graph.index] == 1).sum())  # all of the object already
    models, data_after, labels_after = _round0_refits(start, data, labels, pw, lm_kwargs(pw), costs)
    assert np.array_equal(models, start)
    assert np.array_equal(data_after, data) and np.array_equal(labels_after, labels)


def test_contrast_sensitive_potts_finds_a_small_object_on_precise_flow():
    """Simulated EVIMO-like scene (validation seed 900, ground-truth normal flow), first
    window: with one Potts weight for every edge one of the three objects' outline costs more
    than its flow saves and it joins the background; across its outline no candidate explains
    both sides, so contrast-sensitive weights make that boundary cheaper and all three are
    found (EED detection criterion on their boxes). On the learned flow the contrast is off:
    see the next test. (Until 2026-12-05 a small car of driving-like seed 916 showed this; the
    simulator's corrected rim labels give it enough exact flow to be found either way.)"""
    from dataclasses import replace

    from evseg.metrics import box_to_mask, detection_success
    from evseg.simulator import load_scene_preset, simulate

    rec = simulate(load_scene_preset("evimo_like"), seed=900, duration_us=100_000)  # as `evseg eval seg`
    ev, flow = rec.stream.events, rec.normal_flow.astype(np.float64)
    cfg = load_segmentation_config("evimo_like")
    assert cfg.contrast_min_weight < 1
    shape = rec.stream.sensor_size[::-1]
    truths = [box_to_mask(b, shape) for b in rec.window_truth(0, 10_000).boxes.values()]
    assert len(truths) == 3
    n = int(np.searchsorted(ev["t"], 10_000))

    def found(config):
        r = segment_normal_flow(ev["x"][:n].astype(np.float64), ev["y"][:n].astype(np.float64), ev["t"][:n],
                                flow[:n, 0], flow[:n, 1], config=config, sensor_size=rec.stream.sensor_size)
        return sum(any(detection_success(box_to_mask(b, shape), t) for b in r.boxes.values()) for t in truths)

    assert found(cfg) == 3
    assert found(replace(cfg, contrast_min_weight=1.0)) == 2


def test_contrast_sensitive_potts_is_off_on_noisy_flow():
    """Flow noise of 15 % of the speed (the shipped learned model measures >= 6.8 %): the
    relative ring noise is above contrast_max_noise, and the result is the plain-Potts one."""
    from dataclasses import replace

    from evseg.segmentation.window import prepare_window

    s = synthetic_scene(n_flows=3000, n_objects=2, seed=4)
    rng = np.random.default_rng(0)
    speed = np.hypot(s.nx, s.ny)
    nx = s.nx + rng.normal(0, 0.15, len(speed)) * speed
    ny = s.ny + rng.normal(0, 0.15, len(speed)) * speed
    cfg = SegmentationConfig()
    pw = prepare_window(s.x, s.y, s.t, nx, ny, config=cfg, sensor_size=s.sensor_size)
    assert pw.flow_noise_rel > cfg.contrast_max_noise
    on = segment_normal_flow(s.x, s.y, s.t, nx, ny, config=cfg, sensor_size=s.sensor_size)
    off = segment_normal_flow(s.x, s.y, s.t, nx, ny, config=replace(cfg, contrast_min_weight=1.0),
                              sensor_size=s.sensor_size)
    assert np.array_equal(on.node_labels, off.node_labels)
    assert on.energy == off.energy


def test_an_object_leaving_the_frame_keeps_a_valid_box():
    # A fast object (-3000 px/s) seen only in the first 0.8 ms at the left edge: moved to the
    # window's mid-time it lies wholly off the sensor. Its box is where its events were, never
    # inverted (x1 < x0), and its mask is not empty.
    from evseg.segmentation import load_segmentation_config, segment_normal_flow

    rng = np.random.default_rng(3)
    w, h, n = 346, 260, 8000
    x, y = rng.uniform(0, w - 1, n).round(), rng.uniform(0, h - 1, n).round()
    t = rng.integers(0, 10_000, n)
    v = np.tile([60.0, 0.0], (n, 1))
    obj = (x < 10) & (np.abs(y - 130) < 40)
    t[obj] = rng.integers(0, 800, obj.sum())
    v[obj] = [-3000.0, 0.0]
    a = rng.uniform(0, 2 * np.pi, n)
    g = np.stack([np.cos(a), np.sin(a)], 1)
    s = (g * v).sum(1)
    keep = np.abs(s) > 5
    o = np.argsort(t[keep], kind="stable")
    nf = (g * s[:, None])[keep][o]
    res = segment_normal_flow(x[keep][o], y[keep][o], t[keep][o].astype(np.int64), nf[:, 0], nf[:, 1],
                              config=load_segmentation_config("evimo_like"), sensor_size=(w, h))
    assert len(res.boxes) == 1
    (box,) = res.boxes.values()
    assert box[0] <= box[2] and box[1] <= box[3]
    assert box[0] == 0 and box[2] <= 12 and box[1] >= 85 and box[3] <= 175  # the strip x < 10, |y - 130| < 40
    (mask,) = res.masks.values()
    assert mask.any()


@pytest.mark.parametrize("change, message", [
    ({"t": "seconds"}, r"'t' = 0.0001 at row 1 is not whole microseconds \(time in seconds: multiply by 1e6\)"),
    ({"x": "nan"}, r"'x' = nan at row 2 is not a finite position"),
    ({"uncertainty": "negative"}, r"'uncertainty' = -0.1 at row 3 is negative"),
    ({"ny": "short"}, r"'ny' has shape \(4,\), expected \(5,\) like 'x'"),
])
def test_segment_normal_flow_names_a_bad_argument(change, message):
    from evseg.errors import EventDataError
    from evseg.segmentation import segment_normal_flow

    args = {"x": np.arange(5.0), "y": np.zeros(5), "t": np.arange(5) * 100, "nx": np.ones(5), "ny": np.zeros(5),
            "uncertainty": np.full(5, 0.1)}
    what = next(iter(change))
    if change[what] == "seconds":
        args["t"] = np.arange(5) * 1e-4
    elif change[what] == "nan":
        args["x"][2] = np.nan
    elif change[what] == "negative":
        args["uncertainty"][3] = -0.1
    else:
        args["ny"] = np.zeros(4)
    with pytest.raises(EventDataError, match=rf"segment_normal_flow: {message}"):
        segment_normal_flow(**args)


def test_prepare_window_checks_its_arrays_and_takes_a_preset_name():
    # prepare_window is public: it checks what segment_normal_flow checks, and its config may be
    # given as PipelineConfig takes it.
    import numpy as np
    import pytest

    from evseg.errors import ConfigError, EventDataError
    from evseg.segmentation import prepare_window

    x, y = np.array([1.0, 2.0, 3.0]), np.array([1.0, 1.0, 1.0])
    t, nx, ny = np.array([0, 1, 2]), np.ones(3), np.zeros(3)
    with pytest.raises(EventDataError, match="'t' = 0.5 at row 0 is not whole microseconds"):
        prepare_window(x, y, np.array([0.5, 1.0, 1.5]), nx, ny)
    with pytest.raises(EventDataError, match="'uncertainty' is NaN at row 1"):
        prepare_window(x, y, t, nx, ny, uncertainty=np.array([0.1, np.nan, 0.1]))
    with pytest.raises(ConfigError, match="must be a SegmentationConfig, a preset name or a mapping"):
        prepare_window(x, y, t, nx, ny, config=3)
    assert len(prepare_window(x, y, t, nx, ny, config="eed_like").graph) >= 0


def test_user_input_far_off_the_sensor_or_of_the_wrong_kind_is_named():
    """Far-off positions (a swapped sensor size, another frame) gave boxes clipped to the
    border and lost objects; complex flow lost its imaginary part; a bad previous result or
    tracked boxes failed deep in numpy."""
    from evseg.errors import ConfigError, EventDataError
    from evseg.segmentation import segment_normal_flow

    s = synthetic_scene(n_flows=600, n_objects=1, seed=1)
    w, h = s.sensor_size
    assert s.x.max() > 1.25 * h  # the swapped size (height, width) leaves these columns far off
    with pytest.raises(EventDataError, match=rf"'x' = .* at row \d+ lies far off the {h}x{w} sensor"):
        segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=(h, w))
    with pytest.raises(EventDataError, match=r"'nx' must hold real numbers, got dtype complex128"):
        segment_normal_flow(s.x, s.y, s.t, s.nx.astype(complex), s.ny, sensor_size=s.sensor_size)
    with pytest.raises(ConfigError, match=r"previous must be the previous window's SegmentationResult or None, got str"):
        segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size, previous="abc")
    with pytest.raises(ConfigError, match=r"tracked_objects boxes must be \(K, 4\), got shape \(2, 3\)"):
        segment_normal_flow(s.x, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size,
                            tracked_objects=(np.zeros((2, 3)), np.zeros((2, 4))))
    # Undistorted positions a little beyond the edges are fine.
    segment_normal_flow(s.x * 1.1 - 0.05 * w, s.y, s.t, s.nx, s.ny, sensor_size=s.sensor_size)

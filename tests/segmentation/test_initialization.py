"""Fast sampling, 1-ring translations and motion prediction."""

import numpy as np

from evseg.segmentation.initialization import (
    farthest_candidates, fast_sampling, local_translations, motion_prediction, predict_boxes, ring_agreement,
    ring_noise,
)
from evseg.segmentation.motion_model import normal_flow_of
from evseg.segmentation.preprocessing import delaunay_edges


def test_local_translations_recover_a_pure_translation_exactly():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 100, 300), rng.uniform(0, 100, 300)
    ang = rng.uniform(0, 2 * np.pi, 300)
    model = np.array([[1.0, 0.0, 120.0, -45.0]])
    nx, ny = normal_flow_of(model, np.zeros(300, dtype=int), x, y, np.cos(ang), np.sin(ang))
    keep = np.hypot(nx, ny) > 1.0
    x, y, nx, ny = x[keep], y[keep], nx[keep], ny[keep]
    tx, ty, ok = local_translations(nx, ny, delaunay_edges(x, y), scale_px_s=5.0)
    assert ok.mean() > 0.9
    # noise-free translation: every well-conditioned ring solves it exactly
    np.testing.assert_allclose(tx[ok], 120.0, atol=1e-6)
    np.testing.assert_allclose(ty[ok], -45.0, atol=1e-6)


def _ring_reference(nx, ny, edges, scale, iterations=3, min_conditioning=0.1):
    """The robust 1-ring translation written plainly (per node, per iteration)."""
    m = len(nx)
    norm = np.hypot(nx, ny)
    rings = [[i] for i in range(m)]
    for i, j in edges:
        rings[i].append(j)
        rings[j].append(i)
    tx, ty, ok = np.array(nx, float), np.array(ny, float), np.zeros(m, bool)
    for i in range(m):
        h = np.stack([nx[rings[i]], ny[rings[i]]], 1) / norm[rings[i], None]
        w = np.ones(len(h))
        for it in range(iterations + 1):
            if it:
                r = (h @ np.array([tx[i], ty[i]]) - norm[rings[i]]) / scale
                w = 1 / (1 + r * r)
            a = (h * w[:, None]).T @ h
            ev = np.linalg.eigvalsh(a)
            ok[i] = ev[0] >= min_conditioning * ev[1]
            if ok[i]:
                tx[i], ty[i] = np.linalg.solve(a, (h * (w * norm[rings[i]])[:, None]).sum(0))
            else:  # the node's own flow; its ring is reweighted around it next iteration
                tx[i], ty[i] = nx[i], ny[i]
    return tx, ty, ok


def test_local_translations_match_a_plain_per_node_solution_with_outliers():
    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 60, 120), rng.uniform(0, 60, 120)
    nx, ny = rng.normal(0, 80, 120), rng.normal(0, 80, 120)
    edges = delaunay_edges(x, y)
    tx, ty, ok = local_translations(nx, ny, edges, scale_px_s=20.0)
    rx, ry, rok = _ring_reference(nx, ny, edges, 20.0)
    np.testing.assert_array_equal(ok, rok)
    np.testing.assert_allclose(tx, rx, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(ty, ry, rtol=1e-9, atol=1e-9)


def test_ring_agreement_by_hand():
    # path 0 - 1 - 2 and a lone node 3; flows along x of 10, 10 and 30 px/s, node 3 along y
    nx, ny = np.array([10.0, 10.0, 30.0, 0.0]), np.array([0.0, 0.0, 0.0, 5.0])
    edges = np.array([[0, 1], [1, 2]])
    tx, ty = np.array([10.0, 10.0, 20.0, 0.0]), np.zeros(4)
    agree = ring_agreement(nx, ny, edges, tx, ty, 10.0)
    # node 0: neighbour 1 has r = (10 - 10) / 10 = 0 -> 1.0
    # node 1: neighbours 0 (r = 0 -> 1) and 2 (n_2 = 30 along x: r = (10 - 30) / 10 = -2 -> 1/5),
    #   mean (1 + 0.2) / 2 = 0.6
    # node 2: neighbour 1: r = (20 - 10) / 10 = 1 -> 0.5; node 3: no neighbour -> 0
    np.testing.assert_allclose(agree, [1.0, 0.6, 0.5, 0.0], rtol=0, atol=1e-15)


def test_parallel_ring_does_not_vote():
    x = np.array([0.0, 1.0, 0.0, 1.0])
    y = np.array([0.0, 0.0, 1.0, 1.0])
    tx, ty, ok = local_translations(np.full(4, 50.0), np.zeros(4), delaunay_edges(x, y))
    assert not ok.any()


def test_fast_sampling_frequent_and_far_candidates():
    rng = np.random.default_rng(1)
    bg = rng.normal([30.0, 10.0], 3.0, (900, 2))
    obj = rng.normal([-400.0, 150.0], 3.0, (12, 2))  # 1.3 % of the votes, far away
    scatter = rng.uniform(-100, 100, (60, 2))  # lone outliers
    v = np.concatenate([bg, obj, scatter])
    c = fast_sampling(v[:, 0], v[:, 1], n=6, bin_px_s=20.0, min_separation_px_s=40.0)
    assert c.shape[1] == 4 and len(c) <= 6
    np.testing.assert_allclose(c[:, :2], np.tile([1.0, 0.0], (len(c), 1)))
    assert np.hypot(*(c[0, 2:] - [30.0, 10.0])) < 15.0  # most frequent first
    assert np.min(np.hypot(c[:, 2] + 400.0, c[:, 3] - 150.0)) < 15.0  # the small far object
    d = np.hypot(*(c[:, None, 2:] - c[None, :, 2:]).transpose(2, 0, 1))
    assert np.all(d[~np.eye(len(c), dtype=bool)] >= 40.0)  # clearly different
    # deterministic
    np.testing.assert_array_equal(c, fast_sampling(v[:, 0], v[:, 1], 6, 20.0, 40.0))


def _fast_sampling_reference(vx, vy, n, bin_px_s, min_separation_px_s, min_votes=3):
    """Fast sampling's documented rule written plainly in numpy (bins by np.unique)."""
    ix = np.floor(vx / bin_px_s).astype(np.int64)
    iy = np.floor(vy / bin_px_s).astype(np.int64)
    ix, iy = ix - ix.min(), iy - iy.min()
    _, key, count = np.unique(ix * (iy.max() + 1) + iy, return_inverse=True, return_counts=True)
    means = np.column_stack([np.bincount(key, weights=vx), np.bincount(key, weights=vy)]) / count[:, None]
    d2 = min_separation_px_s**2
    order = np.argsort(-count, kind="stable")
    taken = [means[order[0]]]
    dist2 = ((means - taken[0]) ** 2).sum(axis=1)
    for o in order[1:]:
        if len(taken) >= (n + 1) // 2 or count[o] < 2:
            break
        if dist2[o] >= d2:
            taken.append(means[o])
            dist2 = np.minimum(dist2, ((means - means[o]) ** 2).sum(axis=1))
    while len(taken) < n:
        score = np.where(count >= min_votes, dist2, -1.0)
        o = int(np.argmax(score))
        if score[o] < d2:
            break
        taken.append(means[o])
        dist2 = np.minimum(dist2, ((means - means[o]) ** 2).sum(axis=1))
    return np.array(taken).reshape(-1, 2)


def test_fast_sampling_equals_the_plain_rule_exactly():
    """The compiled bins keep numpy's order of operations: same candidates, bit for bit
    (so segmentations do not change with the implementation)."""
    rng = np.random.default_rng(11)
    for trial in range(200):
        m = int(rng.integers(1, 2000))
        centres = rng.normal(0.0, 200.0, (int(rng.integers(1, 6)), 2))
        v = centres[rng.integers(0, len(centres), m)] + rng.normal(0.0, rng.uniform(1, 30), (m, 2))
        if trial % 3 == 0:
            v = np.round(v / 10.0) * 10.0  # many ties in the counts
        n, b, sep = int(rng.integers(1, 25)), float(rng.uniform(1, 40)), float(rng.uniform(0, 100))
        got = fast_sampling(v[:, 0], v[:, 1], n, b, sep)
        np.testing.assert_array_equal(got[:, 2:], _fast_sampling_reference(v[:, 0], v[:, 1], n, b, sep))


def test_farthest_candidates_find_a_translation_among_normal_flows():
    """The normal flows of a translating disc, n = (T . n_hat) n_hat, lie on a circle through
    0 and T, far from the background's: farthest-point sampling away from the background's
    candidate returns a translation among them (nearer T than the background; the first
    round's refit then moves it onto the disc's model); a lone flow never counts."""
    rng = np.random.default_rng(2)
    angles = np.linspace(0.0, 2.0 * np.pi, 120, endpoint=False)
    normals = np.column_stack([np.cos(angles), np.sin(angles)])
    t = np.array([250.0, -20.0])
    disc = normals * (normals @ t)[:, None]  # n = (T . n_hat) n_hat
    disc = disc[normals @ t > 0]
    bg = rng.normal([90.0, 35.0], 5.0, (500, 2))
    v = np.concatenate([bg, disc, [[-300.0, 300.0]]])
    # bins of 4 sigma and a separation of 8 sigma for sigma = 15 px/s
    c = farthest_candidates(v[:, 0], v[:, 1], np.array([[90.0, 35.0]]), 2, 60.0, 120.0)
    assert 1 <= len(c) <= 2
    np.testing.assert_allclose(c[:, :2], np.tile([1.0, 0.0], (len(c), 1)))
    first = c[0, 2:]
    assert np.hypot(*(first - t)) < 0.5 * np.hypot(*(first - [90.0, 35.0]))
    on_circle = abs(np.hypot(*(first - t / 2.0)) - np.hypot(*t) / 2.0)  # circle with diameter 0-T
    assert on_circle < 30.0  # within half a bin of the disc's normal flows
    assert np.all(np.hypot(c[:, 2] + 300.0, c[:, 3] - 300.0) > 100.0)  # the lone flow
    assert len(farthest_candidates(v[:, 0], v[:, 1], np.array([[90.0, 35.0]]), 0, 60.0, 120.0)) == 0


def test_predict_boxes_moves_by_model_flow():
    boxes = np.array([[10.0, 20.0, 30.0, 40.0]])
    models = np.array([[1.0, 0.0, 100.0, -50.0]])  # pure translation
    got = predict_boxes(boxes, models, (0.0, 0.0), dt_s=0.01, margin_px=2.0)
    np.testing.assert_allclose(got, [[10 + 1 - 2, 20 - 0.5 - 2, 30 + 1 + 2, 40 - 0.5 + 2]])


def test_motion_prediction_fits_the_object_in_its_moved_box():
    rng = np.random.default_rng(2)
    true = np.array([[1.1, 0.1, 200.0, 80.0]])
    # object nodes around (60, 50) at time t; the previous box was 2 px up-left of it
    x, y = rng.uniform(50, 70, 150), rng.uniform(40, 60, 150)
    ang = rng.uniform(0, 2 * np.pi, 150)
    nx, ny = normal_flow_of(true, np.zeros(150, dtype=int), x, y, np.cos(ang), np.sin(ang))
    prev_box = np.array([[48.0, 38.0, 68.0, 58.0]])
    prev_model = np.array([[1.0, 0.0, 180.0, 60.0]])
    cand = motion_prediction(x, y, nx, ny, prev_box, prev_model, (0.0, 0.0), dt_s=0.01,
                             margin_px=4.0, min_nodes=8, loss="none", iterations=20)
    np.testing.assert_allclose(cand, true, rtol=1e-5, atol=1e-3)
    none = motion_prediction(x, y, nx, ny, np.array([[200.0, 200.0, 210.0, 210.0]]), prev_model,
                             (0.0, 0.0), 0.01, 0.0, 8)
    assert none.shape == (0, 4)


def test_consensus_models_recover_object_among_as_many_stray_flows():
    from evseg.segmentation.initialization import consensus_models
    from evseg.segmentation.motion_model import normal_flow_of

    rng = np.random.default_rng(5)
    true = np.array([[1.02, -0.2, 680.0, -4.0], [0.97, 0.05, -120.0, 60.0]])
    n = 40
    region = np.repeat([0, 1], n)
    x = rng.uniform(-20, 20, 2 * n) + np.where(region == 0, -60.0, 60.0)
    y = rng.uniform(-20, 20, 2 * n)
    ang = rng.uniform(0, 2 * np.pi, 2 * n)
    nx, ny = normal_flow_of(true, region, x, y, np.cos(ang), np.sin(ang))
    # Half of each region's flows replaced by random vectors: a least-squares start fails here.
    bad = np.concatenate([rng.choice(n, n // 2, replace=False), n + rng.choice(n, n // 2, replace=False)])
    nx, ny = nx.copy(), ny.copy()
    nx[bad], ny[bad] = rng.uniform(-700, 700, len(bad)), rng.uniform(-700, 700, len(bad))
    got = consensus_models(x, y, nx, ny, region, 2, inlier_px_s=1.0)
    # A sample of 4 inliers solves the noise-free system exactly (float round-off only).
    np.testing.assert_allclose(got, true, rtol=1e-6, atol=1e-6)
    # Deterministic: same seed, same models.
    np.testing.assert_array_equal(got, consensus_models(x, y, nx, ny, region, 2, inlier_px_s=1.0))


def test_consensus_models_tiny_region_gets_identity():
    from evseg.segmentation.initialization import consensus_models

    got = consensus_models(np.zeros(3), np.arange(3.0), np.ones(3), np.zeros(3), np.zeros(3, int), 1, 1.0)
    np.testing.assert_array_equal(got, [[1.0, 0.0, 0.0, 0.0]])


def _translating_flow(n=2000, seed=0):
    rng = np.random.default_rng(seed)
    x, y = rng.uniform(0, 300, n), rng.uniform(0, 200, n)
    a = rng.uniform(0, 2 * np.pi, n)
    hx, hy = np.cos(a), np.sin(a)
    mag = hx * 80.0 - hy * 30.0  # normal flow of the translation (80, -30) px/s
    keep = np.abs(mag) > 5.0
    return x[keep], y[keep], hx[keep], hy[keep], mag[keep], rng


def test_ring_noise_is_zero_for_exact_flow_and_tracks_added_noise():
    x, y, hx, hy, mag, rng = _translating_flow()
    edges = delaunay_edges(x, y)
    assert ring_noise(hx * mag, hy * mag, edges, 10.0) < 1e-9
    # Gaussian noise of 3 px/s along the normal: the estimate is biased low because each
    # node belongs to its own ring (documented ~20-30 %); 0.5-1.1x brackets it.
    noisy = mag + rng.normal(0.0, 3.0, len(mag))
    est = ring_noise(hx * noisy, hy * noisy, edges, 10.0)
    assert 1.5 < est < 3.3
    assert ring_noise(np.empty(0), np.empty(0), np.empty((0, 2), dtype=np.int64), 1.0) == 0.0

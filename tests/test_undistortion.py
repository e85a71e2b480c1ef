"""Normal flow mapped to undistorted pixels (evseg.undistortion)."""

import numpy as np

from evseg.calibration import Calibration
from evseg.undistortion import UndistortionTable, undistort_normal_flow


def _calibration(distortion, size=(346, 260)):
    K = np.array([[200.0, 0, size[0] / 2], [0, 200.0, size[1] / 2], [0, 0, 1]])
    return Calibration(K, np.asarray(distortion, dtype=float), size)


def test_undistorted_normal_flow_follows_the_jacobian():
    table = UndistortionTable.from_calibration(_calibration([-0.3, 0.1, 0.0, 0.0]))
    rng = np.random.default_rng(0)
    x, y = rng.integers(20, 320, 50), rng.integers(20, 240, 50)
    u = rng.normal(0, 300, (50, 2))  # optical flow, px/s
    ang = rng.uniform(0, 2 * np.pi, 50)
    g = np.stack([np.cos(ang), np.sin(ang)], -1)  # unit gradient direction
    n = np.sum(u * g, -1)[:, None] * g  # normal flow seen by the camera
    xu, yu, nxu, nyu = undistort_normal_flow(table, x, y, n[:, 0], n[:, 1])
    # Direct construction: u' = J u, g' = J^-T g / |J^-T g|, n' = (u' . g') g'.
    J = np.stack([np.stack([table.j11[y, x], table.j12[y, x]], -1),
                  np.stack([table.j21[y, x], table.j22[y, x]], -1)], -2)
    u2 = np.einsum("kij,kj->ki", J, u)
    h = np.einsum("kji,kj->ki", np.linalg.inv(J), g)
    g2 = h / np.linalg.norm(h, axis=-1, keepdims=True)
    n2 = np.sum(u2 * g2, -1)[:, None] * g2
    # float32 output of flows up to ~1000 px/s: 1e-3 px/s is far below any flow error.
    np.testing.assert_allclose(np.stack([nxu, nyu], -1), n2, atol=1e-3)
    np.testing.assert_array_equal(xu, table.xu[y, x])
    np.testing.assert_array_equal(yu, table.yu[y, x])


def test_zero_distortion_leaves_positions_and_flow_unchanged():
    table = UndistortionTable.from_calibration(_calibration([0.0, 0.0, 0.0, 0.0]))
    x, y = np.array([5, 100, 300]), np.array([7, 130, 250])
    nx, ny = np.array([100.0, -50.0, 0.0]), np.array([0.0, 20.0, 300.0])
    xu, yu, nxu, nyu = undistort_normal_flow(table, x, y, nx, ny)
    # OpenCV's iterative undistortion with P = K is the identity up to ~1e-4 px here.
    np.testing.assert_allclose(xu, x, atol=1e-3)
    np.testing.assert_allclose(yu, y, atol=1e-3)
    np.testing.assert_allclose(nxu, nx, atol=1e-2)
    np.testing.assert_allclose(nyu, ny, atol=1e-2)


def test_a_calibrated_pipeline_reports_boxes_and_masks_in_raw_pixels():
    # Segmentation runs in undistorted pixels; the reported masks are its masks looked up
    # through the undistortion table, the boxes their extent on the raw grid. (The simulated
    # flow is a pinhole camera's, so with a distortion it segments into many pieces: this
    # checks the mapping, not the segmentation.)
    from evseg.pipeline import MotionSegmentationPipeline, PipelineConfig
    from evseg.simulator import load_scene_preset, simulate
    from evseg.undistortion import mask_to_raw, raw_box

    rec = simulate(load_scene_preset("evimo_like"), seed=1001, duration_us=40_000)
    ok = np.flatnonzero(np.isfinite(rec.normal_flow[:, 0]))
    flow = {"index": ok, "nx": rec.normal_flow[ok, 0], "ny": rec.normal_flow[ok, 1]}
    cal = _calibration([-0.3, 0.1, 0.0, 0.0])
    pipe = MotionSegmentationPipeline(PipelineConfig(flow="precomputed"), sensor_size=(346, 260), calibration=cal)
    table = UndistortionTable.from_calibration(cal)
    checked = 0
    for res in pipe.run(rec.stream, precomputed_flow=flow):
        raw_of_seg = [mask_to_raw(table, m) for m in res.segmentation.masks.values()]
        for oid, box in res.boxes.items():
            x0, y0, x1, y1 = box
            assert 0 <= x0 <= x1 <= 345 and 0 <= y0 <= y1 <= 259
            mask = res.masks[oid]
            assert any((mask == m).all() for m in raw_of_seg)  # one of the segmentation's masks, mapped
            if mask.any():
                assert box == raw_box(mask)
                checked += 1
    assert checked >= 10

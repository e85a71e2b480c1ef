"""Masks, boxes and window truth of a simulated recording."""

import dataclasses

import numpy as np

from evseg.simulator import MotionConfig, ObjectConfig, TextureConfig, load_scene_preset, simulate
from evseg.simulator.ground_truth import mask_box


def one_object_scene(**motion):
    base = load_scene_preset("eed_like").with_sensor_size(100, 80)
    obj = ObjectConfig(count=(1, 1), shape=("disc",), size_px=(20.0, 20.0), aspect=(1.0, 1.0),
                       texture=TextureConfig(family=("uniform",), mean=(0.9, 0.9)),
                       motion=MotionConfig(**motion), in_view=0.0)  # centre of the frame at a random time
    return dataclasses.replace(base, objects=(obj,))


def test_disc_mask_has_the_disc_area_and_box_despite_the_net():
    # A still disc of diameter 20 px behind the EED net: the mask is the full silhouette (the net
    # cuts no holes), area pi r^2 within the anti-aliased rim (~1 px ring), box 20 px wide.
    rec = simulate(one_object_scene(speed_px_s=(0.0, 0.0), wobble=(0.0, 0.0)), seed=1, duration_us=2_000)
    (mask,) = rec.object_masks(1_000)
    assert abs(mask.sum() - np.pi * 10**2) < 2 * np.pi * 10 * 0.5  # half a pixel of rim
    x0, y0, x1, y1 = rec.object_boxes(1_000)[1]
    assert 19 <= x1 - x0 + 1 <= 21 and 19 <= y1 - y0 + 1 <= 21
    # centred on the frame centre (in_view = 0)
    assert abs((x0 + x1) / 2 - 49.5) <= 0.5 and abs((y0 + y1) / 2 - 39.5) <= 0.5


def test_objects_leaving_the_frame_have_empty_masks_and_no_box():
    # 3000 px/s rightwards: the disc crosses the 100 px frame in ~40 ms and travels 300 px in
    # the recording, so it is outside the frame at one end at least
    rec = simulate(one_object_scene(speed_px_s=(3000.0, 3000.0), direction_deg=(0.0, 0.0), wobble=(0.0, 0.0)),
                   seed=2, duration_us=100_000)
    ly = rec.scene.layers[1]
    t_in = t_out = None
    for t in range(0, 100_000, 2_000):
        cx = ly.trajectory.center(t * 1e-6)[0]
        masks = rec.object_masks(t)
        if cx < -20 or cx > 120:
            assert not masks.any() and 1 not in rec.object_boxes(t)
            t_out = t
        elif 20 < cx < 80:
            assert masks[0].sum() > 250 and 1 in rec.object_boxes(t)
            t_in = t
    assert t_in is not None and t_out is not None


def test_window_truth_uses_the_mid_time():
    rec = simulate(one_object_scene(speed_px_s=(200.0, 200.0), wobble=(0.0, 0.0)), seed=3, duration_us=20_000)
    wt = rec.window_truth(4_000, 14_000)
    assert wt.t_us == 9_000
    np.testing.assert_array_equal(wt.masks, rec.object_masks(9_000))
    assert wt.boxes == rec.object_boxes(9_000) and wt.object_ids == rec.object_ids


def test_mask_box_is_inclusive():
    m = np.zeros((5, 6), bool)
    m[1:3, 2:5] = True
    assert mask_box(m) == (2, 1, 4, 2)
    assert mask_box(np.zeros((3, 3), bool)) is None


def test_front_object_occludes_the_one_behind():
    base = load_scene_preset("evimo_like").with_sensor_size(80, 60)
    still = MotionConfig(speed_px_s=(0.0, 0.0), wobble=(0.0, 0.0))
    obj = ObjectConfig(count=(2, 2), shape=("disc",), size_px=(30.0, 30.0), aspect=(1.0, 1.0),
                       motion=still, in_view=0.0)  # both centred on the frame: the front one hides the back one
    rec = simulate(dataclasses.replace(base, objects=(obj,)), seed=0, duration_us=1_000)
    masks = rec.object_masks(500)
    assert rec.object_ids == [1, 2]
    assert not masks[0].any() and masks[1].sum() > 650  # id 2 is in front (pi 15^2 = 707)
    assert not np.any(rec.label == 1)

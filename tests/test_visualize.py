"""Images of events, labels and flow (evseg.visualize): exact colours where defined."""

import numpy as np

from evseg import visualize as vis


def test_flow_colours_follow_direction_and_magnitude():
    rgb = vis.flow_to_rgb(np.array([10.0, -10.0, 0.0, 0.0, 5.0, np.nan]), np.array([0.0, 0.0, 0.0, 10.0, 0.0, 1.0]), 10.0)
    np.testing.assert_array_equal(rgb[0], [255, 0, 0])  # +x (right): red, full value
    np.testing.assert_array_equal(rgb[1], [0, 255, 255])  # -x: cyan
    np.testing.assert_array_equal(rgb[2], [0, 0, 0])  # still: black
    assert rgb[3, 1] == 255 and rgb[3, 2] == 0 and 120 <= rgb[3, 0] <= 135  # +y (down), 90 deg: chartreuse
    np.testing.assert_array_equal(rgb[4], [128, 0, 0])  # half the maximum: half value
    np.testing.assert_array_equal(rgb[5], [0, 0, 0])  # NaN: black
    assert vis.flow_to_rgb(np.zeros((3, 4)), np.zeros((3, 4)), 1.0).shape == (3, 4, 3)


def test_color_wheel_legend_matches_flow_to_rgb():
    wheel = vis.color_wheel_legend(65)
    np.testing.assert_array_equal(wheel[32, 64], [255, 0, 0])  # right rim: +x at full value
    np.testing.assert_array_equal(wheel[0, 0], [255, 255, 255])  # outside the disc
    np.testing.assert_array_equal(wheel[32, 32], [0, 0, 0])  # centre: still


def test_events_and_labels_images():
    x, y = np.array([0, 1, 1, 2]), np.array([0, 0, 0, 1])
    img = vis.events_to_image(x, y, np.array([1, -1, -1, 1]), (3, 2))
    assert img.shape == (2, 3, 3) and img.dtype == np.uint8
    np.testing.assert_array_equal(img[0, 0], vis.ON_RGB)
    np.testing.assert_array_equal(img[0, 1], vis.OFF_RGB)
    np.testing.assert_array_equal(img[1, 0], [255, 255, 255])
    lab = vis.labels_to_image(x, y, np.array([0, -1, 2, 1]), (3, 2))
    np.testing.assert_array_equal(lab[0, 0], vis.BACKGROUND_RGB)
    np.testing.assert_array_equal(lab[0, 1], vis.label_palette(2)[1])  # last event of the pixel wins
    np.testing.assert_array_equal(lab[1, 2], vis.label_palette(2)[0])


def test_palette_colours_are_distinct():
    pal = vis.label_palette(8)
    assert len({tuple(c) for c in pal}) == 8


def test_save_rgb_writes_rgb_order(tmp_path):
    import cv2

    img = np.zeros((4, 5, 3), np.uint8)
    img[..., 0] = 255  # red
    vis.save_rgb(tmp_path / "r.png", img)
    back = cv2.imread(str(tmp_path / "r.png"))  # BGR
    np.testing.assert_array_equal(back[0, 0], [0, 0, 255])


def test_palette_matches_the_overlay_colour_of_each_object():
    # An object must keep one colour across the simulator preview (RGB) and the
    # segmentation overlay (BGR): label_palette row k-1 is object_color(k) reversed.
    from evseg.overlay import object_color

    pal = vis.label_palette(40)
    for k in range(1, 41):
        assert tuple(int(c) for c in pal[k - 1]) == object_color(k)[::-1]


def test_events_off_the_sensor_are_refused_not_drawn_on_another_row():
    # y * width + x put x = 12 of a 10x10 sensor at row 1, column 2.
    import pytest

    from evseg.errors import ConfigError, EventDataError

    x, y = np.array([12, 1]), np.array([0, 1])
    with pytest.raises(EventDataError, match=r"events_to_image: x = 12 at event 0 is outside the 10x10 sensor"):
        vis.events_to_image(x, y, np.array([1, 1]), (10, 10))
    with pytest.raises(EventDataError, match=r"labels_to_image: x = 12 at event 0"):
        vis.labels_to_image(x, y, np.array([1, 0]), (10, 10))
    with pytest.raises(EventDataError, match=r"flow_events_to_image: x = 12"):
        vis.flow_events_to_image(x, y, np.ones((2, 2)), (10, 10), 5.0)
    with pytest.raises(EventDataError, match=r"labels must be integers >= -1"):
        vis.labels_to_image(np.array([1]), np.array([1]), np.array([-2]), (10, 10))
    with pytest.raises(ConfigError, match=r"max_px_s .* got nan"):
        vis.flow_to_rgb(np.ones(2), np.ones(2), float("nan"))


def test_video_frames_of_another_size_or_kind_are_refused_not_dropped(tmp_path):
    # OpenCV's writer skips such frames with only a warning on stderr.
    import pytest

    from evseg.errors import EvsegError
    from evseg.overlay import VideoSink

    with VideoSink(tmp_path / "v.mp4") as sink:
        sink.add(np.zeros((48, 64, 3), np.uint8))
        with pytest.raises(EvsegError, match=r"frame 1 is 32x48, the first was 64x48"):
            sink.add(np.zeros((48, 32, 3), np.uint8))
        with pytest.raises(EvsegError, match=r"frame 1 must be uint8 \(height, width, 3\) BGR, got uint8 \(48, 64\)"):
            sink.add(np.zeros((48, 64), np.uint8))
        sink.add(np.zeros((48, 64, 3), np.uint8))
    import cv2

    assert int(cv2.VideoCapture(str(tmp_path / "v.mp4")).get(cv2.CAP_PROP_FRAME_COUNT)) == 2


def test_label_overlay_names_bad_arguments():
    import pytest

    from evseg.errors import EvsegError
    from evseg.events import make_events
    from evseg.overlay import label_overlay

    ev = make_events([1, 300], [2, 5], [0, 1], [1, 1])
    with pytest.raises(EvsegError, match=r"labels has shape \(1,\), expected one per event \(2,\)"):
        label_overlay(ev, np.array([1]), {}, (346, 260))
    with pytest.raises(EvsegError, match=r"event 1 at \(300, 5\) is outside the 260x346 sensor"):
        label_overlay(ev, np.array([1, 1]), {}, (260, 346))
    with pytest.raises(EvsegError, match="scale must be a whole number >= 1, got 0"):
        label_overlay(ev, np.array([1, 1]), {}, (346, 260), scale=0)
    img = label_overlay(ev, np.array([1, 1]), {1: (0.4, 1.6, 300.2, 5.0)}, (346, 260), scale=1)  # float box
    assert img.shape == (260, 346, 3)

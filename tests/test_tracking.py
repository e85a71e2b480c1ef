from evseg.tracking import ObjectTracker, box_iou, shift_box


def test_box_iou_and_shift():
    assert box_iou((0, 0, 9, 9), (0, 0, 9, 9)) == 1.0
    assert box_iou((0, 0, 4, 4), (5, 5, 9, 9)) == 0.0
    assert shift_box((0, 0, 9, 9), 3.4, -2.6, sensor_size=(20, 20)) == (3, 0, 12, 6)  # y1 = 9 - 2.6 = 6.4 -> 6; y0 = -3 clipped to 0


def test_ids_persist_through_motion_and_swap_of_labels():
    tr = ObjectTracker()
    first = tr.update({1: (0, 0, 9, 9), 2: (50, 50, 59, 59)})
    assert first == {1: 1, 2: 2}
    tr.predict({1: (5, 0), 2: (0, 5)})
    # Next window the segmentation numbers the objects the other way round.
    second = tr.update({1: (50, 55, 59, 64), 2: (5, 0, 14, 9)})
    assert second == {1: 2, 2: 1}


def test_new_object_gets_new_id_and_lost_track_expires():
    tr = ObjectTracker(max_missed=1)
    tr.update({1: (0, 0, 9, 9)})
    assert tr.update({1: (80, 80, 89, 89)}) == {1: 2}
    tr.update({})
    assert 1 not in tr.tracks and 2 in tr.tracks


def test_hits_count_the_windows_a_track_was_found_in():
    """A track missed for a window keeps its count; a dropped track's count goes with it."""
    tr = ObjectTracker(max_missed=1)
    tr.update({1: (0, 0, 9, 9)})
    assert tr.hits == {1: 1}
    tr.update({})  # missed once: kept
    tr.update({3: (0, 0, 9, 9)})
    assert tr.hits == {1: 2}
    tr.update({1: (80, 80, 89, 89)})  # a new object; track 1 missed
    assert tr.hits == {1: 2, 2: 1}
    tr.update({1: (80, 80, 89, 89)})  # track 1 missed twice: dropped
    assert tr.hits == {2: 2}


def test_a_piece_split_off_for_one_window_does_not_take_the_objects_id():
    # A ball tracked for 3 windows comes out as two overlapping pieces in window 4 (the second
    # piece starts track 2), then as one object again whose box matches track 2 a little
    # better: it is still object 1.
    tr = ObjectTracker()
    for k in range(3):
        assert tr.update({1: (10 + k, 10, 40 + k, 40)}) == {1: 1}
    assert tr.update({1: (13, 10, 43, 40), 2: (15, 12, 41, 42)}) == {1: 1, 2: 2}
    assert tr.update({1: (15, 12, 42, 42)}) == {1: 1}
    # Two tentative tracks still compete by IoU alone.
    tr = ObjectTracker()
    tr.update({1: (0, 0, 9, 9), 2: (2, 0, 11, 9)})
    assert tr.update({1: (2, 0, 11, 9)}) == {1: 2}

"""Mask blobs → boxes: the stated rules on hand-made masks, and agreement with the simulator."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fields.mask_boxes import BoxRules, boxes_from_instances, boxes_from_probabilities


def _mask(h, w, k=4):
    p = np.zeros((h, w, k), np.float32)
    p[..., 0] = 1.0
    return p


def _paint(p, r0, r1, c0, c1, cls, value=1.0):
    p[r0:r1, c0:c1, :] = 0.0
    p[r0:r1, c0:c1, 0] = 1.0 - value
    p[r0:r1, c0:c1, cls + 1] = value


def test_empty_mask_gives_no_boxes():
    assert boxes_from_probabilities(_mask(32, 48)) == []
    assert boxes_from_instances(np.zeros((8, 8), np.uint16), {}) == []


def test_single_blob_box_is_its_extent_and_class():
    p = _mask(40, 40)
    _paint(p, 10, 20, 5, 9, cls=2)
    (b,) = boxes_from_probabilities(p)
    assert (b.class_id, b.x0, b.y0, b.x1, b.y1, b.area_px) == (2, 5, 10, 9, 20, 40)
    assert b.yolo(40, 40).startswith("2 0.175000 0.375000 0.100000 0.250000")


def test_soft_edges_follow_the_half_coverage_rule():
    p = _mask(20, 20)
    _paint(p, 5, 10, 5, 10, cls=0, value=0.9)
    _paint(p, 5, 10, 10, 11, cls=0, value=0.49)  # below half: not part of the box
    _paint(p, 10, 11, 5, 10, cls=0, value=0.51)  # above half: part of the box
    (b,) = boxes_from_probabilities(p)
    assert (b.x0, b.y0, b.x1, b.y1) == (5, 5, 10, 11)


def test_tiny_blobs_below_min_area_are_dropped():
    p = _mask(20, 20)
    _paint(p, 2, 3, 2, 5, cls=0)  # 3 px
    _paint(p, 10, 12, 10, 12, cls=0)  # 4 px
    boxes = boxes_from_probabilities(p, BoxRules(min_area_px=4))
    assert [(b.x0, b.y0) for b in boxes] == [(10, 10)]


def test_faint_blobs_below_min_score_are_dropped():
    p = _mask(20, 20)
    _paint(p, 2, 6, 2, 6, cls=0, value=0.55)  # a faint halo blob: mean foreground 0.55
    _paint(p, 10, 14, 10, 14, cls=0, value=0.9)
    assert len(boxes_from_probabilities(p)) == 2  # off by default
    boxes = boxes_from_probabilities(p, BoxRules(min_score=0.6))
    assert [(b.x0, b.y0, round(b.score, 2)) for b in boxes] == [(10, 10, 0.9)]


def test_relative_threshold_puts_each_blob_edge_at_a_share_of_its_peak():
    p = _mask(30, 40)
    _paint(p, 4, 12, 4, 12, cls=0, value=0.35)  # halo ring around a faint person
    _paint(p, 5, 11, 5, 11, cls=0, value=0.6)  # faint person: peak 0.6
    _paint(p, 4, 12, 24, 32, cls=0, value=0.35)  # the same halo around a sharp person
    _paint(p, 5, 11, 25, 31, cls=0, value=0.95)  # sharp person: peak 0.95

    def extents(rules):
        return sorted((b.x0, b.y0, b.x1, b.y1) for b in boxes_from_probabilities(p, rules))

    # absolute threshold 0.3: both blobs take the halo
    assert extents(BoxRules(threshold=0.3)) == [(4, 4, 12, 12), (24, 4, 32, 12)]
    # half of each peak: the faint person keeps the 0.35 ring (>= 0.30), the sharp one drops it (< 0.475)
    assert extents(BoxRules(threshold=0.3, relative_threshold=0.5)) == [(4, 4, 12, 12), (25, 5, 31, 11)]


def test_relative_threshold_separates_people_joined_by_a_faint_bridge():
    p = _mask(20, 30)
    _paint(p, 5, 12, 4, 10, cls=0, value=0.95)
    _paint(p, 5, 12, 13, 19, cls=0, value=0.9)
    _paint(p, 5, 12, 10, 13, cls=0, value=0.7)  # a faint band between them: too shallow a dip (0.2) to split
    assert len(boxes_from_probabilities(p)) == 1
    boxes = sorted(boxes_from_probabilities(p, BoxRules(relative_threshold=0.8)), key=lambda b: b.x0)
    assert [(b.x0, b.x1) for b in boxes] == [(4, 10), (13, 19)]


def test_blob_cut_by_border_dropped_only_beyond_the_threshold():
    p = _mask(30, 30)
    _paint(p, 10, 13, 0, 3, cls=0)  # mostly outside the frame: 3 px of an expected 12
    _paint(p, 20, 27, 0, 4, cls=0)  # 7 px of 12 visible: kept
    kept = boxes_from_probabilities(p, BoxRules(expected_size_px=12.0, max_border_cut=0.5))
    assert [(b.y0, b.y1) for b in kept] == [(20, 27)]
    assert len(boxes_from_probabilities(p)) == 2  # without an expected size, border blobs stay


def test_two_touching_people_of_different_classes_are_split():
    p = _mask(30, 30)
    _paint(p, 5, 20, 5, 9, cls=0)  # standing
    _paint(p, 12, 20, 9, 16, cls=1)  # kneeling, touching
    boxes = sorted(boxes_from_probabilities(p), key=lambda b: b.x0)
    assert [(b.class_id, b.x0, b.x1) for b in boxes] == [(0, 5, 9), (1, 9, 16)]


def test_two_touching_people_of_one_class_are_split_at_the_dip():
    p = _mask(20, 30)
    yy, xx = np.mgrid[0:20, 0:30]
    blob = np.maximum(np.exp(-((xx - 8) ** 2 + (yy - 10) ** 2) / 30.0),
                      np.exp(-((xx - 17) ** 2 + (yy - 10) ** 2) / 30.0))
    value = np.clip(blob * 1.1, 0, 1)
    p[..., 0] = 1 - value
    p[..., 1] = value
    assert (value[10, 8:18] >= 0.5).all()  # one connected blob at the threshold
    assert len(boxes_from_probabilities(p)) == 1  # the peak split is off by default
    boxes = sorted(boxes_from_probabilities(p, BoxRules(peak_dip=0.3)), key=lambda b: b.x0)
    assert len(boxes) == 2
    assert boxes[0].x1 <= boxes[1].x0 + 1
    assert abs((boxes[0].x0 + boxes[0].x1) / 2 - 8.5) <= 1.5
    assert abs((boxes[1].x0 + boxes[1].x1) / 2 - 17.5) <= 1.5


def test_a_speckled_person_is_one_box_after_closing():
    p = _mask(40, 30)
    for r0 in (5, 10, 15, 20):  # a standing person rendered as a column of fragments, 2 px gaps
        _paint(p, r0, r0 + 3, 12, 16, cls=0, value=0.8)
    (b,) = boxes_from_probabilities(p)  # default close_px=2 joins gaps up to 4 px
    assert (b.x0, b.y0, b.x1, b.y1) == (12, 5, 16, 23)
    assert len(boxes_from_probabilities(p, BoxRules(close_px=0))) == 4
    q = _mask(40, 30)
    _paint(q, 5, 20, 5, 9, cls=0)
    _paint(q, 5, 20, 15, 19, cls=0)  # 6 px apart: stays two people
    assert len(boxes_from_probabilities(q)) == 2


def test_a_plateau_person_is_not_split():
    p = _mask(30, 30)
    _paint(p, 5, 25, 10, 16, cls=0, value=0.97)
    p[8, 12, :] = [0.0, 1.0, 0, 0]  # a noisy local max inside the plateau
    assert len(boxes_from_probabilities(p)) == 1


def test_nan_and_out_of_range_probabilities_are_tolerated():
    p = _mask(10, 10)
    p[0, 0] = np.nan
    p[5, 5] = [-1.0, 2.0, 0, 0]
    assert boxes_from_probabilities(p) == []  # single pixels, below the minimum area
    with pytest.raises(ValueError, match="channel 0 background"):
        boxes_from_probabilities(np.zeros((4, 4)))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 50), st.integers(0, 50), st.integers(2, 12), st.integers(2, 12),
                          st.integers(0, 2)), min_size=0, max_size=6))
def test_instance_boxes_match_their_pixels(rects):
    ids = np.zeros((64, 64), np.uint16)
    classes = {}
    for k, (r, c, h, w, cls) in enumerate(rects, start=1):
        ids[r:r + h, c:c + w] = k
        classes[k] = cls
    boxes = boxes_from_instances(ids, classes, BoxRules(min_area_px=1))
    expected = set()
    for k, cls in classes.items():
        rows, cols = np.nonzero(ids == k)
        if len(rows):
            expected.add((cls, cols.min(), rows.min(), cols.max() + 1, rows.max() + 1, len(rows)))
    assert {(b.class_id, b.x0, b.y0, b.x1, b.y1, b.area_px) for b in boxes} == expected


def test_agrees_with_simulator_boxes_on_a_hard_instance_map():
    from sim.world import make_world
    from telemetry.camera import Camera
    from telemetry.frames import orbit_pose

    world = make_world(seed=6, texture_size=512, texel_m=0.05)
    result = world.render(Camera.from_fov(128, 96, 70.0), orbit_pose(20.0, 15.0, -55.0, 30.0))
    boxes = boxes_from_instances(result.instance_ids, result.classes)
    truth = {(b.class_id, b.x0, b.y0, b.x1, b.y1) for b in result.boxes}
    assert {(b.class_id, b.x0, b.y0, b.x1, b.y1) for b in boxes} == truth

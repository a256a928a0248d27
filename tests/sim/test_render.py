"""The simulated world's renderer: determinism, geometry of labels, hard views."""

import numpy as np
import pytest

from sim.people import KNEELING, PRONE, STANDING, Clothing, Person
from sim.world import make_world
from telemetry.camera import Camera
from telemetry.frames import look_at, orbit_pose

GREY = (0.3, 0.3, 0.3)
CLOTHES = Clothing(GREY, (0.05, 0.05, 0.1), (0.6, 0.4, 0.3), (0.02, 0.02, 0.02), (0.03,) * 3)


def _lone_person_world(class_id, yaw=0.3):
    world = make_world(seed=5, n_people=0, n_structures=0, n_trees=0, texture_size=512,
                       texel_m=0.05)
    world.people = [Person(1, class_id, (0.0, 0.0), yaw, 1.75, CLOTHES)]
    return world


def test_same_seed_gives_identical_pixels(small_camera):
    T = orbit_pose(15.0, 20.0, -50.0, 40.0)
    a = make_world(seed=11, texture_size=512, texel_m=0.05).render(small_camera, T)
    b = make_world(seed=11, texture_size=512, texel_m=0.05).render(small_camera, T)
    c = make_world(seed=12, texture_size=512, texel_m=0.05).render(small_camera, T)
    assert np.array_equal(a.rgb, b.rgb)
    assert np.array_equal(a.instance_ids, b.instance_ids)
    assert a.boxes == b.boxes
    assert not np.array_equal(a.rgb, c.rgb)


def test_projected_person_centre_lies_in_its_box():
    world = make_world(seed=2, n_structures=0, n_trees=0, texture_size=512, texel_m=0.05)
    camera = Camera.from_fov(128, 96, 70.0)
    T = orbit_pose(15.0, 12.0, -60.0, 0.0)
    result = world.render(camera, T)
    assert len(result.boxes) >= 3
    by_instance = {p.instance: p for p in world.people}
    inside = [b for b in result.boxes if b.x0 > 0 and b.y0 > 0 and b.x1 < 128 and b.y1 < 96]
    assert len(inside) >= 3
    for box in inside:  # a person cut by the image border may have its centre outside
        prims = by_instance[box.instance].primitives(0.0)
        lo = np.min([p.aabb()[0] for p in prims], axis=0)
        hi = np.max([p.aabb()[1] for p in prims], axis=0)
        uv, in_front = camera.project_world(0.5 * (lo + hi), T)
        assert in_front.all()
        u, v = uv[0]
        assert box.x0 - 0.5 <= u <= box.x1 + 0.5 and box.y0 - 0.5 <= v <= box.y1 + 0.5, (box, uv)


@pytest.mark.parametrize("class_id", [STANDING, KNEELING, PRONE])
def test_box_size_scales_with_inverse_altitude(class_id):
    """15 m vs 50 m nadir: box extent ratio matches the ground-sample-distance ratio within 15 %."""
    world = _lone_person_world(class_id)
    camera = Camera.from_fov(128, 128, 16.0)
    sizes = {}
    for alt in (15.0, 50.0):
        T = look_at([0.0, 0.0, alt], [0.0, 0.0, 0.0])
        (box,) = world.render(camera, T).boxes
        sizes[alt] = max(box.width, box.height)
    # The top of the person is nearer than the ground: compare at the person's mid height.
    mid = {STANDING: 0.9, KNEELING: 0.5, PRONE: 0.2}[class_id]
    predicted = (50.0 - mid) / (15.0 - mid)
    assert sizes[15.0] / sizes[50.0] == pytest.approx(predicted, rel=0.15)


def test_person_heights_match_their_pose():
    for class_id, (lo_m, hi_m) in {STANDING: (1.6, 1.85), KNEELING: (0.9, 1.15),
                                   PRONE: (0.3, 0.45)}.items():
        prims = _lone_person_world(class_id).people[0].primitives(0.0)
        top = max(p.aabb()[1][2] for p in prims)
        assert lo_m <= top <= hi_m, (class_id, top)
    prims = _lone_person_world(PRONE, yaw=0.0).people[0].primitives(0.0)
    length = max(p.aabb()[1][0] for p in prims) - min(p.aabb()[0][0] for p in prims)
    assert 1.6 <= length <= 2.0


@pytest.mark.parametrize("pitch", [-90.0, -89.999, -0.5, 0.0, 10.0])
def test_nadir_and_grazing_views_render_finite(small_world, small_camera, pitch):
    T = orbit_pose(30.0, 20.0, pitch, 15.0)
    result = small_world.render(small_camera, T, supersample=2)
    assert result.rgb.shape == (96, 128, 3)
    assert result.rgb.std() > 1.0  # not a blank frame
    for b in result.boxes:
        assert all(np.isfinite([b.x0, b.y0, b.x1, b.y1]))
        assert 0 <= b.x0 < b.x1 <= 128 and 0 <= b.y0 < b.y1 <= 96


def test_empty_scene_has_no_labels(small_camera):
    world = make_world(seed=1, n_people=0, texture_size=512, texel_m=0.05)
    result = world.render(small_camera, orbit_pose(15.0, 20.0, -45.0))
    assert result.boxes == []
    assert result.yolo_labels() == ""
    assert not result.instance_ids.any()


def test_tiny_people_below_four_pixels_are_not_labelled():
    world = _lone_person_world(PRONE)
    camera = Camera.from_fov(64, 64, 60.0)
    result = world.render(camera, look_at([0.0, 0.0, 400.0], [0.0, 0.0, 0.0]))
    assert result.boxes == []


def test_fully_occluded_person_is_not_labelled():
    from sim.primitives import box

    world = _lone_person_world(STANDING)
    world.scenery.append(box([0.0, 0.0, 4.0], [3.0, 3.0, 0.2], np.eye(3), GREY))  # a roof
    camera = Camera.from_fov(96, 96, 60.0)
    result = world.render(camera, look_at([0.0, 0.0, 20.0], [0.0, 0.0, 0.0]))
    assert result.boxes == []


def test_walking_people_move_and_labels_follow(small_camera):
    world = make_world(seed=4, dynamic=True, n_structures=0, n_trees=0, texture_size=512,
                       texel_m=0.05)
    walkers = [p for p in world.people if p.path is not None]
    assert walkers
    p0 = world.person_positions(0.0)
    p1 = world.person_positions(2.0)
    moved = np.linalg.norm(p1 - p0, axis=1)
    for i, person in enumerate(world.people):
        if person.path is None:
            assert moved[i] == 0.0
        else:
            assert 1.0 < moved[i] < 4.0  # 1-1.6 m/s for 2 s, along a curve
    T = look_at([0.0, 0.0, 40.0], [0.0, 0.0, 0.0])
    a = world.render(small_camera, T, t=0.0)
    b = world.render(small_camera, T, t=2.0)
    assert not np.array_equal(a.instance_ids, b.instance_ids)


def test_yolo_labels_are_normalised(small_world, small_camera):
    result = small_world.render(small_camera, orbit_pose(15.0, 12.0, -60.0))
    for line in result.yolo_labels().splitlines():
        c, *xywh = line.split()
        assert int(c) in (0, 1, 2)
        assert all(0.0 <= float(v) <= 1.0 for v in xywh)


def test_bad_pose_is_rejected(small_world, small_camera):
    with pytest.raises(ValueError):
        small_world.render(small_camera, np.full((4, 4), np.nan))

"""Label transfer: real labels vote the classes of synthetic boxes by geometry."""

import numpy as np
import pytest

from fields.data import parse_labels
from fields.label_transfer import LabelledFrames
from fields.mask_boxes import MaskBox
from fields.synthesis import SynthOptions, match_boxes, synthesize
from sim.views import SimViewRenderer
from sim.world import make_world
from telemetry.camera import Camera
from telemetry.frames import orbit_pose
from telemetry.posesfile import Origin, PoseEntry

CAM = Camera(width=100, height=100, fx=100.0, fy=100.0, cx=50.0, cy=50.0)


def _nadir(x=0.0, y=0.0, z=10.0) -> np.ndarray:
    """cam_from_world of a camera at (x, y, z) ENU looking straight down (image x = east, y = south)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    T[:3, 3] = -T[:3, :3] @ np.array([x, y, z])
    return T


def test_votes_count_each_frame_box_that_sees_the_point():
    # the origin projects to the image centre (50, 50) of both nadir frames
    frames = LabelledFrames(CAM, [_nadir(), _nadir(z=20.0)],
                            [[(2, 40, 40, 60, 60)], [(2, 45, 45, 55, 55), (0, 0, 0, 10, 10)]], 3)
    assert frames.class_votes(np.zeros((1, 3))).tolist() == [0.0, 0.0, 2.0]


def test_a_point_inside_overlapping_boxes_splits_its_vote():
    frames = LabelledFrames(CAM, [_nadir(), _nadir()],
                            [[(0, 40, 40, 60, 60), (1, 45, 45, 70, 70)], [(1, 40, 40, 60, 60)]], 3)
    assert frames.class_votes(np.zeros((1, 3))).tolist() == [0.5, 1.5, 0.0]


def test_points_behind_the_camera_nan_or_outside_every_box_do_not_vote():
    frames = LabelledFrames(CAM, [_nadir()], [[(1, 40, 40, 60, 60)]], 2)
    pts = np.array([[0.0, 0.0, 30.0], [np.nan, 0.0, 0.0], [4.0, 4.0, 0.0]])  # above the camera, NaN, off-box
    assert frames.class_votes(pts).sum() == 0.0
    assert frames.class_votes(np.empty((0, 3))).sum() == 0.0
    assert LabelledFrames(CAM, [], [], 2).class_votes(np.zeros((1, 3))).sum() == 0.0


def test_only_frames_close_in_time_vote_in_a_dynamic_scene():
    frames = LabelledFrames(CAM, [_nadir(), _nadir()], [[(0, 40, 40, 60, 60)], [(1, 40, 40, 60, 60)]], 2,
                            times_us=[0, 1_000_000])
    assert frames.class_votes(np.zeros((1, 3)), t_unix_us=900_000, max_dt_us=200_000).tolist() == [0.0, 1.0]
    assert frames.class_votes(np.zeros((1, 3))).tolist() == [1.0, 1.0]  # no window: all frames


def test_relabel_lifts_box_pixels_by_depth_and_keeps_unseen_boxes():
    frames = LabelledFrames(CAM, [_nadir()], [[(2, 40, 40, 60, 60)]], 3)
    fg = np.zeros((100, 100))
    fg[45:55, 45:55] = 0.9  # a blob at the image centre, seen by the labelled frame
    fg[5:9, 5:9] = 0.8  # a blob no label covers
    depth = np.full((100, 100), 10.0)  # the ground plane z = 0 under a camera 10 m up
    boxes = [MaskBox(0, 45, 45, 55, 55, 100, 0.9), MaskBox(1, 5, 5, 9, 9, 16, 0.8)]
    out, unvoted = frames.relabel(boxes, fg, depth, CAM, _nadir())
    assert [b.class_id for b in out] == [2, 1] and unvoted == 1
    assert [(b.x0, b.y0, b.x1, b.y1) for b in out] == [(b.x0, b.y0, b.x1, b.y1) for b in boxes]
    assert frames.relabel([], fg, depth, CAM, _nadir()) == ([], 0)


def test_relabel_with_nan_depth_keeps_the_mask_class():
    frames = LabelledFrames(CAM, [_nadir()], [[(2, 40, 40, 60, 60)]], 3)
    fg = np.zeros((100, 100))
    fg[45:55, 45:55] = 0.9
    out, unvoted = frames.relabel([MaskBox(0, 45, 45, 55, 55, 100, 0.9)], fg, np.full((100, 100), np.nan),
                                  CAM, _nadir())
    assert out[0].class_id == 0 and unvoted == 1


class _OneClassSim:
    """The simulator as a field whose mask names every person "prone" (class 2), with the depth of
    the plane 0.5 m above the ground: the failure of an undertrained class head, exact geometry aside."""

    def __init__(self, world):
        self.sim = SimViewRenderer(world, supersample=2)

    def render_view_depth(self, camera, cam_from_world, t_unix_us=None):
        rgb, prob = self.sim.render_view(camera, cam_from_world, t_unix_us)
        fg = 1.0 - prob[..., 0]
        wrong = np.zeros_like(prob)
        wrong[..., 0], wrong[..., 3] = 1.0 - fg, fg
        origin, dirs = camera.rays_world(cam_from_world, camera.pixel_grid())
        depth = (0.5 - origin[2]) / dirs[..., 2]
        return rgb, wrong, depth

    def render_view(self, camera, cam_from_world, t_unix_us=None):
        return self.render_view_depth(camera, cam_from_world, t_unix_us)[:2]


def test_label_votes_fix_the_classes_of_a_one_class_mask(tmp_path):
    world = make_world(seed=3, n_people=10, people_radius_m=7.0, n_structures=0, n_trees=0,
                       texture_size=512, texel_m=0.05)
    cam = Camera.from_fov(128, 96, 60.0)
    sim = SimViewRenderer(world, supersample=2)
    real = [orbit_pose(15.0, 18.0, -40.0, az) for az in range(0, 360, 30)]
    labels = [[(b.class_id, b.x0, b.y0, b.x1, b.y1) for b in sim.render_full(cam, T).boxes] for T in real]
    frames = LabelledFrames(cam, real, labels, 3)
    novel = [orbit_pose(22.0, 4.0, -80.0, az) for az in (20.0, 140.0, 260.0)]
    entries = [PoseEntry(None, None, T, "novel") for T in novel]
    report = synthesize(_OneClassSim(world), cam, Origin(0.0, 0.0, 0.0), entries, tmp_path,
                        list(world.class_names), SynthOptions(), labels_from=frames)
    assert report.class_source == "labels" and report.relabelled_boxes > 0
    any_class = same_class = prone = 0
    true_classes = set()
    for k, T in enumerate(novel):
        truth = sim.render_full(cam, T).boxes
        true_classes |= {b.class_id for b in truth}
        lines = (tmp_path / "labels" / f"synth_{k:05d}.txt").read_text().splitlines()
        pred = [MaskBox(c, x0, y0, x1, y1, 0, 1.0) for c, x0, y0, x1, y1 in parse_labels(
            "\n".join(lines), cam.width, cam.height, 3)]
        any_class += match_boxes(pred, truth, 0.5, 4, same_class=False).true_positives
        same_class += match_boxes(pred, truth, 0.5, 4).true_positives
        prone += match_boxes([MaskBox(2, b.x0, b.y0, b.x1, b.y1, 0, 1.0) for b in pred], truth, 0.5, 4).true_positives
    assert true_classes == {0, 1, 2} and any_class >= 10
    assert prone <= 0.6 * any_class  # the mask's own classes would be wrong for most
    assert same_class >= 0.9 * any_class
    with pytest.raises(TypeError, match="render_view_depth"):
        synthesize(sim, cam, Origin(0.0, 0.0, 0.0), entries, tmp_path / "x", list(world.class_names),
                   labels_from=frames)


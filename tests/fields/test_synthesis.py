"""Synthesis against the simulator as a perfect field: files, names, labels, box agreement."""

import json

import cv2
import numpy as np

from fields.mask_boxes import BoxRules
from fields.novel_poses import NovelPoseOptions, static_novel_poses
from fields.synthesis import BoxMatch, SynthOptions, match_boxes, synthesize
from sim.views import SimViewRenderer, one_hot_classes
from sim.world import make_world
from telemetry.camera import Camera
from telemetry.frames import orbit_pose
from telemetry.posesfile import Origin, PosesFile


def test_one_hot_classes():
    ids = np.array([[0, 1], [2, 2]], np.uint16)
    prob = one_hot_classes(ids, {1: 2, 2: 0}, 3)
    assert prob.shape == (2, 2, 4)
    assert prob.argmax(-1).tolist() == [[0, 3], [1, 1]]


def test_synthesize_writes_a_consistent_labelled_set(tmp_path):
    world = make_world(seed=8, n_structures=1, n_trees=1, texture_size=512, texel_m=0.05)
    cam = Camera.from_fov(128, 96, 50.0)
    real = [orbit_pose(15.0, 20.0, -37.0, az) for az in range(0, 360, 30)]
    novel = static_novel_poses(cam, real, NovelPoseOptions(altitudes_m=(16.0, 20.0), count=4, seed=2))
    kept = [p.entry() for p in novel if p.kept]
    renderer = SimViewRenderer(world, supersample=2)
    names = list(world.class_names)
    calls = []
    report = synthesize(renderer, cam, Origin(42.0, -83.0, 200.0), kept, tmp_path, names,
                        SynthOptions(rules=BoxRules(min_area_px=4)),
                        progress=lambda i, n: calls.append((i, n)))
    assert calls[-1] == (4, 4)
    assert report.images == 4 and report.images_per_minute > 0
    poses = PosesFile.load(tmp_path / "poses.json")
    stems = sorted(p.stem for p in (tmp_path / "images").glob("*.jpg"))
    assert [e.frame.rsplit(".", 1)[0] for e in poses.frames] == stems
    assert sorted(p.stem for p in (tmp_path / "labels").glob("*.txt")) == stems
    assert all(e.source == "novel" and "altitude_m" in e.extra for e in poses.frames)
    assert (tmp_path / "contact_sheet.png").is_file()
    assert json.loads((tmp_path / "report.json").read_text())["boxes"] == report.boxes

    total = BoxMatch(0, 0, 0, [])
    for e in poses.frames:
        truth = renderer.render_full(cam, e.cam_from_world).boxes
        lines = (tmp_path / "labels" / (e.frame[:-4] + ".txt")).read_text().splitlines()
        pred = [_box_from_yolo(line, 128, 96) for line in lines]
        total = total + match_boxes(pred, truth, min_truth_height_px=6)
        img = cv2.imread(str(tmp_path / "images" / e.frame))
        assert img.shape == (96, 128, 3)
    assert total.true_positives >= 3
    assert total.recall >= 0.95 and total.precision >= 0.9 and total.mean_iou >= 0.9


class _B:
    def __init__(self, c, x0, y0, x1, y1):
        self.class_id, self.x0, self.y0, self.x1, self.y1 = c, x0, y0, x1, y1


def _box_from_yolo(line, w, h):
    c, cx, cy, bw, bh = line.split()
    cx, cy, bw, bh = float(cx) * w, float(cy) * h, float(bw) * w, float(bh) * h
    return _B(int(c), cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2)


def test_match_boxes_counts_and_ignores_small_truth():
    truth = [_B(0, 0, 0, 10, 20), _B(1, 50, 50, 53, 53)]  # second is 3 px tall
    pred = [_B(0, 1, 1, 10, 20), _B(1, 50, 50, 53, 53), _B(0, 80, 80, 90, 90)]
    m = match_boxes(pred, truth, min_truth_height_px=6)
    assert (m.true_positives, m.false_positives, m.false_negatives) == (1, 1, 0)
    assert m.recall == 1.0 and m.precision == 0.5
    assert match_boxes([], truth).recall == 0.0
    assert match_boxes([_B(1, 0, 0, 10, 20)], truth[:1]).true_positives == 0  # wrong class

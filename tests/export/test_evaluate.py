"""mAP through pycocotools on cases with known answers."""

import numpy as np
import pytest

from export.dataset import label_path, load_data_config, load_rgb, read_labels
from export.evaluate import coco_map, evaluate

NAMES = {0: "standing", 1: "kneeling", 2: "prone"}


def gt_predictor(images):
    """Predicts exactly the labelled boxes (score 0.9) of each image, in order."""
    it = iter(images)

    def predict(img):
        p = next(it)
        h, w = img.shape[:2]
        lab = read_labels(label_path(p), 3)
        out = np.zeros((len(lab), 6), np.float32)
        out[:, 0], out[:, 2] = (lab[:, 1] - lab[:, 3] / 2) * w, (lab[:, 1] + lab[:, 3] / 2) * w
        out[:, 1], out[:, 3] = (lab[:, 2] - lab[:, 4] / 2) * h, (lab[:, 2] + lab[:, 4] / 2) * h
        out[:, 4], out[:, 5] = 0.9, lab[:, 0]
        return out

    return predict


def test_perfect_predictions_give_map_one(tiny_data):
    cfg = load_data_config(tiny_data)
    res = evaluate(gt_predictor(cfg.val), cfg.val, cfg.names)
    assert res.map50 == pytest.approx(1.0) and res.map50_95 == pytest.approx(1.0)
    assert res.images == 6 and res.instances > 0
    for r in res.per_class.values():
        assert r["instances"] == 0 or r["map50"] == pytest.approx(1.0)
    assert load_rgb(cfg.val[0]).shape == (64, 96, 3)


def test_half_found_gives_51_of_101_points():
    gts = [np.array([[0, 10, 10, 30, 30], [0, 50, 50, 70, 70]], np.float32)]
    preds = [np.array([[10, 10, 30, 30, 0.9, 0]], np.float32)]
    res = coco_map(gts, preds, [(100, 100)], {0: "standing"})
    assert res.map50 == pytest.approx(51 / 101) and res.map50_95 == pytest.approx(51 / 101)


def test_false_positive_ranked_first_halves_precision():
    gts = [np.array([[0, 10, 10, 30, 30]], np.float32)]
    preds = [np.array([[60, 60, 80, 80, 0.9, 0], [10, 10, 30, 30, 0.5, 0]], np.float32)]
    res = coco_map(gts, preds, [(100, 100)], {0: "a"})
    assert res.map50 == pytest.approx(0.5)


def test_loose_box_counts_at_iou50_only():
    gts = [np.array([[0, 0, 0, 20, 20]], np.float32)]
    preds = [np.array([[0, 0, 20, 28, 0.9, 0]], np.float32)]  # IoU 400/560 = 0.714
    res = coco_map(gts, preds, [(100, 100)], {0: "a"})
    assert res.map50 == pytest.approx(1.0)
    assert res.map50_95 == pytest.approx(0.5)  # hits at 0.50..0.70 (5 of 10 thresholds)


def test_wrong_class_and_classes_without_ground_truth():
    gts = [np.array([[0, 10, 10, 30, 30]], np.float32), np.zeros((0, 5), np.float32)]
    preds = [np.array([[10, 10, 30, 30, 0.9, 1]], np.float32), np.zeros((0, 6), np.float32)]
    res = coco_map(gts, preds, [(100, 100)] * 2, NAMES)
    assert res.map50 == 0.0
    assert res.per_class["kneeling"]["map50"] is None and res.per_class["standing"]["map50"] == 0.0


def test_no_predictions_at_all():
    gts = [np.array([[2, 10, 10, 30, 30]], np.float32)]
    res = coco_map(gts, [np.zeros((0, 6), np.float32)], [(100, 100)], NAMES)
    assert res.map50 == 0.0 and res.per_class["prone"]["map50"] == 0.0
    assert "prone" in res.table()

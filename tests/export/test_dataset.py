"""YOLO datasets: tolerant reading (missing labels = background, bad lines skipped), augmentation."""

import numpy as np
import pytest

from export import dataset as ds_mod
from export.dataset import AugmentConfig, DatasetError, YoloDataset, collate, label_path, load_data_config

read_labels = ds_mod.read_labels


def test_data_yaml_lists_splits_and_names(tiny_data):
    cfg = load_data_config(tiny_data)
    assert cfg.names == {0: "red", 1: "green", 2: "blue"} and cfg.nc == 3
    assert len(cfg.train) == len(cfg.val) == 6


def test_data_yaml_variants(tmp_path, tiny_data):
    root = tiny_data.parent
    lst = tmp_path / "train.txt"
    lst.write_text("\n".join(str(p) for p in sorted((root / "train" / "images").iterdir())[:3]) + "\n\n")
    y = tmp_path / "d.yaml"
    y.write_text(f"path: {root}\ntrain: {lst}\nval: [val/images]\nnames: [a, b, c]\n")
    cfg = load_data_config(y)
    assert len(cfg.train) == 3 and len(cfg.val) == 6 and cfg.names[2] == "c"
    y.write_text("train: nowhere/images\nnc: 2\n")
    with pytest.raises(DatasetError, match="not found"):
        load_data_config(y)
    y.write_text("train: [\n")
    with pytest.raises(DatasetError, match="YAML"):
        load_data_config(y)
    with pytest.raises(DatasetError, match="not found"):
        load_data_config(tmp_path / "missing.yaml")
    y.write_text(f"path: {root}\ntrain: train/images\n")
    with pytest.raises(DatasetError, match="names"):
        load_data_config(y)


def test_label_path_uses_last_images_component(tmp_path):
    assert label_path(tmp_path / "images" / "x" / "images" / "a.png") == tmp_path / "images" / "x" / "labels" / "a.txt"
    assert label_path(tmp_path / "frames" / "a.jpg") == tmp_path / "frames" / "a.txt"


def test_missing_label_file_is_background(tmp_path):
    assert read_labels(tmp_path / "none.txt", 3).shape == (0, 5)


def test_malformed_lines_are_skipped_and_boxes_clipped(tmp_path):
    f = tmp_path / "a.txt"
    f.write_text("0 0.5 0.5 0.2 0.2\nbad line\n7 0.5 0.5 0.1 0.1\n1 0.5 nan 0.1 0.1\n\n"
                 "2 0.98 0.5 0.1 0.2\n1 0.5 0.5 0 0.1\n1.5 0.5 0.5 0.1 0.1\n0 0.5 0.5\n")
    lab = read_labels(f, 3)
    assert lab[:, 0].tolist() == [0, 2]
    np.testing.assert_allclose(lab[1], [2, 0.965, 0.5, 0.07, 0.2], atol=1e-6)  # clipped at the right border


@pytest.mark.parametrize("mosaic", [0.0, 1.0])
def test_augmented_samples_keep_boxes_inside(tiny_data, mosaic):
    cfg = load_data_config(tiny_data)
    ds = YoloDataset(cfg.train, 3, imgsz=64, augment=AugmentConfig(mosaic=mosaic), seed=1)
    n_boxes = 0
    for i in range(len(ds)):
        img, boxes = ds[i]
        assert img.shape == (64, 64, 3) and img.dtype == np.uint8
        assert (boxes[:, 1:] >= 0).all() and (boxes[:, 1:] <= 64).all()
        assert (boxes[:, 3] > boxes[:, 1]).all() and (boxes[:, 4] > boxes[:, 2]).all()
        n_boxes += len(boxes)
    assert n_boxes > 0
    imgs, targets = collate([ds[0], ds[1]])
    assert imgs.shape == (2, 3, 64, 64) and imgs.max() <= 1.0 and targets.shape[1] == 6


def test_plain_letterboxed_sample_maps_labels_exactly(tiny_data):
    cfg = load_data_config(tiny_data)
    ds = YoloDataset(cfg.train, 3, imgsz=96)  # images are 96x64 → letterbox pads 16 px top and bottom
    img, boxes = ds[1]
    lab = ds.labels[1]
    np.testing.assert_allclose(boxes[:, 1], (lab[:, 1] - lab[:, 3] / 2) * 96, atol=1e-3)
    np.testing.assert_allclose(boxes[:, 2], (lab[:, 2] - lab[:, 4] / 2) * 64 + 16, atol=1e-3)


def test_empty_split_is_an_error():
    with pytest.raises(DatasetError):
        YoloDataset([], 3)

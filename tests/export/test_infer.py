"""In-flight inference: torch-free, letterbox, NMS, edge cases, foreign class names, CLI."""

import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from export.infer import Detector, ModelError, letterbox, nms, parse_names, postprocess

REPO = Path(__file__).resolve().parents[2]


def test_inference_imports_no_torch(onnx_model, tmp_path):
    path, _ = onnx_model
    code = (
        "import sys, numpy as np\n"
        "from export.infer import Detector\n"
        f"d = Detector({str(path)!r}, threads=1)\n"
        "d.detect(np.zeros((50, 70, 3), np.uint8), conf=0.0)\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "print('ok', len(d.names))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok", "3"]


def test_detector_reads_names_and_size_from_model(onnx_model):
    path, _ = onnx_model
    d = Detector(path)
    assert d.names == {0: "standing", 1: "kneeling", 2: "prone"}
    assert d.imgsz == (64, 96) and d.nc == 3
    with pytest.raises(ModelError, match="fixed"):
        Detector(path, imgsz=640)


@pytest.mark.parametrize("shape", [(64, 96, 3), (200, 50, 3), (31, 7, 3), (64, 96), (64, 96, 1), (40, 40, 4)],
                         ids=["same", "tall", "tiny", "grey", "grey1", "rgba"])
def test_any_image_shape_runs_and_boxes_stay_inside(onnx_model, shape):
    path, _ = onnx_model
    d = Detector(path, threads=1)
    img = np.random.default_rng(0).integers(0, 255, shape, dtype=np.uint8)
    det = d.detect_array(img, conf=0.0, iou=0.5)
    assert det.shape[1] == 6 and len(det) > 0
    h, w = shape[:2]
    assert (det[:, [0, 2]] >= 0).all() and (det[:, [0, 2]] <= w).all()
    assert (det[:, [1, 3]] >= 0).all() and (det[:, [1, 3]] <= h).all()


def test_blank_image_gives_no_detections_at_default_conf(onnx_model):
    path, _ = onnx_model
    assert Detector(path).detect(np.full((64, 96, 3), 114, np.uint8)) == []


def test_rejects_float_image(onnx_model):
    with pytest.raises(ValueError, match="uint8"):
        Detector(onnx_model[0]).detect(np.zeros((8, 8, 3), np.float32))


@pytest.mark.parametrize("content", [b"", b"not an onnx model at all", b"\x08\x07" + bytes(range(200))],
                         ids=["empty", "text", "garbage"])
def test_corrupt_model_file_gives_clear_error(tmp_path, content):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(content)
    with pytest.raises(ModelError, match="cannot load ONNX model"):
        Detector(bad)


def test_truncated_model_file_gives_clear_error(onnx_model, tmp_path):
    bad = tmp_path / "cut.onnx"
    bad.write_bytes(onnx_model[0].read_bytes()[:20000])
    with pytest.raises(ModelError):
        Detector(bad)


def test_missing_model_file(tmp_path):
    with pytest.raises(ModelError, match="not found"):
        Detector(tmp_path / "nope.onnx")


@settings(max_examples=50, deadline=None)
@given(h=st.integers(1, 300), w=st.integers(1, 300), th=st.sampled_from([32, 64, 96]), tw=st.sampled_from([32, 96]))
def test_letterbox_maps_image_corners_inside_the_input(h, w, th, tw):
    out, lb = letterbox(np.zeros((h, w, 3), np.uint8), (th, tw))
    assert out.shape == (th, tw, 3)
    x1, y1 = w * lb.scale + lb.pad_x, h * lb.scale + lb.pad_y
    assert lb.pad_x >= 0 and lb.pad_y >= 0 and x1 <= tw + 0.5 and y1 <= th + 0.5
    # content touches both sides of at least one axis
    assert min(abs(x1 + lb.pad_x - tw), abs(y1 + lb.pad_y - th)) <= 1.0


def test_nms_is_class_aware_and_suppresses_overlaps():
    # two overlapping boxes of class 0, one identical box of class 1, one far box of class 0
    out = np.zeros((4 + 2, 4), np.float32)
    out[:4] = np.array([[10, 10, 8, 8], [11, 10, 8, 8], [10, 10, 8, 8], [50, 50, 4, 4]], np.float32).T
    out[4] = [0.9, 0.8, 0.0, 0.7]
    out[5] = [0.0, 0.0, 0.85, 0.0]
    det = postprocess(out, conf=0.25, iou=0.5)
    assert sorted(det[:, 5].tolist()) == [0, 0, 1]
    assert np.allclose(sorted(det[:, 4]), [0.7, 0.85, 0.9])
    # multi-label keeps every class above conf per box
    out[5, 3] = 0.6  # the far box is also class 1
    assert len(postprocess(out, conf=0.25, iou=0.5, multi_label=True)) == 4


def test_nms_reference_against_brute_force():
    rng = np.random.default_rng(0)
    xy = rng.uniform(0, 50, (60, 2))
    boxes = np.c_[xy, xy + rng.uniform(2, 20, (60, 2))]
    scores = rng.uniform(0, 1, 60)
    keep = nms(boxes, scores, 0.4)
    from export.infer import box_iou

    kept = boxes[keep]
    iou = box_iou(kept, kept)
    np.fill_diagonal(iou, 0)
    assert iou.max() <= 0.4
    # every dropped box overlaps a kept, higher-scoring box
    for i in set(range(60)) - set(keep.tolist()):
        better = keep[scores[keep] > scores[i]]
        assert (box_iou(boxes[i:i + 1], boxes[better]) > 0.4).any()


def test_no_candidates_gives_empty_array():
    assert postprocess(np.zeros((7, 10), np.float32), conf=0.5).shape == (0, 6)


def test_parse_names_variants():
    assert parse_names({"names": "{0: 'person', 1: 'car'}"}, 2) == {0: "person", 1: "car"}
    assert parse_names({"names": "['a', 'b']"}, 2) == {0: "a", 1: "b"}
    assert parse_names({}, 2) == {0: "class0", 1: "class1"}
    with pytest.raises(ModelError):
        parse_names({"names": "{0: person"}, 1)


def test_foreign_model_with_other_names_runs_through_cli(tmp_path):
    """A model in ultralytics layout with different classes (nc=2, 'person', 'car') runs unchanged."""
    import torch

    from export.onnx_export import export_onnx
    from export.yolo import YOLOv8

    torch.manual_seed(0)
    path = export_onnx(YOLOv8(nc=2, names={0: "person", 1: "car"}).eval(), tmp_path / "other.onnx", 64)
    img = tmp_path / "grey.png"
    cv2.imwrite(str(img), np.random.default_rng(0).integers(0, 255, (48, 80), dtype=np.uint8))
    out = subprocess.run([sys.executable, "-m", "agent.cli", "detect", str(path), str(img), "--conf", "0",
                          "--threads", "1", "--json"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res[0]["image"] == str(img) and res[0]["detections"]
    assert {d["name"] for d in res[0]["detections"]} <= {"person", "car"}


def test_cli_detect_corrupt_model_is_one_line_error(tmp_path):
    bad = tmp_path / "bad.onnx"
    bad.write_bytes(b"garbage")
    out = subprocess.run([sys.executable, "-m", "agent.cli", "detect", str(bad), str(bad)], cwd=REPO,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0 and "cannot load ONNX model" in out.stderr


def test_timings_split_the_call(onnx_model):
    parts: dict = {}
    Detector(onnx_model[0]).detect_array(np.zeros((64, 96, 3), np.uint8), timings=parts)
    assert set(parts) == {"pre", "run", "post"} and all(v >= 0 for v in parts.values())
    assert parts["run"] > 0

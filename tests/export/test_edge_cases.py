"""Decode edge cases through a real onnxruntime session of a hand-built graph in ultralytics layout.

The graph ignores its input and emits fixed candidates, so the expected boxes in the original image
are known exactly: whole-content boxes, boxes crossing the image border, 1-pixel boxes, no boxes.
"""

import numpy as np
import onnx
import pytest
from onnx import TensorProto, helper

from export.infer import Detector


def constant_model(path, candidates: np.ndarray, names: dict, size=(64, 64)):
    """ONNX model: images [1,3,H,W] → output0 = candidates [1,4+nc,N] (+ 0·mean(images))."""
    h, w = size
    const = helper.make_tensor("C", TensorProto.FLOAT, candidates.shape, candidates.astype(np.float32).ravel())
    zero = helper.make_tensor("Z", TensorProto.FLOAT, [], [0.0])
    nodes = [helper.make_node("ReduceMean", ["images"], ["m"], keepdims=0),
             helper.make_node("Mul", ["m", "Z"], ["z"]),
             helper.make_node("Add", ["C", "z"], ["output0"])]
    graph = helper.make_graph(nodes, "const", [helper.make_tensor_value_info("images", TensorProto.FLOAT,
                                                                             [1, 3, h, w])],
                              [helper.make_tensor_value_info("output0", TensorProto.FLOAT, list(candidates.shape))],
                              initializer=[const, zero])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    for k, v in {"names": str(names), "stride": "32", "imgsz": str([h, w]), "task": "detect"}.items():
        p = model.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(model, str(path))
    return path


def candidates(rows):
    """rows of (cx, cy, w, h, score0, score1) in network-input pixels → [1, 6, N]."""
    return np.asarray(rows, np.float32).T[None]


# original image 100 wide x 50 high into 64x64: scale 0.64, pad_x 0, pad_y 16
IMG = np.zeros((50, 100, 3), np.uint8)


def test_whole_content_box_maps_to_the_full_image(tmp_path):
    m = constant_model(tmp_path / "m.onnx", candidates([(32, 32, 64, 32, 0.9, 0.1)]), {0: "a", 1: "b"})
    (d,) = Detector(m).detect(IMG)
    assert (d.name, d.class_id) == ("a", 0)
    np.testing.assert_allclose([d.x0, d.y0, d.x1, d.y1], [0, 0, 100, 50], atol=1e-3)


def test_boxes_crossing_the_border_are_clipped(tmp_path):
    rows = [(0, 20, 12.8, 6.4, 0.8, 0.0), (64, 48, 12.8, 6.4, 0.0, 0.7)]  # left edge; bottom-right corner
    m = constant_model(tmp_path / "m.onnx", candidates(rows), {0: "a", 1: "b"})
    dets = Detector(m).detect(IMG)
    boxes = {d.name: [d.x0, d.y0, d.x1, d.y1] for d in dets}
    np.testing.assert_allclose(boxes["a"], [0, 1.25, 10, 11.25], atol=1e-3)
    np.testing.assert_allclose(boxes["b"], [90, 45, 100, 50], atol=1e-3)


def test_one_pixel_boxes_survive(tmp_path):
    rows = [(10, 30, 0.64, 0.64, 0.5, 0.0), (50, 40, 0.64, 0.64, 0.0, 0.6)]
    m = constant_model(tmp_path / "m.onnx", candidates(rows), {0: "a", 1: "b"})
    dets = Detector(m).detect(IMG)
    assert len(dets) == 2
    for d in dets:
        assert d.x1 - d.x0 == pytest.approx(1.0, abs=1e-3) and d.y1 - d.y0 == pytest.approx(1.0, abs=1e-3)


def test_no_objects_gives_no_detections(tmp_path):
    m = constant_model(tmp_path / "m.onnx", candidates([(32, 32, 10, 10, 0.1, 0.2)] * 5), {0: "a", 1: "b"})
    assert Detector(m).detect(IMG) == []
    assert Detector(m).detect(IMG[:, :, 0]) == []  # grayscale


def test_grayscale_and_square_inputs_map_the_same_way(tmp_path):
    m = constant_model(tmp_path / "m.onnx", candidates([(32, 32, 64, 64, 0.9, 0.1)]), {0: "a", 1: "b"})
    (d,) = Detector(m).detect(np.zeros((30, 30), np.uint8))
    np.testing.assert_allclose([d.x0, d.y0, d.x1, d.y1], [0, 0, 30, 30], atol=1e-3)

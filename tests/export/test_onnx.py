"""ONNX export: ultralytics layout, single file, opset 17, numerically equal to torch."""

import ast

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from export.onnx_export import export_onnx
from export.yolo import YOLOv8


def test_onnx_matches_torch_on_random_input(onnx_model):
    path, model = onnx_model
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    x = torch.rand(1, 3, 64, 96, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        ref = model(x).numpy()
    out = sess.run(None, {"images": x.numpy()})[0]
    assert out.shape == ref.shape == (1, 7, 126)
    assert np.abs(out - ref).max() < 1e-3


def test_onnx_layout_and_metadata(onnx_model):
    path, _ = onnx_model
    proto = onnx.load(str(path))
    assert [o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")] == [17]
    assert [i.name for i in proto.graph.input] == ["images"]
    assert [o.name for o in proto.graph.output] == ["output0"]
    dims = [d.dim_value for d in proto.graph.input[0].type.tensor_type.shape.dim]
    assert dims == [1, 3, 64, 96]
    meta = {p.key: p.value for p in proto.metadata_props}
    for key in ("description", "author", "date", "version", "license", "docs", "stride", "task", "batch",
                "imgsz", "names", "args"):
        assert key in meta
    assert ast.literal_eval(meta["names"]) == {0: "standing", 1: "kneeling", 2: "prone"}
    assert ast.literal_eval(meta["imgsz"]) == [64, 96]
    assert meta["stride"] == "32" and meta["task"] == "detect"
    # single file: all weights inside
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in proto.graph.initializer)
    assert sorted(p.name for p in path.parent.iterdir()) == ["m.onnx"]


def test_export_rejects_size_not_multiple_of_stride(tmp_path):
    with pytest.raises(ValueError, match="multiple of 32"):
        export_onnx(YOLOv8(nc=1), tmp_path / "x.onnx", 100)
    assert not list(tmp_path.iterdir())
